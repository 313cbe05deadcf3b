"""Planning problems and planner options: validated, frozen, JSON in/out.

:class:`PlanProblem` says *what* to plan: start and goal points of the end effector [m] in
the base frame (x right, y up, z toward the user), start and end velocities [m/s] (rest by
default), optional via points [m] and an optional payload [kg] carried at the end effector.
:class:`PlanOptions` says *how*, in four parts kept apart as rockit keeps a problem apart from
its transcription and solver: :class:`CommandLimits` (the physics: |Tc| <= tc_max in command
units, 0 < tc_max <= 4096, or the device's speed-dependent limit, minus a feedback reserve),
:class:`Transcription` (acceleration profile, number of intervals), :class:`SolverSettings`
(Hessian, time budget, warm start, fallback) and :class:`Checks` (dense re-check, refinement,
cross-checks, plant run). None of them knows about a particular solver's options.

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
            raise InvalidProblemError(f"via_m must be a list of points, got {vias!r}", field="via_m",
                                      allowed="a list of points, each 3 numbers")
        object.__setattr__(self, "via_m", tuple(require_vec3(f"via_m[{i}]", v, InvalidProblemError) for i, v in enumerate(vias)))
        if len(self.via_m) > 8:
            raise InvalidProblemError(f"at most 8 via points are supported, got {len(self.via_m)}", field="via_m",
                                      allowed="at most 8 via points")
        object.__setattr__(self, "payload_kg", require_number("payload_kg", self.payload_kg, InvalidProblemError, 0.0, 1.0))
        for name in ("start_velocity_m_s", "goal_velocity_m_s"):
            speed = float(np.linalg.norm(getattr(self, name)))
            if speed > 5.0:
                raise InvalidProblemError(f"{name} has speed {speed:.3g} m/s; at most 5 m/s is plannable", field=name,
                                          allowed="a speed of at most 5 m/s")

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
        from falcon_plan.model.workspace import require_in_workspace  # the kinematics: loaded on use

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
        """The problem in ``data`` (the JSON object of :meth:`to_dict`; ``start_m`` and ``goal_m``
        required); unknown keys raise :class:`InvalidProblemError`."""
        require_known_fields(cls, data, InvalidProblemError)
        missing = [k for k in ("start_m", "goal_m") if k not in data]
        if missing:
            raise InvalidProblemError(f"PlanProblem JSON lacks field(s) {missing}")
        return cls(**data)


HESSIANS = ("exact", "limited-memory")
"""Values of SolverSettings.hessian."""
PROFILES = ("linear", "constant")
"""Values of Transcription.profile (the acceleration on each interval of the transcription)."""
WARM_STARTS = ("none", "neighbours")
"""Values of SolverSettings.warm_start."""
REPLAN_SEARCHES = ("shortest", "first")
"""Values of SolverSettings.replan_search."""


def _require_choice(name: str, value: Any, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise InvalidProblemError(f"{name} must be one of {allowed}, got {value!r}", field=name,
                                  allowed=f"one of {allowed}")


def _unknown_option(name: str) -> InvalidProblemError:
    """The error for a planner option ``name`` that does not exist (it lists those that do)."""
    return InvalidProblemError(f"unknown planner option {name!r}; allowed: {sorted(OPTION_FIELDS)} "
                               f"(or the parts {list(OPTION_PARTS)})", field=name, allowed=sorted(OPTION_FIELDS))


def _require_flag(name: str, value: Any) -> None:
    if not isinstance(value, bool):
        raise InvalidProblemError(f"{name} must be true or false, got {value!r}", field=name, allowed="true or false")


@dataclass(frozen=True)
class CommandLimits:
    """The problem's physics: what the plan may command the motors to do.

    Attributes
    ----------
    tc_max : command limit |Tc| <= tc_max [command units], in (0, 4096]; default 2500, the
        static saturation the paper measured. Used with ``limit="constant"`` only.
    limit : "constant" (default): |Tc| <= tc_max; "device": |Tc| <= L(w), the device's
        speed-dependent limit (2500 at rest rising to 4096 above 2 rad/s of leg speed,
        :mod:`falcon_plan.model.saturation`, the rule the simulated plant applies), so plans
        use what the device gives in motion and stay trackable from rest.
    feedback_reserve : command units kept free for the executor's feedback [command units],
        0..1000, subtracted from the limit in the plan (constant or device); default 150
        (:data:`DEFAULT_FEEDBACK_RESERVE`).
    """

    tc_max: float = 2500.0
    limit: str = "constant"
    feedback_reserve: float = 150.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "tc_max", require_number("tc_max", self.tc_max, InvalidProblemError, 0.0,
                                                          float(ACRA2009.command_limit), low_open=True))
        _require_choice("limit", self.limit, LIMIT_KINDS)
        object.__setattr__(self, "feedback_reserve",
                           require_number("feedback_reserve", self.feedback_reserve, InvalidProblemError, 0.0, 1000.0))
        if self.limit == "constant" and self.feedback_reserve >= self.tc_max:
            raise InvalidProblemError(f"feedback_reserve ({self.feedback_reserve:g}) must be smaller than "
                                      f"tc_max ({self.tc_max:g})", field="feedback_reserve",
                                      allowed=f"smaller than tc_max ({self.tc_max:g})")

    def bound(self, params: FalconParams) -> CommandBound:
        """The command bound these limits impose on a device with ``params``."""
        return CommandBound(self.limit, self.tc_max, self.feedback_reserve, SaturationModel.of(params))


@dataclass(frozen=True)
class Transcription:
    """How the continuous problem is made finite (the optimiser never sees the problem itself).

    Attributes
    ----------
    profile : the acceleration on each interval: "linear" (default; continuous, piecewise
        linear, the durations converge at second order in 1/N) or "constant" (one value per
        interval; first order: the configuration before the linear profile).
    n_intervals : intervals of the transcription, 4..:data:`MAX_INTERVALS`; default None: :data:`DEFAULT_INTERVALS`
        plus :data:`INTERVALS_PER_VIA` per via point (:meth:`intervals_for`; see their
        docstrings for the measured gap to the converged duration).
    switching : True (default): read the bang-bang command pattern off a coarse
        transcription and solve for its exact switch times and duration
        (:mod:`falcon_plan.planning.shooting`; constant or device limit, with or without via
        points, with or without friction: within 0.01 % of the converged duration, at about
        the cost of a solve at N = 8, a few times that under the device's limit); the
        transcription at ``n_intervals`` is solved only where that fails. False: always the
        transcription.
    """

    profile: str = "linear"
    n_intervals: int | None = None
    switching: bool = True

    def __post_init__(self) -> None:
        _require_choice("profile", self.profile, PROFILES)
        _require_flag("switching", self.switching)
        if self.n_intervals is not None:
            object.__setattr__(self, "n_intervals",
                               require_whole_number("n_intervals", self.n_intervals, InvalidProblemError, 4, MAX_INTERVALS))

    def intervals_for(self, problem: PlanProblem) -> int:
        """N for ``problem``: ``n_intervals``, or by default :data:`DEFAULT_INTERVALS` plus
        :data:`INTERVALS_PER_VIA` per via point (at most :data:`MAX_INTERVALS`)."""
        if self.n_intervals is not None:
            return self.n_intervals
        return min(DEFAULT_INTERVALS + INTERVALS_PER_VIA * len(problem.via_m), MAX_INTERVALS)


@dataclass(frozen=True)
class SolverSettings:
    """How the transcribed problem is solved, and what happens when that fails.

    Attributes
    ----------
    hessian : "limited-memory" (L-BFGS, default: first derivatives only, compiled) or "exact"
        (second derivatives in CasADi's virtual machine, ~10x slower per plan).
    time_budget_s : wall-time budget of the optimiser [s], in (0, 600]; past it the planner
        gives up and (with ``fallback``) returns the ruckig reference instead.
    warm_start : "none" (default: every plan starts from the same straight-line guess, so it
        never depends on earlier queries) or "neighbours" (start from the nearest solved
        neighbour's solution, see :mod:`falcon_plan.planning.warmstart`; fewer iterations
        for streams of nearby goals, same optimum). It warm-starts the transcription at N,
        i.e. where the switching-time solve does not apply or fails
        (``Transcription.switching``).
    fallback : on optimiser failure or time-out, return the ruckig joint-space reference
        (``method = "ruckig-fallback"``) instead of raising :class:`PlanningFailed`.
    replan_search : how a plan from a moving state (:mod:`falcon_plan.planning.replan`)
        searches its warm guesses: "shortest" (default: every guess solved and the shortest
        extremal kept, a leg in four arcs tried too: within 0.3 % of the optimum) or "first"
        (the first guess that makes a plan within the bound: about 8x less time, up to a few %
        longer; for a stream of goals, e.g. a moving target, where latency matters more).
    """

    hessian: str = "limited-memory"
    time_budget_s: float = 5.0
    warm_start: str = "none"
    fallback: bool = True
    replan_search: str = "shortest"

    def __post_init__(self) -> None:
        _require_choice("hessian", self.hessian, HESSIANS)
        object.__setattr__(self, "time_budget_s",
                           require_number("time_budget_s", self.time_budget_s, InvalidProblemError, 0.0, 600.0,
                                          low_open=True))
        _require_choice("warm_start", self.warm_start, WARM_STARTS)
        _require_flag("fallback", self.fallback)
        _require_choice("replan_search", self.replan_search, REPLAN_SEARCHES)


@dataclass(frozen=True)
class Checks:
    """What is verified and reported about a solved plan.

    Attributes
    ----------
    dense_factor : the constraints are re-checked at this many points per interval (2..1000).
    command_tolerance : relative excess of |Tc| over the bound accepted on the dense re-check
        before a plan is rejected, 0..0.5 (the transcription imposes the limit at its
        constraint points; in between the command may exceed it by a hair).
    refine : re-solve on another grid (N/2, and 2N when that estimate is not conclusive, see
        ``planning.pipeline.refine_transcription``) and report, by Richardson extrapolation, the converged
        duration (N -> infinity) and the plan's gap to it (about 1.5x the cost of the plan
        alone, 3x when 2N is solved); when the N plan's gap exceeds ``optimality_target``,
        the 2N plan (a quarter of the gap with the linear profile) is returned instead.
    optimality_target : the gap to the converged duration accepted with ``refine``, in
        (0, 1] (default 0.003, 0.3 %).
    crosscheck : compute the toppra (same path, straight line) and ruckig reference durations
        (about 10-30 ms).
    plant_check : run the trajectory closed-loop on the simulated plant with the executor's
        controller and report the tracking and the executed peak command.
    """

    dense_factor: int = 10
    command_tolerance: float = 0.01
    refine: bool = True
    optimality_target: float = 0.003
    crosscheck: bool = True
    plant_check: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "dense_factor",
                           require_whole_number("dense_factor", self.dense_factor, InvalidProblemError, 2, 1000))
        object.__setattr__(self, "command_tolerance",
                           require_number("command_tolerance", self.command_tolerance, InvalidProblemError, 0.0, 0.5))
        object.__setattr__(self, "optimality_target",
                           require_number("optimality_target", self.optimality_target, InvalidProblemError, 0.0, 1.0,
                                          low_open=True))
        for name in ("refine", "crosscheck", "plant_check"):
            _require_flag(name, getattr(self, name))


OPTION_PARTS: dict[str, type] = {"limits": CommandLimits, "transcription": Transcription,
                                 "solver": SolverSettings, "checks": Checks}
"""The parts of :class:`PlanOptions`, by attribute name, in the order they act: the problem's
physics, its transcription, the solver, the checks of the result."""
OPTION_FIELDS: dict[str, str] = {f.name: part for part, cls in OPTION_PARTS.items()
                                 for f in dataclasses.fields(cls)}
"""Every option's name -> the part that owns it (names are unique across the parts, checked
in tests/planning/test_problem.py)."""


@dataclass(frozen=True)
class PlanOptions:
    """How to plan and what to check, in four parts (rockit's problem / transcription /
    solver split, toppra's constraint / path / algorithm):

    Attributes
    ----------
    limits : :class:`CommandLimits`, the problem's physics (command limit kind, tc_max,
        feedback reserve).
    transcription : :class:`Transcription` (acceleration profile, number of intervals).
    solver : :class:`SolverSettings` (Hessian, time budget, warm start, fallback).
    checks : :class:`Checks` (dense re-check, N -> 2N refinement and optimality target,
        toppra/ruckig cross-checks, plant run).

    Build with the parts (``PlanOptions(limits=CommandLimits(tc_max=2000))``) or, shorter,
    by option name: ``PlanOptions.of(tc_max=2000, refine=False)``; every option name is
    unique across the parts (:data:`OPTION_FIELDS`). Use :meth:`fast` for the service's
    fast path (no cross-checks, no refinement, no plant run).
    """

    limits: CommandLimits = CommandLimits()
    transcription: Transcription = Transcription()
    solver: SolverSettings = SolverSettings()
    checks: Checks = Checks()

    def __post_init__(self) -> None:
        for part, cls in OPTION_PARTS.items():
            if not isinstance(getattr(self, part), cls):
                raise InvalidProblemError(f"PlanOptions.{part} must be a {cls.__name__}, "
                                          f"got {getattr(self, part)!r}")

    @classmethod
    def of(cls, **changes: Any) -> "PlanOptions":
        """The default options with ``changes`` (option names, e.g. ``tc_max=2000``, or whole
        parts, e.g. ``checks=Checks(...)``) applied; unknown names raise InvalidProblemError."""
        return cls().replace(**changes)

    @classmethod
    def fast(cls, **changes: Any) -> "PlanOptions":
        """Options for latency-critical callers: only the plan and its dense re-check;
        ``changes`` as in :meth:`of`."""
        return cls.of(**{"crosscheck": False, "refine": False, "plant_check": False, **changes})

    def replace(self, **changes: Any) -> "PlanOptions":
        """A copy with ``changes`` applied (option names routed to their part, or whole
        parts), validated again; unknown names raise InvalidProblemError."""
        parts = {name: getattr(self, name) for name in OPTION_PARTS}
        by_part: dict[str, dict[str, Any]] = {}
        for name, value in changes.items():
            if name in OPTION_PARTS:
                parts[name] = value
            elif name in OPTION_FIELDS:
                by_part.setdefault(OPTION_FIELDS[name], {})[name] = value
            else:
                raise _unknown_option(name)
        for part, fields in by_part.items():
            parts[part] = dataclasses.replace(parts[part], **fields)
        return PlanOptions(**parts)

    def command_bound(self, params: FalconParams) -> CommandBound:
        """The command bound these options impose on a device with ``params``."""
        return self.limits.bound(params)

    def intervals_for(self, problem: PlanProblem) -> int:
        """N of the transcription for ``problem`` (:meth:`Transcription.intervals_for`)."""
        return self.transcription.intervals_for(problem)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict, one object per part: ``{"limits": {...}, "transcription": {...},
        "solver": {...}, "checks": {...}}``."""
        return {part: dataclasses.asdict(getattr(self, part)) for part in OPTION_PARTS}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PlanOptions":
        """Inverse of :meth:`to_dict`. ``data`` may also give options by name at the top
        level (``{"tc_max": 2000}``, as the service's requests and the CLI's ``--options`` do),
        applied on top of the parts; unknown names raise :class:`InvalidProblemError`."""
        if not isinstance(data, dict):
            raise InvalidProblemError(f"planner options must be a JSON object, got {data!r}")
        changes: dict[str, Any] = {}
        for name, value in data.items():
            if name in OPTION_PARTS:
                if not isinstance(value, dict):
                    raise InvalidProblemError(f"options.{name} must be an object of "
                                              f"{[f.name for f in dataclasses.fields(OPTION_PARTS[name])]}")
                require_known_fields(OPTION_PARTS[name], value, InvalidProblemError)
                changes.update(value)
            elif name not in OPTION_FIELDS:
                raise _unknown_option(name)
        changes.update({k: v for k, v in data.items() if k in OPTION_FIELDS})
        return cls.of(**changes)


