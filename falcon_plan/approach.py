"""Running a trajectory from wherever the device is: home if needed, a planned approach move
to the trajectory's start, then the trajectory, all in one executor run (one log).

The approach is the quintic straight-line move (:mod:`falcon_plan.planning.quintic`) from
the measured position to the trajectory's start, as fast as keeps its feed-forward within
:data:`APPROACH_TC_MAX` (a gentle move, not a minimum-time one), followed directly by the
trajectory (both are at rest at the junction). It runs in the same executor run as the
trajectory, so the device is held throughout: two runs would drop the force in between.
The log therefore holds the pre-roll, the approach and the trajectory; the replay and the
identification use all of it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.trajectory import Trajectory

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device
    from falcon_plan.execution.executor import ExecutionReport
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.recording.live import LiveView

APPROACH_TOLERANCE_M = 0.5e-3
"""No approach move when the device is this close to the trajectory's start [m] (the
executor's start check allows 3 mm)."""
JOIN_TOLERANCE_M = 1e-6
"""Trajectories join when the first ends within this of the second's start [m], both slower
than this [m/s] there (planners meet their boundary conditions to about 1e-9)."""
JOIN_RAMP_S = 1e-5
"""Where the two trajectories' accelerations differ at the junction (a minimum-time plan
still brakes at full command the moment it arrives), the joined trajectory ramps from one to
the other over this long [s]: to the device, at 1 kHz, a step. Joining at one node would
instead bend the first trajectory's last interval toward the second's acceleration (with a
linear profile) and move its end off the junction."""
APPROACH_TC_MAX = 1500.0
"""Peak feed-forward of the approach move [command units] (the planner's default is 2500)."""


def _holds_still(traj: Trajectory) -> bool:
    """True for a trajectory at rest throughout (any interpolation describes it exactly)."""
    return not (np.any(traj.velocity_m_s) or np.any(traj.acceleration_m_s2))


def _as_linear(traj: Trajectory) -> Trajectory:
    """``traj`` with its acceleration read as linear between samples: a piecewise-constant one
    gets, inside every interval, a sample :data:`JOIN_RAMP_S` after its start, so that the
    acceleration ramps to the interval's value over that long and then stays (the same motion
    to within the ramp)."""
    if traj.interpolation == "linear":
        return traj
    h = np.diff(traj.t_s)
    ramp = np.minimum(JOIN_RAMP_S, 0.5 * h)[:, None]
    a = traj.acceleration_m_s2[:-1]
    p_in = traj.position_m[:-1] + traj.velocity_m_s[:-1] * ramp + 0.5 * a * ramp ** 2
    v_in = traj.velocity_m_s[:-1] + a * ramp

    def woven(nodes: np.ndarray, inside: np.ndarray) -> np.ndarray:
        out = np.empty((2 * len(nodes) - 1,) + nodes.shape[1:])
        out[0::2], out[1::2] = nodes, inside
        return out

    # each sample carries the acceleration of the interval before it (the first, its own)
    acc_nodes = np.vstack([a[:1], a])
    return Trajectory(woven(traj.t_s, traj.t_s[:-1] + ramp[:, 0]), woven(traj.position_m, p_in),
                      woven(traj.velocity_m_s, v_in), woven(acc_nodes, a), woven(traj.commands, traj.commands[:-1]),
                      traj.params_name, traj.source, dict(traj.meta), "linear")


def concatenate(first: Trajectory, second: Trajectory) -> Trajectory:
    """``first`` then ``second`` (shifted in time); ``first`` must end where ``second``
    starts, both at rest there, and both must interpolate their accelerations alike unless
    one of them holds still (InvalidProblemError otherwise). A change of acceleration at the
    junction becomes a ramp of :data:`JOIN_RAMP_S`."""
    if first.params_name != second.params_name:
        raise InvalidProblemError(f"cannot join trajectories of parameter sets {first.params_name!r} "
                                  f"and {second.params_name!r}")
    gap = float(np.linalg.norm(first.position_m[-1] - second.position_m[0]))
    moving = max(float(np.abs(first.velocity_m_s[-1]).max()), float(np.abs(second.velocity_m_s[0]).max()))
    if gap > JOIN_TOLERANCE_M or moving > JOIN_TOLERANCE_M:
        raise InvalidProblemError(f"trajectories join only at rest at one point (gap {gap:.3g} m, "
                                  f"speed {moving:.3g} m/s at the junction)")
    if first.interpolation == second.interpolation or _holds_still(second):
        interpolation = first.interpolation
    elif _holds_still(first):
        interpolation = second.interpolation
    else:  # one of each: read the piecewise-constant one as linear with ramps at its nodes
        interpolation = "linear"
        first, second = _as_linear(first), _as_linear(second)
    ramp = 0.0 if np.allclose(first.acceleration_m_s2[-1], second.acceleration_m_s2[0]) else JOIN_RAMP_S
    keep = len(first.t_s) if ramp else len(first.t_s) - 1
    t = np.concatenate([first.t_s[:keep], second.t_s - second.t_s[0] + first.t_s[-1] + ramp])
    stack = lambda name: np.vstack([getattr(first, name)[:keep], getattr(second, name)])  # noqa: E731
    return Trajectory(t - t[0], stack("position_m"), stack("velocity_m_s"), stack("acceleration_m_s2"),
                      stack("commands"), second.params_name, second.source, dict(second.meta), interpolation)


