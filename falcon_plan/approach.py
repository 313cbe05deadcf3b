"""Running a trajectory from wherever the device is: home if needed, a planned approach move
to the trajectory's start, a hold there, then the trajectory, all in one executor run (one log).

A bumpless start. After homing, or after a run that let go, a Falcon is moving, usually
falling. A paced run (a device that lives in wall-clock time) is held from the moment it is
handed over: a :class:`~falcon_plan.execution.holding.HoldLoop` runs the executor's controller
at the loop rate, brakes the device where it is and holds it there with gravity compensation
while the run is prepared (the approach, the controller's gain schedule: tens to hundreds of
milliseconds in which a device given zero force would fall), and the run takes the device over
from the hold at its first tick; the approach starts from the held point at rest. A device that
lives only when driven (a simulation stepped as fast as it goes: no time passes while the host
computes) is measured instead: a few zero-force ticks give its position and its velocity
(:func:`measure_state`), and the approach (:func:`approach_from_state`) starts from that state,
velocity included, and from the acceleration the device has under zero force (so its
feed-forward starts at zero and the gravity compensation comes in smoothly as the approach
brakes). Either way the approach ends at rest at the trajectory's start: a quintic in each
coordinate, as fast as keeps its feed-forward within :data:`APPROACH_TC_MAX` (a gentle move,
not a minimum-time one). The start is then held for the pre-roll before the trajectory, so the
hold begins settled. When the device is already at the start and still, there is no approach:
the executor's pre-roll holds it there. Everything runs in one executor run, so the device is
held throughout (two runs would drop the force in between); the log holds the approach, the
hold and the trajectory, and the replay and the identification use all of it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import sys
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device
    from falcon_plan.execution.executor import ExecutionReport, Executor
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
STILL_SPEED_M_S = 2e-3
"""A device measured slower than this is still [m/s] (a count per 20 ms near the centre)."""
MEASURE_TICKS = 4
"""Zero-force ticks that measure the device's state before a run (3 count differences)."""
BRAKING_TC_MAX = 2350.0
"""Peak feed-forward when braking a moving device [command units]: the planner's default bound
(2500 less the feedback reserve)."""
BRAKING_REACH = (0.5, 0.4, 0.6, 0.3)
"""Braking quintics tried per duration T: rest at the start point plus this times T times the
start velocity (0.5: as far as a constant deceleration would go)."""


@dataclass(frozen=True)
class MeasuredState:
    """Where the device is and how it moves, at the tick after the last reading (the
    executor's first): ``position_m`` [m], ``velocity_m_s`` [m/s], base frame."""

    position_m: np.ndarray
    velocity_m_s: np.ndarray

    @property
    def still(self) -> bool:
        """Slower than :data:`STILL_SPEED_M_S`."""
        return float(np.linalg.norm(self.velocity_m_s)) < STILL_SPEED_M_S


def measure_state(device: Device, params: Any, ticks: int = MEASURE_TICKS) -> MeasuredState:
    """The ``device``'s state from ``ticks`` zero-force exchanges (>= 2): counts fitted by a
    straight line in time (least squares; whole counts; the readings' own time on a device that
    keeps wall-clock time, one period per exchange on one that steps per packet, its
    ``device_clock``; a reading whose time repeats the previous one is the same reading again,
    as threaded USB I/O returns when no new status came, and counts once), position and
    velocity of the fit extrapolated one period past the last exchange, to when the executor's
    first reading is taken, through the
    forward kinematics and the Jacobian of ``params``. Raises SafetyStop if the counts have no
    forward-kinematic solution."""
    from falcon_plan.errors import KinematicsError, SafetyStop
    from falcon_plan.model.kinematics import counts_to_position, jacobian

    readings = [device.exchange(np.zeros(3, dtype=np.int64)) for _ in range(max(2, int(ticks)))]
    period = 1.0 / float(device.rate_hz)
    fresh = [i for i, r in enumerate(readings) if i == 0 or r.t_s != readings[i - 1].t_s]
    counts = np.array([np.asarray(readings[i].counts, dtype=float) for i in fresh])
    if getattr(device, "device_clock", "wall") == "ticks":   # it lives one period per exchange
        t = (np.array(fresh, dtype=float) - (len(readings) - 1)) * period
    else:                                                     # it keeps its own time
        t = np.array([readings[i].t_s for i in fresh]) - readings[-1].t_s
    if len(fresh) < 2:             # nothing new came: still, as far as can be told
        slope, at_next = np.zeros(3), counts[-1]
    else:
        slope, intercept = np.polyfit(t, counts, 1)      # [counts/s], [counts]
        at_next = intercept + slope * period
    try:
        position = counts_to_position(at_next, params)
    except KinematicsError as exc:
        raise SafetyStop(f"measured counts {counts[-1].tolist()} have no forward-kinematic solution ({exc})") from exc
    leg_rate = slope / params.counts_per_rad
    return MeasuredState(position, np.linalg.solve(jacobian(position, params), leg_rate))


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


