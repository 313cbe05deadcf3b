"""Independent checks of a planned trajectory.

- :func:`dense_check`: the constraints re-checked on the *continuous* trajectory (its own
  interpolation) at ``factor`` points per interval (default 10, so 10x the planner's grid):
  commands by the model's inverse dynamics against the plan's command bound (constant, or
  the device's speed-dependent limit, minus the feedback reserve), and the workspace margins
  (>= 0 inside). This is what says the limit holds *between* the nodes, not only where the
  optimiser imposed it.
- :func:`plant_check`: a closed-loop run on the simulated plant (SimPlant + the paper's
  encoder PD, with the trajectory's commands as feed-forward advanced by the plant's command
  delay); a run that raises is reported (``ran`` False, with the error), never raised.

- :func:`grid_refinement`: the same problem solved on half or twice as many intervals
  (warm-started from the plan itself), and from the two durations the converged duration
  (N -> infinity) by Richardson extrapolation (:func:`extrapolate`).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import angles_to_counts, counts_to_position, inverse_kinematics
from falcon_plan.model.workspace import ANGLE_MARGIN_NAMES, CONSTRAINT_NAMES, angle_margins_deg
from falcon_plan.planning.bound import CommandBound
from falcon_plan.trajectory import Trajectory

if TYPE_CHECKING:
    from falcon_plan.falconlog import FalconLog
    from falcon_plan.planning.casadi_planner import NodeMotion

log = logging.getLogger(__name__)

PLANT_MAX_ERROR_MM = 3.0
"""A plant run passes when the Cartesian tracking error stays below this [mm] ..."""
PLANT_FINAL_ERROR_MM = 0.5
"""... and the final position is within this of the goal [mm], ``settle_s`` (default 0.3 s;
the paper's soft PD takes about that long to settle) after the end."""
HOLD_BEFORE_S = 0.05
"""A rest-to-rest run first holds still this long [s] (the command delay line fills)."""


@dataclass(frozen=True)
class DenseCheck:
    """Result of :func:`dense_check`.

    worst_command_ratio : max over time and motors of |Tc| / bound (<= 1 means within), the
        bound being the plan's (tc_max or the device's limit L(w), minus the reserve).
    worst_command_time_s : where it occurs [s].
    worst_margin : smallest workspace margin (>= 0 inside; radians for the angle rows, sine
        or determinant units for the others, see workspace.CONSTRAINT_NAMES).
    worst_margin_name : which margin (name and leg).
    n_points : points checked.
    worst_angle_margin_deg : the smallest distance of a leg to an angle limit [deg] (leg
        angle, knee or parallelogram: :func:`~falcon_plan.model.workspace.angle_margins_deg`,
        what the plan's plot draws).
    worst_angle_margin_name : which one, e.g. ``leg angle, leg 2``.
    forward_singularity_margin : smallest forward-singularity measure above its floor
        [unitless |det|].
    """

    worst_command_ratio: float
    worst_command_time_s: float
    worst_margin: float
    worst_margin_name: str
    n_points: int
    worst_angle_margin_deg: float = math.nan
    worst_angle_margin_name: str = ""
    forward_singularity_margin: float = math.nan

    def within(self, command_tolerance: float) -> bool:
        """True when |Tc| <= (1 + command_tolerance) tc_max and every margin >= 0 (with a
        1e-6 numerical allowance)."""
        return self.worst_command_ratio <= 1.0 + command_tolerance and self.worst_margin >= -1e-6

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def dense_times(traj: Trajectory, factor: int) -> np.ndarray:
    """``factor`` evenly spaced points in every interval of ``traj`` plus the final time [s]."""
    t = traj.t_s
    frac = np.arange(factor) / factor
    dense = (t[:-1, None] + np.diff(t)[:, None] * frac[None, :]).ravel()
    return np.append(dense, t[-1])


def dense_check(model: FalconModel, traj: Trajectory, bound: CommandBound, factor: int = 10) -> DenseCheck:
    """Re-check the plan ``traj``: |Tc| (``model``'s inverse dynamics) <= ``bound`` and
    ``model``'s workspace margins >= 0, at ``factor`` points per interval.

    At each interval's start the acceleration is the interval's own (right limit); for a
    piecewise-constant acceleration the interval's end is covered by the left limit evaluated
    separately, so both ends of every interval are checked as well as the inside.
    """
    t = dense_times(traj, factor)
    pos, vel, acc = traj.at_time(t)
    all_p, all_v, all_a, all_t = pos, vel, acc, t
    if traj.interpolation == "constant":
        # left limits at the interval ends: the previous interval's acceleration
        ends = traj.t_s[1:]
        k = np.arange(len(traj.t_s) - 1)
        h = np.diff(traj.t_s)[:, None]
        a_prev = traj.acceleration_m_s2[k]
        p_end = traj.position_m[k] + traj.velocity_m_s[k] * h + 0.5 * a_prev * h * h
        v_end = traj.velocity_m_s[k] + a_prev * h
        all_p = np.vstack([pos, p_end])
        all_v = np.vstack([vel, v_end])
        all_a = np.vstack([acc, a_prev])
        all_t = np.concatenate([t, ends])
    tc = model.inverse_dynamics(all_p, all_v, all_a)
    ratio = (np.abs(tc) / bound.allowed(model, all_p, all_v, all_a)).max(axis=1)
    i = int(np.argmax(ratio))
    margins = model.workspace_margins(pos)
    j = np.unravel_index(int(np.argmin(margins)), margins.shape)
    # the same margins for people: in degrees, each angle to its own limit (the rows above mix
    # radians and sines, so their smallest number need not be the nearest limit)
    angle, forward = angle_margins_deg(pos, model)
    k = np.unravel_index(int(np.nanargmin(angle)), angle.shape)
    return DenseCheck(float(ratio[i]), float(all_t[i]), float(margins[j]), _margin_name(int(j[1])),
                      int(len(all_t)), float(angle[k]), f"{ANGLE_MARGIN_NAMES[k[1]]}, leg {k[2]}",
                      float(np.nanmin(forward)))


def _margin_name(row: int) -> str:
    """Name of row ``row`` of workspace_margins (CONSTRAINT_NAMES x legs, then the det)."""
    per_leg = len(CONSTRAINT_NAMES) - 1
    if row < 3 * per_leg:
        return f"{CONSTRAINT_NAMES[row // 3]} (leg {row % 3})"
    return CONSTRAINT_NAMES[-1]


@dataclass(frozen=True)
class PlantCheck:
    """Result of :func:`plant_check`.

    Attributes
    ----------
    ran : False when the plant run raised (``note`` says what).
    passed : the run met :data:`PLANT_MAX_ERROR_MM` and :data:`PLANT_FINAL_ERROR_MM` (False
        when it did not run to the end).
    max_error_mm : largest Cartesian tracking error against the plan [mm].
    final_error_mm : distance from the goal ``settle_s`` after the end [mm].
    max_command : peak |Tc| the controller issued [command units].
    rate_hz : the loop rate of the run [Hz].
    run_time_s : wall time of the check [s].
    note : why the run failed ("" otherwise).
    max_command_over_limit : peak of |Tc| / L(w) over the run: each issued command against
        the device's speed-dependent limit at the motion it acts on
        (:func:`executed_limit_ratio`); <= 1 means the device delivered every command the
        controller asked for.
    """

    ran: bool
    passed: bool | None
    max_error_mm: float | None
    final_error_mm: float | None
    max_command: float | None
    rate_hz: float | None
    run_time_s: float
    note: str = ""
    max_command_over_limit: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def plant_check(model: FalconModel, traj: Trajectory, *, rate_hz: float = 800.0,
                settle_s: float = 0.3) -> PlantCheck:
    """Run ``traj`` closed loop on the simulated plant (``model``'s dynamics and effects) under
    the executor's controller (:meth:`falcon_plan.control.Controller.executor_default`: PD
    with the derivative on the error and ``model``'s feed-forward two samples ahead, the same
    value the executor runs) at ``rate_hz`` [Hz], after a hold at the start; errors are
    measured against the plan from the encoder counts.

    Passes when the Cartesian error stays below :data:`PLANT_MAX_ERROR_MM` and ends within
    :data:`PLANT_FINAL_ERROR_MM` ``settle_s`` after the end. A plant error (the device leaving
    the workspace) is reported as a failure with its message.
    """
    t0 = time.perf_counter()
    from falcon_plan.control import Controller
    from falcon_plan.sim.plant import SimPlant

    try:
        plant = SimPlant(model, rate_hz=rate_hz)
        controller = Controller.executor_default(rate_hz, model)
        plant.reset(traj.position_m[0], traj.velocity_m_s[0])
        # hold still first when the plan starts at rest (fills the command delay line, lets
        # the PD settle), then the plan sampled on the loop's grid, then the goal held
        k_hold = int(round(HOLD_BEFORE_S * rate_hz)) if not np.any(traj.velocity_m_s[0]) else 0
        n = int(math.ceil((traj.duration_s + settle_s) * rate_hz)) + 1
        t = np.arange(-k_hold, n) / rate_hz
        pos, _, _ = traj.at_time(np.clip(t, 0.0, traj.duration_s) + traj.t_s[0])
        ref = angles_to_counts(inverse_kinematics(pos, model.params).theta1, model.params)
        run = controller.run_on(plant, ref, model)
        # a command issued at t acts from t + delay on (the plant's delay line)
        delay = model.params.command_delay_samples + int(model.effects.extra_delay_samples)
        over_limit = executed_limit_ratio(model, traj, run.commands, t + delay / rate_hz)
        measured = counts_to_position(run.counts[k_hold:].astype(float), model.params)
        err_mm = 1e3 * np.linalg.norm(measured - pos[k_hold:], axis=1)
        final_mm = 1e3 * float(np.linalg.norm(plant.position_m - traj.position_m[-1]))
    except Exception as exc:  # the plant is another engineer's code: report, never crash the plan
        log.warning("plant check failed: %s", exc)
        return PlantCheck(False, False, None, None, None, rate_hz, time.perf_counter() - t0,
                          f"plant run failed: {type(exc).__name__}: {exc}")
    max_err = float(err_mm.max())
    passed = max_err <= PLANT_MAX_ERROR_MM and final_mm <= PLANT_FINAL_ERROR_MM
    return PlantCheck(True, passed, max_err, final_mm, float(np.abs(run.commands[k_hold:]).max()), rate_hz,
                      time.perf_counter() - t0, max_command_over_limit=over_limit)


def executed_limit_ratio(model: FalconModel, traj: Trajectory, commands: np.ndarray, t_s: np.ndarray) -> float:
    """max |Tc_k| / L(w_k): executed commands against the device's speed-dependent limit
    (:mod:`falcon_plan.model.saturation`, what the plant clips to).

    ``commands`` (K, 3) [command units] act while ``model``'s device follows the plan ``traj`` at times
    ``t_s`` (K,) [s, plan time; before 0 and after the end the plan is at rest]; w_k is the
    plan's leg speed there, J(p) v [rad/s] (the device tracks the plan to a few counts, so
    its speed is the plan's to a small fraction of the 2 rad/s over which the limit rises).
    """
    from falcon_plan.model.saturation import SaturationModel

    tq = np.asarray(t_s, float) + traj.t_s[0]
    pos, vel, _ = traj.at_time(tq)
    moving = ((tq >= traj.t_s[0]) & (tq <= traj.t_s[-1]))[:, None]
    bound = CommandBound("device", 0.0, 0.0, SaturationModel.of(model.params))
    limit = bound.device_limit(model, pos, np.where(moving, vel, 0.0))
    return float((np.abs(np.asarray(commands, float)) / limit).max())


def log_limit_ratio(model: FalconModel, traj: Trajectory, log: FalconLog, preroll_s: float) -> float:
    """:func:`executed_limit_ratio` of ``log``, a falcon log written by the executor running
    ``traj`` on ``model``'s device after ``preroll_s`` [s] of holding: the command logged at t acts from t + d / rate on,
    d = the device's command delay [samples], i.e. on the plan at t - preroll_s + d / rate."""
    acting = np.asarray(log.t_s, float) - preroll_s + model.params.command_delay_samples / float(log.rate_hz)
    return executed_limit_ratio(model, traj, np.asarray(log.tc, float), acting)


CONVERGENCE_ORDER = {"constant": 1, "linear": 2}
"""Order in 1/N at which the durations converge, per acceleration profile: measured over
the benchmark problems (T_N - T_inf halves from N to 2N with a constant acceleration per
interval, and drops about fourfold with a linear one); :func:`extrapolate` relies on it."""


def extrapolate(t_coarse: float, t_fine: float, order: int, ratio: float = 2.0) -> float:
    """Richardson extrapolation to N -> infinity [s] of the durations ``t_coarse`` at N
    intervals and ``t_fine`` at ``ratio`` N (> 1), converging at ``order`` in 1/N:
    T_inf = T_fine + (T_fine - T_coarse) / (ratio^order - 1)."""
    return t_fine + (t_fine - t_coarse) / (ratio ** order - 1)


@dataclass(frozen=True)
class RefinementCheck:
    """Result of :func:`grid_refinement`: the same problem solved on another grid.

    n_intervals : the other grid's N.
    duration_s : its duration [s] (None if that solve failed).
    change : its relative change against the plan, (T_other - T_plan) / T_plan.
    solver_status, solve_time_s : IPOPT's status and the wall time of that solve [s].
    converged_duration_s : the converged duration (N -> infinity) extrapolated from the two
        (:func:`extrapolate`) [s].
    gap : the plan's gap to it, (T_plan - T_inf) / T_inf.
    trajectory : the other grid's plan (None if that solve failed).
    """

    n_intervals: int
    duration_s: float | None
    change: float | None
    solver_status: str
    solve_time_s: float
    converged_duration_s: float | None = None
    gap: float | None = None
    trajectory: Trajectory | None = field(default=None, repr=False, compare=False)


def plan_segments(problem: Any, traj: Trajectory) -> tuple[int, ...]:
    """Interval counts of ``traj``'s segments between the via points of ``problem`` (from its
    ``meta``, as the planner records them; else the planner's default split of its N)."""
    from falcon_plan.planning.casadi_planner import segment_counts

    if "segments" in traj.meta:
        return tuple(int(k) for k in traj.meta["segments"])
    return segment_counts(problem, len(traj.t_s) - 1)


def resampled_guess(traj: Trajectory, source: tuple[int, ...], target: tuple[int, ...]) -> Any:
    """``traj`` (segments of ``source`` intervals each) at the nodes of a grid with ``target``
    intervals per segment (equal within a segment, the segment ends kept), as a planner guess
    (a ``NodeMotion``). Exact when every target count is a multiple of its source count (each
    interval split without changing the acceleration profile); otherwise the motion sampled
    at the new nodes (for the "constant" profile, the acceleration at each new interval's start)."""
    from falcon_plan.planning.casadi_planner import NodeMotion

    t0 = traj.t_s[0]
    ends = traj.t_s[np.cumsum((0, *source))] - t0
    t = np.append(np.concatenate([np.linspace(ends[j], ends[j + 1], k + 1)[:-1] for j, k in enumerate(target)]),
                  ends[-1])
    pos, vel, acc = traj.at_time(t + t0)
    if traj.interpolation == "constant":
        acc = acc[:-1]
    else:
        acc[-1] = traj.acceleration_m_s2[-1]
    return NodeMotion(traj.duration_s, pos, vel, acc, np.diff(t))


def grid_refinement(model: FalconModel, problem: Any, traj: Trajectory, bound: CommandBound,
                    hessian: str = "limited-memory", coarser: bool = False) -> RefinementCheck:
    """Solve ``problem`` again on another grid and estimate the converged duration from the
    two (same acceleration profile as ``traj``, the planner's result, warm-started from it;
    the same ``model`` and command ``bound``).

    ``coarser`` False (default): twice the intervals in every segment (nested grids: each
    interval split in two); True: half of them (each segment's count halved, rounded, at
    least 1), the cheap partner of a refinement sequence N/2 -> N. The extrapolation uses the
    ratio of the total interval counts. ``hessian``: IPOPT's Hessian choice, as the plan's.
    """
    from falcon_plan.planning.casadi_planner import solve_min_time

    source = plan_segments(problem, traj)
    target = tuple(max(1, round(k / 2)) for k in source) if coarser else tuple(2 * k for k in source)
    n, n_other = sum(source), sum(target)
    other = solve_min_time(model, problem, n_intervals=n_other, bound=bound, hessian=hessian,
                           guess=resampled_guess(traj, source, target), profile=traj.interpolation,
                           segments=target)
    if not other.success:
        return RefinementCheck(n_other, None, None, other.solver_status, other.solve_time_s)
    order = CONVERGENCE_ORDER[traj.interpolation]
    if n_other > n:
        t_inf = extrapolate(traj.duration_s, other.duration_s, order, n_other / n)
    else:
        t_inf = extrapolate(other.duration_s, traj.duration_s, order, n / n_other)
    return RefinementCheck(n_other, other.duration_s, (other.duration_s - traj.duration_s) / traj.duration_s,
                           other.solver_status, other.solve_time_s, t_inf,
                           (traj.duration_s - t_inf) / t_inf, other.trajectory)


__all__ = ["DenseCheck", "RefinementCheck", "grid_refinement", "resampled_guess",
           "plan_segments", "dense_check",
           "dense_times", "PlantCheck", "plant_check", "executed_limit_ratio", "log_limit_ratio", "extrapolate",
           "CONVERGENCE_ORDER", "PLANT_MAX_ERROR_MM", "PLANT_FINAL_ERROR_MM"]