def with_approach(trajectory: Trajectory, here_m: Any, model: FalconModel, rate_hz: float) -> Trajectory:
    """``trajectory`` preceded by the approach move from ``here_m`` [m, base frame] to its
    start (the trajectory itself when already within :data:`APPROACH_TOLERANCE_M`), planned
    with ``model`` at ``rate_hz`` [Hz] (the executor's rate). ``meta["approach_s"]`` is the
    approach's duration [s] (absent without an approach). Raises WorkspaceError if the
    straight line to the start leaves the workspace."""
    from falcon_plan.planning.quintic import quintic_trajectory

    here = np.asarray(here_m, dtype=float).reshape(3)
    start = trajectory.position_m[0]
    if np.linalg.norm(here - start) <= APPROACH_TOLERANCE_M:
        return trajectory
    move = quintic_trajectory(here, start, model, rate_hz=rate_hz, tc_max=APPROACH_TC_MAX)
    joined = concatenate(move, trajectory)
    return Trajectory(joined.t_s, joined.position_m, joined.velocity_m_s, joined.acceleration_m_s2,
                      joined.commands, joined.params_name, joined.source,
                      {**joined.meta, "approach_s": move.duration_s}, joined.interpolation)


def home_if_needed(device: Device, kind: str) -> None:
    """Home the ``device`` unless it is homed; ``kind`` is its
    :data:`~falcon_plan.execution.device_factory.DEVICE_KINDS` entry (for "usb" the user is
    told to move the grip, as a real Falcon homes only when the grip moves)."""
    if not device.homed:
        if kind == "usb":
            print("homing: pull the grip fully out, then push it back in", file=sys.stderr)
        device.home()


def run_from_here(device: Device, kind: str, trajectory: Trajectory, model: FalconModel, *,
                  log_path: str | Path | None = None, mcap: str | Path | None = None, live: LiveView | None = None,
                  plan_report: dict[str, Any] | None = None,
                  **executor_options: Any) -> tuple[ExecutionReport, float]:
    """Home ``device`` if needed (``kind`` as in :func:`home_if_needed`), read where it is,
    and execute the approach move and ``trajectory`` in one
    :class:`~falcon_plan.execution.executor.Executor` run with ``model`` (its feed-forward
    and its parameters for forward kinematics); ``executor_options`` go to the Executor
    (rate_hz, pace, preroll_s, settle_s, controller, ...). Returns the
    ExecutionReport and the approach's duration [s] (0 when none was needed):
    ``trajectory`` starts at that time after the pre-roll.

    The run's records: ``log_path`` the falcon log (CSV; a ``.mcap`` path gets an MCAP
    recording instead), ``mcap`` an MCAP recording beside it, ``live`` a
    :class:`~falcon_plan.recording.live.LiveView` that shows the run; the recording holds the
    trajectory actually run (approach included) with ``plan_report``, the planner's report."""
    from falcon_plan.execution.device_factory import read_position
    from falcon_plan.execution.executor import Executor
    from falcon_plan.recording.recorder import open_recorder

    if log_path is not None and Path(log_path).suffix.lower() == ".mcap":
        if mcap is not None:
            raise InvalidProblemError("give the MCAP recording once: as the log path or as mcap, not both")
        mcap, log_path = log_path, None
    if mcap is not None and log_path is not None and Path(mcap).resolve() == Path(log_path).resolve():
        raise InvalidProblemError(f"the MCAP recording and the falcon log are the same file ({mcap}); give two names")
    home_if_needed(device, kind)
    here = read_position(device, model.params)  # one zero-force tick
    recorder = open_recorder(mcap, live)
    with recorder if recorder is not None else contextlib.nullcontext():
        executor = Executor(device, model, log_path=log_path, zero_force_periods_before=1, sink=recorder,
                            **executor_options)
        full = with_approach(trajectory, here, model, executor.rate_hz)
        if recorder is not None:
            recorder.plan(full, plan_report)
        report = executor.run(full)
    if log_path is None and mcap is not None:
        report = dataclasses.replace(report, log_path=str(mcap))
    return report, float(full.meta.get("approach_s", 0.0))


__all__ = ["concatenate", "with_approach", "home_if_needed", "run_from_here",
           "APPROACH_TOLERANCE_M", "APPROACH_TC_MAX"]