def _quintic_coefficients(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, p1: np.ndarray,
                          duration: float) -> np.ndarray:
    """(6, 3) coefficients c_i of p(t) = sum c_i t^i from (p0, v0, a0) at 0 to (p1, 0, 0) at T."""
    t = duration
    d = p1 - p0 - v0 * t - 0.5 * a0 * t * t
    e = -v0 - a0 * t
    f = -a0
    c3 = (10 * d - 4 * e * t + 0.5 * f * t * t) / t ** 3
    c4 = (-15 * d + 7 * e * t - f * t * t) / t ** 4
    c5 = (6 * d - 3 * e * t + 0.5 * f * t * t) / t ** 5
    return np.array([p0, v0, 0.5 * a0, c3, c4, c5])


def _quintic_samples(p0: np.ndarray, v0: np.ndarray, a0: np.ndarray, p1: np.ndarray, duration: float,
                     rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, position, velocity, acceleration) of the quintic sampled at ``rate_hz``."""
    n = max(int(math.ceil(duration * rate_hz)), 2)
    t = np.linspace(0.0, duration, n + 1)
    c = _quintic_coefficients(p0, v0, a0, p1, duration)
    powers = t[:, None] ** np.arange(6)
    pos = powers @ c
    vel = (powers[:, :5] * np.arange(1, 6)) @ c[1:]
    acc = (powers[:, :4] * np.array([2.0, 6.0, 12.0, 20.0])) @ c[2:]
    return t, pos, vel, acc


def _braking(state: MeasuredState, model: FalconModel, tc_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, position, velocity, acceleration) at 400 Hz and the duration of the shortest quintic
    that brings the moving ``state`` to rest (free end point, from the zero-force acceleration)
    within +-``tc_max`` and the workspace; WorkspaceError if none up to 2 s does."""
    from falcon_plan.errors import WorkspaceError
    from falcon_plan.model.workspace import in_workspace

    p0, v0 = state.position_m, state.velocity_m_s
    a0 = np.asarray(model.forward_dynamics(p0, v0, np.zeros(3)), dtype=float)
    for duration in np.arange(0.02, 2.0, 0.005):
        for reach in BRAKING_REACH:
            samples = _quintic_samples(p0, v0, a0, p0 + reach * duration * v0, duration, 400.0)
            _, pos, vel, acc = samples
            if np.all(in_workspace(pos, model.params, model.limits)) \
                    and np.abs(model.inverse_dynamics(pos, vel, acc)).max() <= tc_max:
                return p0 + reach * duration * v0, a0, np.array(duration)
    raise WorkspaceError(f"the device moving at {np.round(v0, 3).tolist()} m/s from {np.round(p0, 4).tolist()} m "
                         f"cannot be brought to rest within the workspace and +-{tc_max:g} command units")


