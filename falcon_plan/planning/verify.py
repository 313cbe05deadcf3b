"""Independent checks of a planned trajectory.

- :func:`dense_check`: the constraints re-checked on the *continuous* trajectory (its own
  piecewise-constant-acceleration interpolation) at ``factor`` points per interval (default
  10, so 10x the planner's grid): commands by the model's inverse dynamics against tc_max,
  and the workspace margins (>= 0 inside). This is what says the limit holds *between* the
  nodes, not only where the optimiser imposed it.
- :func:`plant_check`: a closed-loop run on the simulated plant (SimPlant + the paper's
  encoder PD, with the trajectory's commands as feed-forward advanced by the plant's command
  delay); skipped with a note when the simulator is not available.

- :func:`grid_refinement`: the duration's change when the same problem is solved on twice
  as many intervals (warm-started from the plan itself, each interval split in two).
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import angles_to_counts, counts_to_position, inverse_kinematics
from falcon_plan.model.workspace import CONSTRAINT_NAMES
from falcon_plan.planning.trajectory import Trajectory

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

    worst_command_ratio : max over time and motors of |Tc| / tc_max (<= 1 means within).
    worst_command_time_s : where it occurs [s].
    worst_margin : smallest workspace margin (>= 0 inside; radians for the angle rows, sine
        or determinant units for the others, see workspace.CONSTRAINT_NAMES).
    worst_margin_name : which margin (name and leg).
    n_points : points checked.
    """

    worst_command_ratio: float
    worst_command_time_s: float
    worst_margin: float
    worst_margin_name: str
    n_points: int

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


def dense_check(model: FalconModel, traj: Trajectory, tc_max: float, factor: int = 10) -> DenseCheck:
    """Re-check |Tc| <= tc_max and the workspace at ``factor`` points per interval.

    At each interval's start the acceleration is the interval's own (right limit); the
    interval's end is covered by the left limit evaluated separately, so both ends of every
    interval are checked as well as the inside.
    """
    t = dense_times(traj, factor)
    pos, vel, acc = traj.at_time(t)
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
    ratio = np.abs(tc).max(axis=1) / tc_max
    i = int(np.argmax(ratio))
    margins = model.workspace_margins(pos)
    j = np.unravel_index(int(np.argmin(margins)), margins.shape)
    return DenseCheck(float(ratio[i]), float(all_t[i]), float(margins[j]), _margin_name(int(j[1])),
                      int(len(all_t)))


def _margin_name(row: int) -> str:
    """Name of row ``row`` of workspace_margins (CONSTRAINT_NAMES x legs, then the det)."""
    per_leg = len(CONSTRAINT_NAMES) - 1
    if row < 3 * per_leg:
        return f"{CONSTRAINT_NAMES[row // 3]} (leg {row % 3})"
    return CONSTRAINT_NAMES[-1]


@dataclass(frozen=True)
class PlantCheck:
    """Result of :func:`plant_check` (``ran`` False with a ``note`` when skipped)."""

    ran: bool
    passed: bool | None
    max_error_mm: float | None
    final_error_mm: float | None
    max_command: float | None
    rate_hz: float | None
    run_time_s: float
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def plant_check(model: FalconModel, traj: Trajectory, *, rate_hz: float = 800.0,
                settle_s: float = 0.3) -> PlantCheck:
    """Run ``traj`` closed loop on the simulated plant (``model``'s dynamics and effects) under
    the executor's controller (:meth:`falcon_plan.control.Controller.executor_default`: PD
    with the derivative on the error and ``model``'s feed-forward two samples ahead, the same
    value the executor runs), after a hold at the start; errors are measured against the plan
    from the encoder counts.

    Passes when the Cartesian error stays below :data:`PLANT_MAX_ERROR_MM` and ends within
    :data:`PLANT_FINAL_ERROR_MM` ``settle_s`` after the end. Skipped (ran False, note) when
    ``falcon_plan.sim`` is not importable; a plant error (the device leaving the workspace)
    is reported as a failure with its message.
    """
    t0 = time.perf_counter()
    try:
        from falcon_plan.control import Controller
        from falcon_plan.sim.plant import SimPlant
    except ImportError as exc:
        return PlantCheck(False, None, None, None, None, None, 0.0, f"simulated plant not available: {exc}")
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
        measured = counts_to_position(run.counts[k_hold:].astype(float), model.params)
        err_mm = 1e3 * np.linalg.norm(measured - pos[k_hold:], axis=1)
        final_mm = 1e3 * float(np.linalg.norm(plant.position_m - traj.position_m[-1]))
    except Exception as exc:  # the plant is another engineer's code: report, never crash the plan
        log.warning("plant check failed: %s", exc)
        return PlantCheck(True, False, None, None, None, rate_hz, time.perf_counter() - t0,
                          f"plant run failed: {type(exc).__name__}: {exc}")
    max_err = float(err_mm.max())
    passed = max_err <= PLANT_MAX_ERROR_MM and final_mm <= PLANT_FINAL_ERROR_MM
    return PlantCheck(True, passed, max_err, final_mm, float(np.abs(run.commands[k_hold:]).max()), rate_hz,
                      time.perf_counter() - t0)


@dataclass(frozen=True)
class RefinementCheck:
    """Result of :func:`grid_refinement`: the duration at 2N [s] (None if that solve failed),
    its relative change (T_2N - T_N) / T_N, and the solver status."""

    n_intervals: int
    duration_s: float | None
    change: float | None
    solver_status: str
    solve_time_s: float


def upsample_guess(traj: Trajectory, factor: int = 2) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """The same motion on ``factor`` times as many intervals, as a planner guess (T, p, v, a):
    exact, since each interval is split without changing its constant acceleration."""
    t = np.linspace(0.0, traj.duration_s, factor * (len(traj.t_s) - 1) + 1)
    pos, vel, _ = traj.at_time(t)
    acc = np.repeat(traj.acceleration_m_s2[:-1], factor, axis=0)
    return traj.duration_s, pos, vel, acc


def grid_refinement(model: FalconModel, problem: Any, traj: Trajectory, tc_max: float,
                    hessian: str = "limited-memory") -> RefinementCheck:
    """Solve ``problem`` again with twice the intervals of ``traj`` (the planner's result)."""
    from falcon_plan.planning.casadi_planner import solve_min_time

    n2 = 2 * (len(traj.t_s) - 1)
    fine = solve_min_time(model, problem, n_intervals=n2, tc_max=tc_max, hessian=hessian,
                          guess=upsample_guess(traj))
    if not fine.success:
        return RefinementCheck(n2, None, None, fine.solver_status, fine.solve_time_s)
    return RefinementCheck(n2, fine.duration_s, (fine.duration_s - traj.duration_s) / traj.duration_s,
                           fine.solver_status, fine.solve_time_s)


__all__ = ["DenseCheck", "RefinementCheck", "grid_refinement", "upsample_guess", "dense_check", "dense_times", "PlantCheck", "plant_check",
           "PLANT_MAX_ERROR_MM", "PLANT_FINAL_ERROR_MM"]
