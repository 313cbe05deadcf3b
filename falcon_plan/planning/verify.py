"""Independent checks of a planned trajectory.

- :func:`dense_check`: the constraints re-checked on the *continuous* trajectory (its own
  interpolation) at ``factor`` points per interval (default 10, so 10x the planner's grid):
  commands by the model's inverse dynamics against the plan's command bound (constant, or
  the device's speed-dependent limit, minus the feedback reserve), and the workspace margins
  (>= 0 inside). This is what says the limit holds *between* the nodes, not only where the
  optimiser imposed it.
- :func:`require_executable`: a trajectory from elsewhere (a file) refused before a device
  runs it when its nodes contradict each other (a jump), it needs more command than the device
  can ever give, or it leaves the workspace;
- :func:`plant_check`: a closed-loop run on the simulated plant (SimPlant + the paper's
  encoder PD, with the trajectory's commands as feed-forward advanced by the plant's command
  delay); a run that raises is reported (``ran`` False, with the error), never raised.

(A plan's gap to the converged duration comes from solving again on another grid:
:mod:`falcon_plan.planning.refinement`, a stage of the pipeline, not a check.)
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import angles_to_counts, counts_to_position, inverse_kinematics
from falcon_plan.model.workspace import ANGLE_MARGIN_NAMES, CONSTRAINT_NAMES, angle_margins_deg
from falcon_plan.planning.bound import CommandBound
from falcon_plan.trajectory import Trajectory

if TYPE_CHECKING:
    from falcon_plan.falconlog import FalconLog

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


NODE_POSITION_TOLERANCE_M = 1e-4
"""Largest gap [m] between where a trajectory's interpolation from one node lands and its next
node's position (a switching-time plan's RK4 nodes agree with its linear-acceleration
interpolation to ~2e-7 m; a jerk-limited motion sampled at 1 kHz to ~1e-7 m): a larger one is a jump the device would be asked to make in one tick."""
NODE_VELOCITY_TOLERANCE_M_S = 1e-2
"""The same for the velocity [m/s]."""
EXECUTABLE_COMMAND_TOLERANCE = 0.01
"""How far above the device's full command range (saturation.full, 4096) a trajectory's
commands may reach on the dense re-check before it is refused: the device could never give
them. (Above the speed-dependent limit L(w) but within the range, e.g. a plan with tc_max 4096
from rest, it runs with a note: the first milliseconds may not be tracked exactly.)"""


def node_gaps(traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Per interval of ``traj`` (N - 1,): how far its interpolation from the interval's first
    node lands from the next node, in position [m] and velocity [m/s]."""
    h = np.diff(traj.t_s)[:, None]
    p, v, a = traj.position_m, traj.velocity_m_s, traj.acceleration_m_s2
    if traj.interpolation == "linear":
        p_end = p[:-1] + v[:-1] * h + (a[:-1] / 3.0 + a[1:] / 6.0) * h * h
        v_end = v[:-1] + 0.5 * (a[:-1] + a[1:]) * h
    else:
        p_end = p[:-1] + v[:-1] * h + 0.5 * a[:-1] * h * h
        v_end = v[:-1] + a[:-1] * h
    return np.linalg.norm(p_end - p[1:], axis=1), np.linalg.norm(v_end - v[1:], axis=1)


def require_executable(model: FalconModel, traj: Trajectory, what: str = "the trajectory",
                       factor: int = 10) -> str | None:
    """Raise :class:`~falcon_plan.errors.InvalidParameterError` (one line naming ``what``, where
    and what is allowed) when ``traj`` cannot be run on a device of ``model``: a node outside the
    workspace (:class:`~falcon_plan.errors.WorkspaceError`), its nodes contradict each other (:func:`node_gaps` over :data:`NODE_POSITION_TOLERANCE_M` or
    :data:`NODE_VELOCITY_TOLERANCE_M_S`: a jump), its motion needs more command than the
    device's full range on the dense re-check (:data:`EXECUTABLE_COMMAND_TOLERANCE`), or it
    leaves the workspace (the dense re-checks at ``factor`` points per interval). Returns a note
    when it needs more than the device's speed-dependent limit L(w) somewhere but stays within
    the range (None otherwise)."""
    from falcon_plan.errors import InvalidParameterError
    from falcon_plan.model.saturation import SaturationModel
    from falcon_plan.model.workspace import require_in_workspace

    require_in_workspace(traj.position_m, model.params, model.limits, what=f"{what}: point")
    dp, dv = node_gaps(traj)
    k = int(np.argmax(dp / NODE_POSITION_TOLERANCE_M + dv / NODE_VELOCITY_TOLERANCE_M_S))
    if dp[k] > NODE_POSITION_TOLERANCE_M or dv[k] > NODE_VELOCITY_TOLERANCE_M_S:
        raise InvalidParameterError(
            f"{what} jumps at t = {traj.t_s[k + 1]:.4f} s (node {k + 1}): its position is {1e3 * dp[k]:.3f} mm and "
            f"its velocity {dv[k]:.4f} m/s away from where its own motion from the node before leads "
            f"(allowed: {1e3 * NODE_POSITION_TOLERANCE_M:g} mm, {NODE_VELOCITY_TOLERANCE_M_S:g} m/s); "
            "a device cannot jump: plan it again (falcon-plan plan --out)")
    saturation = SaturationModel.of(model.params)
    limit = CommandBound("device", saturation.full, 0.0, saturation)
    check = dense_check(model, traj, limit, factor)
    if check.worst_margin < -1e-6:   # between its nodes (each node is inside)
        raise InvalidParameterError(
            f"{what} leaves the workspace between its nodes ({check.worst_margin_name}; leg angles "
            f"{-check.worst_angle_margin_deg:.1f} deg past a limit): every point must be inside it; plan it again")
    if check.worst_command_ratio <= 1.0 + EXECUTABLE_COMMAND_TOLERANCE:
        return None   # within L(w) <= the full range everywhere: no second pass needed
    over = dense_check(model, traj, CommandBound("constant", saturation.full, 0.0, saturation), factor)
    if over.worst_command_ratio > 1.0 + EXECUTABLE_COMMAND_TOLERANCE:
        raise InvalidParameterError(
            f"{what} needs |Tc| = {over.worst_command_ratio * saturation.full:.0f} at t = "
            f"{over.worst_command_time_s:.4f} s, more than the device can give ({saturation.full:g}); allowed: "
            f"at most {saturation.full:g} (the device's limit L(w): {limit.describe()}); plan it again, or give it "
            "more time")
    return (f"{what} needs {100 * (check.worst_command_ratio - 1):.1f} % more command than the device's "
            f"speed-dependent limit allows at t = {check.worst_command_time_s:.4f} s: it may not be tracked "
            "exactly there")


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


__all__ = ["DenseCheck", "dense_check", "dense_times", "node_gaps", "require_executable", "PlantCheck", "plant_check", "executed_limit_ratio",
           "log_limit_ratio", "PLANT_MAX_ERROR_MM", "PLANT_FINAL_ERROR_MM"]