def approach_from_state(state: MeasuredState, start_m: Any, model: FalconModel, rate_hz: float,
                        tc_max: float = APPROACH_TC_MAX) -> Trajectory:
    """The approach from the measured ``state`` to ``start_m`` [m], at rest there, sampled at
    ``rate_hz`` [Hz]: for a moving device first the braking, a quintic in each coordinate from
    the state's position and velocity and the acceleration ``model`` gives the device under
    zero force (so the feed-forward starts near zero and the gravity compensation comes in
    with the braking) to rest at a free point ahead, the shortest within +-:data:`BRAKING_TC_MAX`;
    then the quintic straight-line move to ``start_m`` as fast as keeps its feed-forward within
    +-``tc_max`` [command units]. Raises WorkspaceError when either leaves the workspace."""
    from falcon_plan.planning.quintic import quintic_trajectory

    p1 = np.asarray(start_m, dtype=float).reshape(3)
    here = state.position_m
    braking = None
    if not state.still:
        stop, a0, duration = _braking(state, model, BRAKING_TC_MAX)
        t, pos, vel, acc = _quintic_samples(state.position_m, state.velocity_m_s, a0, stop, float(duration), rate_hz)
        braking = Trajectory(t, pos, vel, acc, model.inverse_dynamics(pos, vel, acc), model.params.name, "approach",
                             {"duration_s": float(duration), "rate_hz": rate_hz})
        here = stop
    if np.linalg.norm(here - p1) <= JOIN_TOLERANCE_M:
        return braking if braking is not None else hold(p1, 1.0 / rate_hz, model)
    move = quintic_trajectory(here, p1, model, rate_hz=rate_hz, tc_max=tc_max)
    return move if braking is None else concatenate(braking, move)


def hold(point_m: Any, duration_s: float, model: FalconModel) -> Trajectory:
    """Holding still at ``point_m`` [m] for ``duration_s`` [s] (> 0), the gravity feed-forward
    of ``model`` as its commands."""
    p = np.repeat(np.asarray(point_m, dtype=float).reshape(1, 3), 2, axis=0)
    zeros = np.zeros((2, 3))
    return Trajectory(np.array([0.0, duration_s]), p, zeros, zeros, model.holding_commands(p), model.params.name,
                      "hold", {"duration_s": duration_s})


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


def rehearse_after_homing(executor: Executor, start_m: Any, model: FalconModel) -> None:
    """Before any force, prepare and discard (:meth:`Executor.rehearse`) the kind of run that
    follows homing: the approach from the home pose (zero counts, where homing leaves the
    device) to ``start_m`` [m, base frame] and the hold there for the executor's pre-roll. The
    preparation of the real run then runs beside the hold without first-in-process work
    (kernels loaded, forward kinematics built, cache keys serialised: calls that hold the
    interpreter lock for 5-30 ms each, during which the hold cannot tick). A rehearsal that
    cannot be made (the home pose outside ``model``'s workspace, a start the run itself will
    refuse) is skipped: the real preparation says what is wrong."""
    from falcon_plan.errors import FalconPlanError
    from falcon_plan.model.kinematics import counts_to_position

    home = counts_to_position(np.zeros(3), model.effects.encoder_params(model.params)).reshape(3)
    try:
        move = approach_from_state(MeasuredState(home, np.zeros(3)), start_m, model, executor.rate_hz)
        held = hold(np.asarray(start_m, dtype=float).reshape(3), max(executor.preroll_s, 0.1), model)
        executor.rehearse(concatenate(move, held), move.duration_s)
    except FalconPlanError as exc:
        log.debug("no rehearsal of the preparation: %s", exc)


