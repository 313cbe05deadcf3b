"""A smooth reference motion: the quintic point-to-point move, with feed-forward commands.

The end effector moves on the straight line from ``start`` to ``goal`` [m, base frame] with
the rest-to-rest quintic time law s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5, tau = t / T, so
position, velocity and acceleration are continuous and zero velocity and acceleration hold at
both ends. The feed-forward commands are the model's inverse dynamics along it. It serves as
a test and benchmark fixture and as a planner-free fallback for the ``execute`` command; it
is not time-optimal (peak speed 1.875 x the mean).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.workspace import require_in_workspace
from falcon_plan.trajectory import Trajectory

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel



def _time_law(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s, ds/dtau, d2s/dtau2 of the quintic at tau in [0, 1]."""
    s = tau ** 3 * (10.0 - 15.0 * tau + 6.0 * tau ** 2)
    ds = 30.0 * tau ** 2 * (1.0 - tau) ** 2
    dds = 60.0 * tau * (1.0 - tau) * (1.0 - 2.0 * tau)
    return s, ds, dds


def _build(start: np.ndarray, goal: np.ndarray, duration_s: float, model: FalconModel,
           rate_hz: float) -> Trajectory:
    n = max(int(math.ceil(duration_s * rate_hz)), 2)
    t = np.linspace(0.0, duration_s, n + 1)
    s, ds, dds = _time_law(t / duration_s)
    delta = goal - start
    pos = start + s[:, None] * delta
    vel = (ds / duration_s)[:, None] * delta
    acc = (dds / duration_s ** 2)[:, None] * delta
    cmd = model.inverse_dynamics(pos, vel, acc)
    return Trajectory(t, pos, vel, acc, cmd, model.params.name, "quintic",
                      {"duration_s": duration_s, "rate_hz": rate_hz})


def quintic_trajectory(start_m: Any, goal_m: Any, model: FalconModel, duration_s: float | None = None,
                       *, rate_hz: float = 800.0, tc_max: float = 2500.0) -> Trajectory:
    """The quintic move from ``start_m`` to ``goal_m`` [m] with feed-forward commands.

    Parameters
    ----------
    start_m, goal_m : (3,) end-effector points [m]; both, and the line between them, must be
        in ``model``'s workspace.
    model : FalconModel whose inverse dynamics give the feed-forward commands.
    duration_s : move time [s]; None picks the shortest one (to 1 ms) whose feed-forward
        stays within +-``tc_max`` [command units].
    rate_hz : sample rate of the returned trajectory [Hz].

    Raises
    ------
    WorkspaceError : the line leaves the workspace.
    InvalidProblemError : bad duration, or no duration up to 10 s keeps within ``tc_max``.
    """
    start = np.asarray(start_m, dtype=float).reshape(3)
    goal = np.asarray(goal_m, dtype=float).reshape(3)
    line = start + np.linspace(0.0, 1.0, 51)[:, None] * (goal - start)
    require_in_workspace(line, model.params, model.limits, what="quintic path point")
    if duration_s is not None:
        if not (math.isfinite(duration_s) and duration_s > 0):
            raise InvalidProblemError(f"duration_s must be a positive number, got {duration_s!r}")
        return _build(start, goal, float(duration_s), model, rate_hz)

    def peak(duration: float) -> float:
        return float(np.abs(_build(start, goal, duration, model, 400.0).commands).max())

    hi = 10.0
    if peak(hi) > tc_max:
        raise InvalidProblemError(
            f"no quintic move up to {hi} s keeps the feed-forward within +-{tc_max} (gravity alone "
            "may exceed it)")
    lo = 1e-3
    while hi - lo > 1e-3:
        mid = math.sqrt(lo * hi) if hi / lo > 4 else 0.5 * (lo + hi)
        lo, hi = (mid, hi) if peak(mid) > tc_max else (lo, mid)
    return _build(start, goal, hi, model, rate_hz)
