"""Planning problems and planner options: validated, frozen, JSON in/out.

:class:`PlanProblem` says *what* to plan: start and goal points of the end effector [m] in
the base frame (x right, y up, z toward the user), start and end velocities [m/s] (rest by
default), optional via points [m] and an optional payload [kg] carried at the end effector.
:class:`PlanOptions` says *how*: the command limit |Tc| <= tc_max (command units, 0 < tc_max
<= 4096), the number of intervals of the transcription, the optimiser's time budget, and
which verifications and cross-checks to run. Neither knows about any solver.

Both reject bad input at construction (:class:`InvalidProblemError`, or
:class:`WorkspaceError` naming which point is outside the workspace and why, when checked
against a model with :meth:`PlanProblem.require_in_workspace`), and ``from_dict`` rejects
unknown keys with a message listing the allowed ones.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.params import ACRA2009, FalconParams
from falcon_plan.model.saturation import SaturationModel
from falcon_plan.model.workspace import require_in_workspace
from falcon_plan.planning.bound import LIMIT_KINDS, CommandBound
from falcon_plan.validation import (require_known_fields, require_number, require_vec3,
                                    require_whole_number)

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel

ZERO_MOVE_M = 1e-6
"""A rest-to-rest problem whose waypoints all lie within this of each other [m] is a
zero-length move: there is nothing to plan (the planner says so instead of solving)."""

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class PlanProblem:
    """A point-to-point motion of the end effector (base frame, SI units).

    Attributes
    ----------
    start_m, goal_m : start and goal points [m].
    start_velocity_m_s, goal_velocity_m_s : velocities at the ends [m/s]; rest by default.
    via_m : points [m] the motion must pass through, in order (at a transcription node).
    payload_kg : extra point mass at the end effector [kg] (the model's Effects.payload_kg).
    """

    start_m: Vec3
    goal_m: Vec3
    start_velocity_m_s: Vec3 = (0.0, 0.0, 0.0)
    goal_velocity_m_s: Vec3 = (0.0, 0.0, 0.0)
    via_m: tuple[Vec3, ...] = ()
    payload_kg: float = 0.0

    def __post_init__(self) -> None:
        for name in ("start_m", "goal_m", "start_velocity_m_s", "goal_velocity_m_s"):
            object.__setattr__(self, name, require_vec3(name, getattr(self, name), InvalidProblemError))
        vias = self.via_m
        if isinstance(vias, np.ndarray):
            vias = vias.tolist()
        if not isinstance(vias, (list, tuple)):
            raise InvalidProblemError(f"via_m must be a list of points, got {vias!r}")
        object.__setattr__(self, "via_m", tuple(require_vec3(f"via_m[{i}]", v, InvalidProblemError) for i, v in enumerate(vias)))
        if len(self.via_m) > 8:
            raise InvalidProblemError(f"at most 8 via points are supported, got {len(self.via_m)}")
        object.__setattr__(self, "payload_kg", require_number("payload_kg", self.payload_kg, InvalidProblemError, 0.0, 1.0))
        for name in ("start_velocity_m_s", "goal_velocity_m_s"):
            speed = float(np.linalg.norm(getattr(self, name)))
            if speed > 5.0:
                raise InvalidProblemError(f"{name} has speed {speed:.3g} m/s; at most 5 m/s is plannable")

    @property
    def waypoints_m(self) -> np.ndarray:
        """Start, via points and goal, shape (2 + n_via, 3) [m]."""
        return np.array([self.start_m, *self.via_m, self.goal_m], dtype=float)

    @property
    def is_rest_to_rest(self) -> bool:
        """True when both end velocities are zero."""
        return not any(self.start_velocity_m_s) and not any(self.goal_velocity_m_s)

    @property
    def is_zero_length(self) -> bool:
        """True for a rest-to-rest move whose waypoints coincide (within :data:`ZERO_MOVE_M`)."""
        spread = np.abs(self.waypoints_m - self.waypoints_m[0]).max()
        return self.is_rest_to_rest and float(spread) <= ZERO_MOVE_M

    def require_in_workspace(self, model: FalconModel) -> None:
        """Raise :class:`WorkspaceError` naming the first point (start, via i, goal) outside
        ``model``'s workspace and why (unreachable, leg-angle range, near a singularity)."""
        names = ["start", *[f"via point {i}" for i in range(len(self.via_m))], "goal"]
        for name, point in zip(names, self.waypoints_m):
            require_in_workspace(point, model.params, model.limits, what=name)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (lists of floats)."""
        return {"start_m": list(self.start_m), "goal_m": list(self.goal_m),
                "start_velocity_m_s": list(self.start_velocity_m_s),
                "goal_velocity_m_s": list(self.goal_velocity_m_s),
                "via_m": [list(v) for v in self.via_m], "payload_kg": self.payload_kg}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PlanProblem":
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`InvalidProblemError`."""
        require_known_fields(cls, data, InvalidProblemError)
        missing = [k for k in ("start_m", "goal_m") if k not in data]
        if missing:
            raise InvalidProblemError(f"PlanProblem JSON lacks field(s) {missing}")
        return cls(**data)


HESSIANS = ("exact", "limited-memory")
PROFILES = ("linear", "constant")
"""Values of PlanOptions.profile (the acceleration on each interval of the transcription)."""
WARM_STARTS = ("none", "neighbours")
"""Values of PlanOptions.warm_start."""


@dataclass(frozen=True)
class PlanOptions:
    """How to plan and what to check.

    Attributes
    ----------
    tc_max : command limit |Tc| <= tc_max [command units], in (0, 4096]; default 2500, the
        static saturation the paper measured. Used with ``limit="constant"`` only.
    limit : "constant" (default): |Tc| <= tc_max; "device": |Tc| <= L(w), the device's
        speed-dependent limit (2500 at rest rising to 4096 above 2 rad/s of leg speed,
        :mod:`falcon_plan.model.saturation`, the rule the simulated plant applies), so plans
        use what the device gives in motion and stay trackable from rest.
    feedback_reserve : command units kept free for the executor's feedback [command units],
        subtracted from the limit in the plan (constant or device); default
        :data:`DEFAULT_FEEDBACK_RESERVE`.
    profile : the acceleration on each interval: "linear" (default; continuous, piecewise
        linear, the durations converge at second order in 1/N) or "constant" (one value per
        interval; first order: the configuration before the linear profile).
    n_intervals : intervals of the transcription, 4..400; default None: :data:`DEFAULT_INTERVALS`
        plus :data:`INTERVALS_PER_VIA` per via point (:meth:`intervals_for`; see their
        docstrings for the measured gap to the converged duration).
    time_budget_s : wall-time budget of the optimiser [s]; past it the planner gives up and
        (with ``fallback``) returns the ruckig reference instead.
    hessian : "limited-memory" (L-BFGS, default: first derivatives only, compiled) or "exact"
        (second derivatives in CasADi's virtual machine, ~10x slower per plan).
    fallback : on optimiser failure or time-out, return the ruckig joint-space reference
        (``method = "ruckig-fallback"``) instead of raising :class:`PlanningFailed`.
    crosscheck : compute the toppra (same path, straight line) and ruckig reference durations
        (about 10-30 ms).
    refine : re-solve on another grid (N/2, and 2N when that estimate is not conclusive, see
        ``planning.api._refine``) and report, by Richardson extrapolation, the converged
        duration (N -> infinity) and the plan's gap to it (about 1.5x the cost of the plan
        alone, 3x when 2N is solved); when the N plan's gap exceeds ``optimality_target``,
        the 2N plan (a quarter of the gap with the linear profile) is returned instead.
    optimality_target : the gap to the converged duration accepted with ``refine`` (default
        0.003, 0.3 %).
    plant_check : run the trajectory closed-loop on the simulated plant (if available).
    dense_factor : the constraints are re-checked at this many points per interval (>= 2).
    command_tolerance : relative excess of |Tc| over tc_max accepted on the dense re-check
        before a plan is rejected (the transcription imposes the limit at both ends of every
        interval; in between the command may exceed it by a hair).
    warm_start : "none" (default: every plan starts from the same straight-line guess, so it
        never depends on earlier queries) or "neighbours" (start from the nearest solved
        neighbour's solution, see :mod:`falcon_plan.planning.warmstart`; fewer iterations
        for streams of nearby goals, same optimum).

    Use :meth:`fast` for the service's fast path (no cross-checks, no refinement, no plant run).
    """

    tc_max: float = 2500.0
    n_intervals: int | None = None
    time_budget_s: float = 5.0
    hessian: str = "limited-memory"
    fallback: bool = True
    crosscheck: bool = True
    refine: bool = True
    plant_check: bool = True
    dense_factor: int = 10
    command_tolerance: float = 0.01
    warm_start: str = "none"
    limit: str = "constant"
    feedback_reserve: float = 150.0
    profile: str = "linear"
    optimality_target: float = 0.003

    def __post_init__(self) -> None:
        object.__setattr__(self, "tc_max", require_number("tc_max", self.tc_max, InvalidProblemError, 0.0, float(ACRA2009.command_limit),
                                                       low_open=True))
        if self.limit not in LIMIT_KINDS:
            raise InvalidProblemError(f"limit must be one of {LIMIT_KINDS}, got {self.limit!r}")
        if self.profile not in PROFILES:
            raise InvalidProblemError(f"profile must be one of {PROFILES}, got {self.profile!r}")
        object.__setattr__(self, "feedback_reserve",
                           require_number("feedback_reserve", self.feedback_reserve, InvalidProblemError, 0.0, 1000.0))
        object.__setattr__(self, "optimality_target",
                           require_number("optimality_target", self.optimality_target, InvalidProblemError, 0.0, 1.0, low_open=True))
        if self.limit == "constant" and self.feedback_reserve >= self.tc_max:
            raise InvalidProblemError(f"feedback_reserve ({self.feedback_reserve:g}) must be smaller than "
                                      f"tc_max ({self.tc_max:g})")
        if self.n_intervals is not None:
            object.__setattr__(self, "n_intervals", require_whole_number("n_intervals", self.n_intervals, InvalidProblemError, 4, 400))
        object.__setattr__(self, "time_budget_s",
                           require_number("time_budget_s", self.time_budget_s, InvalidProblemError, 0.0, 600.0, low_open=True))
        if self.warm_start not in WARM_STARTS:
            raise InvalidProblemError(f"warm_start must be one of {WARM_STARTS}, got {self.warm_start!r}")
        if self.hessian not in HESSIANS:
            raise InvalidProblemError(f"hessian must be one of {HESSIANS}, got {self.hessian!r}")
        for name in ("fallback", "crosscheck", "refine", "plant_check"):
            if not isinstance(getattr(self, name), bool):
                raise InvalidProblemError(f"{name} must be true or false, got {getattr(self, name)!r}")
        object.__setattr__(self, "dense_factor", require_whole_number("dense_factor", self.dense_factor, InvalidProblemError, 2, 1000))
        object.__setattr__(self, "command_tolerance",
                           require_number("command_tolerance", self.command_tolerance, InvalidProblemError, 0.0, 0.5))

    def intervals_for(self, problem: PlanProblem) -> int:
        """N for ``problem``: ``n_intervals``, or by default :data:`DEFAULT_INTERVALS` plus
        :data:`INTERVALS_PER_VIA` per via point (at most 400)."""
        if self.n_intervals is not None:
            return self.n_intervals
        return min(DEFAULT_INTERVALS + INTERVALS_PER_VIA * len(problem.via_m), 400)

    def command_bound(self, params: FalconParams) -> CommandBound:
        """The command bound these options impose on a device with ``params``."""
        return CommandBound(self.limit, self.tc_max, self.feedback_reserve, SaturationModel.of(params))

    @classmethod
    def fast(cls, **changes: Any) -> "PlanOptions":
        """Options for latency-critical callers: only the plan and its dense re-check."""
        base = {"crosscheck": False, "refine": False, "plant_check": False}
        base.update(changes)
        return cls(**base)

    def replace(self, **changes: Any) -> "PlanOptions":
        """A copy with some options changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PlanOptions":
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`InvalidProblemError`."""
        require_known_fields(cls, data, InvalidProblemError)
        return cls(**data)


DEFAULT_INTERVALS = 24
"""Default N without via points. With the linear profile the durations converge at second
order: over the benchmark problems N = 24 is 0.06-0.44 % above a 192-interval solve (the
long, low-limit moves lose most), N = 28 0.05-0.32 %, N = 12 0.5-1.3 %. With ``refine`` (on
by default) a plan above ``optimality_target`` is replaced by its 2N refinement, so the
default plans are within 0.3 % (see benchmarks/bench_planner.py)."""
INTERVALS_PER_VIA = 12
"""Intervals added per via point by default: each segment between via points has its own
duration, and at 24 intervals in all the via problems were 0.4-1.1 % above the converged
duration (0.1-0.24 % at 48)."""
DEFAULT_FEEDBACK_RESERVE = PlanOptions.feedback_reserve
"""Default reserve [command units]: the executor's PD (kp = 10 per count, kd = 0.1 per
count/s) adds up to about 110 units on top of the feed-forward while tracking minimum-time
plans on the simulated plant; 150 keeps the executed command within the device's limit on
the benchmark problems (see tests/planning/test_device_limit.py)."""

__all__ = ["PlanProblem", "PlanOptions", "HESSIANS", "WARM_STARTS", "PROFILES",
           "DEFAULT_INTERVALS", "INTERVALS_PER_VIA", "DEFAULT_FEEDBACK_RESERVE", "ZERO_MOVE_M"]