DEFAULT_INTERVALS = 24
"""Default N without via points. With the linear profile the durations converge at second
order: over the benchmark problems N = 24 is 0.06-0.44 % above a 192-interval solve (the
long, low-limit moves lose most), N = 28 0.05-0.32 %, N = 12 0.5-1.3 %. With ``refine`` (on
by default) a plan above ``optimality_target`` is replaced by its 2N refinement, so the
default plans are within 0.3 % (see benchmarks/bench_planner.py)."""
MAX_INTERVALS = 400
"""The most intervals any transcription has: the largest ``n_intervals`` accepted, and the
cap of the default N and of the planner's re-solves at 2N (a larger NLP takes seconds)."""
INTERVALS_PER_VIA = 12
"""Intervals added per via point by default: each segment between via points has its own
duration, and at 24 intervals in all the via problems were 0.4-1.1 % above the converged
duration (0.1-0.24 % at 48)."""
DEFAULT_FEEDBACK_RESERVE = CommandLimits.feedback_reserve
"""Default reserve [command units]: the executor's PD (kp = 10 per count, kd = 0.1 per
count/s) adds up to about 110 units on top of the feed-forward while tracking minimum-time
plans on the simulated plant; 150 keeps the executed command within the device's limit on
the benchmark problems (see tests/planning/test_device_limit.py)."""

__all__ = ["MAX_INTERVALS", "PlanProblem", "PlanOptions", "CommandLimits", "Transcription", "SolverSettings", "Checks",
           "OPTION_PARTS", "OPTION_FIELDS", "HESSIANS", "WARM_STARTS", "REPLAN_SEARCHES", "PROFILES",
           "DEFAULT_INTERVALS", "INTERVALS_PER_VIA", "DEFAULT_FEEDBACK_RESERVE", "ZERO_MOVE_M"]