def run_from_here(device: Device, kind: str, trajectory: Trajectory, model: FalconModel, *,
                  log_path: str | Path | None = None, mcap: str | Path | None = None, live: LiveView | None = None,
                  plan_report: dict[str, Any] | None = None, cancel: threading.Event | None = None,
                  **executor_options: Any) -> tuple[ExecutionReport, float]:
    """Home ``device`` if needed (``kind`` as in :func:`home_if_needed`), hold it where it is
    (a paced run) or measure its state (:func:`measure_state`; see the module docstring), and
    execute the approach move from there, the hold at the
    start and ``trajectory`` in one :class:`~falcon_plan.execution.executor.Executor` run with
    ``model`` (its feed-forward and its parameters for forward kinematics);
    ``executor_options`` go to the Executor (rate_hz, pace, preroll_s, settle_s, controller,
    ...): with an approach, the pre-roll is the hold after it. The tracking error counts from
    the trajectory's start. Returns the ExecutionReport and the approach's duration [s] (0 when
    none was needed): ``trajectory`` starts at that time plus the pre-roll in the log.

    The run's records: ``log_path`` the falcon log (CSV; a ``.mcap`` path gets an MCAP
    recording instead), ``mcap`` an MCAP recording beside it, ``live`` a
    :class:`~falcon_plan.recording.live.LiveView` that shows the run; the recording holds the
    trajectory actually run (approach included) with ``plan_report``, the planner's report.
    ``cancel`` set mid-run stops it (the executor's safe stop, or zero force with ``release``)."""
    from falcon_plan.execution.executor import Executor
    from falcon_plan.execution.holding import HoldLoop
    from falcon_plan.recording.recorder import open_recorder

    if log_path is not None and Path(log_path).suffix.lower() == ".mcap":
        if mcap is not None:
            raise InvalidProblemError("give the MCAP recording once: as the log path or as mcap, not both")
        mcap, log_path = log_path, None
    if mcap is not None and log_path is not None and Path(mcap).resolve() == Path(log_path).resolve():
        raise InvalidProblemError(f"the MCAP recording and the falcon log are the same file ({mcap}); give two names")
    executor = Executor(device, model, log_path=log_path, **executor_options)
    if executor.pace:
        rehearse_after_homing(executor, trajectory.position_m[0], model)
    holding = HoldLoop(executor) if executor.pace else None     # its law designed before any force
    home_if_needed(device, kind)
    preroll_s, start = executor.preroll_s, trajectory.position_m[0]
    with holding if holding is not None else contextlib.nullcontext():   # holding from here on
        if holding is not None:   # braked and settled before the preparation competes for the CPU
            holding.wait_settled()
        recorder = open_recorder(mcap, live)
        with recorder if recorder is not None else contextlib.nullcontext():
            executor.sink = recorder
            if holding is None:   # no time passes while the host computes: measure, then prepare
                state = measure_state(device, model.params)
                executor.zero_force_periods_before = MEASURE_TICKS
            else:                 # held where it was; prepared meanwhile
                state = MeasuredState(holding.point_m, np.zeros(3))
            if state.still and np.linalg.norm(state.position_m - start) <= APPROACH_TOLERANCE_M:
                full, approach_s = trajectory, 0.0
            else:
                move = approach_from_state(state, start, model, executor.rate_hz)
                full = concatenate(move, trajectory) if preroll_s == 0 else \
                    concatenate(concatenate(move, hold(start, preroll_s, model)), trajectory)
                approach_s, executor.preroll_s = move.duration_s, 0.0
                executor.approach_s = approach_s
            motion_start_s = full.duration_s - trajectory.duration_s if approach_s else 0.0
            executor.prepare(full, motion_start_s)
            if recorder is not None:
                recorder.plan(full, plan_report)
            if holding is not None:
                holding.wait_settled()   # still there (raises what ended the hold, if anything)
            report = executor.run(full, cancel=cancel, motion_start_s=motion_start_s, hold=holding)
    if log_path is None and mcap is not None:
        report = dataclasses.replace(report, log_path=str(mcap))
    return report, approach_s


__all__ = ["concatenate", "with_approach", "home_if_needed", "run_from_here", "measure_state",
           "approach_from_state", "hold", "rehearse_after_homing", "MeasuredState", "APPROACH_TOLERANCE_M", "APPROACH_TC_MAX"]
