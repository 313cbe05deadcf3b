"""Safety of trajectory execution, independent of the caller.

The executor applies every check below on every run; a caller can tighten the bounds
(:class:`SafetyConfig`) but not switch them off.

- **No force before homing**: :func:`require_homed` refuses to start (the encoder zero is
  meaningless until all legs are homed).
- **Start where the plan starts**: :func:`require_near_start` refuses when the measured
  position is far from the trajectory's first point (the PD would otherwise jump).
- **Command clamp**: the control law clamps to +-``command_limit`` (at most the device's
  4096, which the device clamps to again, so the 16-bit wire value never wraps);
  :func:`require_finite_commands` stops a NaN before it reaches the device.
- **Watchdog**: :class:`Watchdog`, a thread that calls a trip action (zero force) when the
  loop has not kicked it for ``watchdog_timeout_s`` (default 50 ms, at most
  :data:`WATCHDOG_MAX_S`). Nothing public says the Falcon's firmware ever drops a command by
  itself (libnifalcon documents no timeout), so the project assumes it keeps the last one
  forever: this watchdog, the device's own watchdog thread
  (:class:`~falcon_plan.devices.base.BaseDevice`, ``watchdog_s``) and the device's exit
  hooks (atexit, SIGINT, SIGTERM) are what end the force, never the firmware.
- **Workspace guard**: :class:`WorkspaceGuard` takes the *measured* counts to a position by
  warm-started forward kinematics and stops when it leaves the workspace widened by
  ``workspace_slack_rad`` (the planner keeps inside the limits; the slack keeps tracking
  error from tripping the guard).
- **Plausible readings**: :class:`TickGuard` is the set of per-tick checks the one force loop
  (:class:`~falcon_plan.execution.force_loop.ForceLoop`: the executor's run, the hold before it,
  the doctor's holds) makes on each reading, and it sends each command through a
  :class:`WatchedExchange` (the finite check, the loop's watchdog): no leg faster than
  :data:`MAX_LEG_SPEED_RAD_S` since the previous reading, then the workspace guard, then, in a
  loop that follows a reference (the run, the hold, the doctor's PD), no leg farther than
  ``max_tracking_error_counts`` from it: a controller that lost the device (ringing at the
  command limit, as a design that took friction for damping did) or a grip held far off its
  path ends the loop with zero force instead of fighting on.
- **Zero force on every exit**: :func:`zero_force_best_effort` never raises, so it can run
  in a ``finally`` without masking the original error; it returns what kept zero from the
  device, and the executor puts that in its report (a run whose final zero failed is a
  device error, never "completed").
- **A failing device ends the run**: any exception from the device's exchange (a
  :class:`~falcon_plan.errors.DeviceError`, or any other type, which the executor wraps in
  one naming it) ends the run with status ``device_error`` and that message; the USB
  driver's own guards (a failed I/O thread, no status for the silence bound) make sure a
  device that stopped answering cannot look like one that holds still.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import DeviceError, InvalidParameterError, KinematicsError, SafetyStop
from falcon_plan.model.kinematics import MATH_OPS, PositionTracker, leg_equations, scalar_leg_frames
from falcon_plan.model.params import ACRA2009, FalconParams
from falcon_plan.model.workspace import (CONSTRAINT_NAMES, DEFAULT_LIMITS, WorkspaceLimits, bar_determinant,
                                         workspace_constraint_values)
from falcon_plan.timing import DeadlineTimer, realtime_thread

if TYPE_CHECKING:
    from falcon_plan.compiled import BufferedFunction
    from falcon_plan.devices.base import Device, DeviceReading

log = logging.getLogger(__name__)

WATCHDOG_MAX_S = 0.1
"""Longest allowed watchdog bound [s]: the longest a stalled loop may leave a stale command
applied (the firmware may keep it forever)."""
MAX_TRACKING_ERROR_COUNTS = 250.0
"""Largest allowed tracking-error bound [counts] (0.16 rad of leg angle, about 10 mm at the
grip), the default. A device that follows its controller stays within it (measured on a
minimum-time plan with effects the model does not know: 40 g and Coulomb friction, LQR 23
counts, PD 58; 0.1 kg, PD 106; cables of 40 N.m/rad, LQR 169; a falling device caught by the
hold, 57); one the controller has lost passes it within a few of its swings (a hold ringing at
the command limit, 200-377 counts; a run on a design that took friction for damping, 326)."""


@dataclass(frozen=True)
class SafetyConfig:
    """Bounds of the execution safety checks (tighten them; they cannot be switched off).

    Attributes
    ----------
    command_limit : commands are clamped to +-this [command units], 1..4096.
    watchdog_timeout_s : zero force when the loop stalls longer than this [s], in
        (0, WATCHDOG_MAX_S].
    workspace_slack_rad : the guard's workspace is the model's limits widened by this on every
        angle [rad], >= 0.
    max_start_error_m : refuse to start when the measured position is farther than this from
        the trajectory's first point [m], > 0.
    max_tracking_error_counts : stop (zero force) when a leg reads farther than this from its
        reference [counts], in (0, :data:`MAX_TRACKING_ERROR_COUNTS`].
    """

    command_limit: int = ACRA2009.command_limit
    watchdog_timeout_s: float = 0.05
    workspace_slack_rad: float = math.radians(2.0)
    max_start_error_m: float = 0.003
    max_tracking_error_counts: float = MAX_TRACKING_ERROR_COUNTS

    def __post_init__(self) -> None:
        if (isinstance(self.command_limit, bool) or int(self.command_limit) != self.command_limit
                or not 1 <= self.command_limit <= ACRA2009.command_limit):
            raise InvalidParameterError(
                f"command_limit must be a whole number in [1, {ACRA2009.command_limit}], got {self.command_limit!r}")
        if not 0.0 < self.watchdog_timeout_s <= WATCHDOG_MAX_S:
            raise InvalidParameterError(
                f"watchdog_timeout_s must be in (0, {WATCHDOG_MAX_S}] s (the longest a stalled "
                f"loop may leave a command applied), got {self.watchdog_timeout_s!r}")
        if not (math.isfinite(self.workspace_slack_rad) and self.workspace_slack_rad >= 0.0):
            raise InvalidParameterError(f"workspace_slack_rad must be >= 0, got {self.workspace_slack_rad!r}")
        if not (math.isfinite(self.max_start_error_m) and self.max_start_error_m > 0.0):
            raise InvalidParameterError(f"max_start_error_m must be > 0, got {self.max_start_error_m!r}")
        if not 0.0 < self.max_tracking_error_counts <= MAX_TRACKING_ERROR_COUNTS:
            raise InvalidParameterError(f"max_tracking_error_counts must be in (0, {MAX_TRACKING_ERROR_COUNTS:g}] "
                                        f"counts, got {self.max_tracking_error_counts!r}")

    def to_dict(self) -> dict[str, float]:
        """JSON-ready dict (slack in degrees)."""
        return {"command_limit": int(self.command_limit), "watchdog_timeout_s": self.watchdog_timeout_s,
                "workspace_slack_deg": math.degrees(self.workspace_slack_rad),
                "max_start_error_mm": self.max_start_error_m * 1e3,
                "max_tracking_error_counts": self.max_tracking_error_counts}


def require_homed(device: Device) -> None:
    """Raise :class:`SafetyStop` unless ``device.homed`` is true (no force before homing)."""
    if not bool(getattr(device, "homed", False)):
        raise SafetyStop(
            f"refusing to run: {type(device).__name__} is not homed, so its encoder zero is "
            "meaningless; home it first (falcon-plan home, or device.home())")


def require_near_start(measured_m: Any, start_m: Any, max_error_m: float) -> None:
    """Raise :class:`SafetyStop` when ``measured_m``, the measured position (3,) [m, base
    frame], is farther than ``max_error_m`` [m] from ``start_m``, the trajectory's start
    (3,) [m, base frame]."""
    dist = float(np.linalg.norm(np.asarray(measured_m, float) - np.asarray(start_m, float)))
    if not dist <= max_error_m:
        raise SafetyStop(
            f"refusing to run: the device is at {np.round(np.asarray(measured_m) * 1e3, 2).tolist()} mm, "
            f"{dist * 1e3:.2f} mm from the trajectory start {np.round(np.asarray(start_m) * 1e3, 2).tolist()} mm "
            f"(allowed {max_error_m * 1e3:.2f} mm); plan from the current position")


def require_finite_commands(commands: Any) -> np.ndarray:
    """``commands`` (three motor commands [command units], array-like) as int64 (3,);
    :class:`SafetyStop` if they are not three finite numbers (a controller bug must not reach
    the motors). Clamping is the control law's (to ``command_limit``) and the
    device's (to 4096)."""
    arr = np.asarray(commands, dtype=float)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise SafetyStop(f"refusing to send motor commands {arr.tolist()}: not three finite numbers")
    return arr.astype(np.int64)


def exchange(device: Device, commands: np.ndarray) -> DeviceReading:
    """``device.exchange(commands)``: any failure of it is the device's, a
    :class:`~falcon_plan.errors.DeviceError` naming it (e.g. a raw ``usb.core.USBError``);
    DeviceError and SafetyStop pass as they are."""
    try:
        return device.exchange(commands)
    except (DeviceError, SafetyStop):
        raise
    except Exception as exc:  # any failure is the device's
        raise DeviceError(f"device I/O failed: {type(exc).__name__}: {exc}") from exc


def follow_deadlines(device: Device, timer: DeadlineTimer | None) -> None:
    """Tell ``device`` the deadlines (``timer``) of the loop that paces its exchanges from now on
    (None: no more), where it can use them (a USB Falcon with threaded I/O answers a late hand-over
    with the tick's own reading: :meth:`~falcon_plan.devices.usb_falcon.UsbFalcon.follow_deadlines`);
    other devices, and wrappers of them, need not know."""
    follow = getattr(device, "follow_deadlines", None)
    if follow is not None:
        follow(timer)


def zero_force_best_effort(device: Device) -> Exception | None:
    """Try ``device.zero_force()``; never raises. Returns the exception it hit (or None),
    which is logged, so that the caller's original error stays the one reported."""
    try:
        device.zero_force()
    except Exception as exc:  # noqa: BLE001 - best effort on an error path, by design
        log.warning("zero force failed (%s: %s)", type(exc).__name__, exc)
        return exc
    return None


class Watchdog:
    """A daemon thread that calls ``on_trip`` once when :meth:`kick` has not been called for
    ``timeout_s`` [s] (> 0), as measured by ``clock`` (a monotonic clock in seconds,
    ``time.perf_counter`` by default).

    Use as a context manager around the loop and kick it once per tick. After a trip,
    :attr:`tripped` is true and :attr:`reason` names the stall; the loop must stop (the trip
    action has zeroed the force). The check runs every ``timeout_s / 5``, so a stall is
    caught within 1.2 x ``timeout_s``. It needs the GIL: a stall inside a C call that holds
    the GIL delays the trip (I/O and sleeps release it).
    """

    def __init__(self, on_trip: Callable[[], None], timeout_s: float = 0.05,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        if not timeout_s > 0:
            raise InvalidParameterError(f"timeout_s must be positive, got {timeout_s!r}")
        self.timeout_s = float(timeout_s)
        self._on_trip = on_trip
        self._clock = clock
        self._last_kick = clock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.tripped = False
        self.reason = ""

    def kick(self) -> None:
        """Tell the watchdog the loop is alive."""
        self._last_kick = self._clock()

    def start(self) -> "Watchdog":
        """Start watching (the stall clock starts now)."""
        self.kick()
        self._thread = threading.Thread(target=self._watch, name="falcon-watchdog", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None

    def __enter__(self) -> "Watchdog":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _watch(self) -> None:
        realtime_thread()   # as the loop it watches: a normal thread holding the GIL would hold it back
        poll = self.timeout_s / 5.0
        while not self._stop.wait(poll):
            stalled = self._clock() - self._last_kick
            if stalled > self.timeout_s:
                self.reason = (f"watchdog: the control loop stalled for {stalled * 1e3:.1f} ms "
                               f"(bound {self.timeout_s * 1e3:.0f} ms); force zeroed")
                self.tripped = True
                log.error(self.reason)
                try:
                    self._on_trip()
                except Exception as exc:  # noqa: BLE001 - report, the loop stops anyway
                    log.error("watchdog trip action failed (%s: %s)", type(exc).__name__, exc)
                return


class WatchedExchange:
    """A force loop's exchanges with ``device`` under the loop's :class:`Watchdog`
    (:attr:`watchdog`, bound ``timeout_s`` [s]; the loop starts it and kicks it every tick).

    Calling it sends commands checked by :func:`require_finite_commands` through
    :func:`exchange` (any failure a :class:`~falcon_plan.errors.DeviceError`). When the watchdog
    trips it zeroes the force, after the exchange in progress if that ends within 5 ms, else at
    once (the loop is stuck inside the device call); every exchange after a trip raises
    :class:`~falcon_plan.errors.SafetyStop` naming the stall. Built by
    :class:`~falcon_plan.execution.force_loop.ForceLoop` only."""

    def __init__(self, device: Device, timeout_s: float) -> None:
        self.device = device
        self.watchdog = Watchdog(self._trip, timeout_s)
        self._lock = threading.Lock()
        self.sent = np.zeros(3, dtype=np.int64)
        """The commands of the last call that reached the device, as checked and sent (int64
        (3,)) [command units]."""

    def __call__(self, commands: Any) -> DeviceReading:
        """Send ``commands`` (3,) [command units] (kept in :attr:`sent`); the reading."""
        commands = require_finite_commands(commands)
        with self._lock:
            if self.watchdog.tripped:
                raise SafetyStop(self.watchdog.reason)
            reading = exchange(self.device, commands)
        self.sent = commands
        return reading

    def _trip(self) -> None:
        if self._lock.acquire(timeout=0.005):
            try:
                zero_force_best_effort(self.device)
            finally:
                self._lock.release()
        else:
            zero_force_best_effort(self.device)


"""Scalar operations for the model's "ops"-generic equations (a point at a time, no numpy)."""


GUARD_NEWTON_STEPS = 3
"""Newton steps of the compiled guard's warm-started forward kinematics (a tick moves the point
well under a millimetre, from which two steps already reach machine precision)."""
GUARD_RESIDUAL_M = 1e-9
"""Loop-closure residual [m] below which the compiled guard's position counts as converged."""
_guard_cache: dict[tuple[FalconParams, WorkspaceLimits], "tuple[Any, Any] | None"] = {}


def compiled_guard(params: FalconParams, limits: WorkspaceLimits) -> "BufferedFunction | None":
    """The guard's per-tick arithmetic as one compiled CasADi Function (C, built once per
    machine, loaded once per process; each call returns new buffers, so guards in several
    threads never share them): (counts (3), seed (3) [m]) -> (p (3) [m], max |loop residual|
    [m], workspace margins (3 legs x 4 + forward_det, :func:`workspace_constraint_values` at
    p, all >= 0 inside ``limits``)), p by :data:`GUARD_NEWTON_STEPS` Newton steps from the
    seed with the geometry and encoder scale of ``params``. None without a compiler."""
    from falcon_plan.compiled import BufferedFunction

    key = (params, limits)
    if key not in _guard_cache:
        import casadi as ca

        from falcon_plan.compiled import build_library
        from falcon_plan.model.kinematics import fk_newton_sx
        from falcon_plan.model.symbolic import CASADI_OPS, leg_angles_sx

        counts, seed = ca.SX.sym("counts", 3), ca.SX.sym("seed", 3)
        theta1 = params.theta_home_rad + counts / params.counts_per_rad
        p, residual = fk_newton_sx(theta1, seed, params, GUARD_NEWTON_STEPS)
        legs = leg_angles_sx(p, params)
        det = bar_determinant([legs.theta2[i] for i in range(3)], [legs.theta3[i] for i in range(3)],
                              params, CASADI_OPS)
        margins = workspace_constraint_values(legs.theta1, legs.theta2, legs.theta3, ca.fabs(det),
                                              limits, CASADI_OPS)
        # the library's cache key is its source, constants included: one name serves every set
        fn = ca.Function("falcon_workspace_guard", [counts, seed],
                         [p, residual, ca.vertcat(*margins)], {"cse": True})
        library = build_library(fn)
        _guard_cache[key] = (fn, library) if library is not None else None
    built = _guard_cache[key]
    return None if built is None else BufferedFunction(*built, hold_gil=True)   # a few us on the loop's thread


class WorkspaceGuard:
    """Stops when the measured state leaves the workspace.

    Each :meth:`check` takes encoder counts to leg angles and, by forward kinematics
    warm-started from the previous point, to the end-effector position [m, base frame] with
    the geometry of ``params``; then checks it against ``limits`` widened by ``slack_rad``
    [rad] (reachability, leg-angle range, knee and parallelogram margins, forward
    singularity). The per-tick path is one compiled call (:func:`compiled_guard`, a few µs);
    the first reading, a reading it cannot converge on, and any reading it finds outside
    take the scalar Python path (:class:`PositionTracker`, then ``leg_equations`` and
    ``workspace_constraint_values`` on floats, ~40 µs), which names the reason. Both use
    the same equations as :func:`~falcon_plan.model.workspace.check_workspace`; tests check
    that they agree.
    """

    def __init__(self, params: FalconParams = ACRA2009, limits: WorkspaceLimits = DEFAULT_LIMITS,
                 slack_rad: float = math.radians(2.0), compiled: bool = True) -> None:
        self.params = params
        self.limits = limits.scaled(-slack_rad)
        self._frames = scalar_leg_frames(params)
        self._tracker = PositionTracker(params)
        self._fast = compiled_guard(params, self.limits) if compiled else None
        self._seeded = False
        self.fast_checks = 0
        """Checks answered by the compiled path (the rest took the scalar one)."""

    @property
    def compiled(self) -> bool:
        """True when the per-tick path runs compiled C."""
        return self._fast is not None and self._fast.compiled

    def position(self, counts: Any) -> np.ndarray:
        """End-effector position [m] of measured counts (3,); SafetyStop if FK fails."""
        try:
            return self._tracker.position(counts)
        except KinematicsError as exc:
            raise SafetyStop(f"workspace guard: measured counts {np.asarray(counts).tolist()} have no "
                             f"forward-kinematic solution ({exc})") from exc

    def violation(self, p: Any) -> str:
        """Why point ``p`` [m, base frame] is outside the widened workspace ("" if inside)."""
        px, py, pz = (float(x) for x in p)
        angles = []
        try:
            for erx, ery, etx, ety in self._frames:
                eq = leg_equations(px * erx + py * ery, px * etx + py * ety, pz, self.params, MATH_OPS)
                angles.append((eq["theta1"], eq["theta2"], eq["theta3"]))
        except ValueError:  # sqrt / acos outside their domain: no real solution
            return "not reachable by the legs"
        det = abs(bar_determinant([a[1] for a in angles], [a[2] for a in angles], self.params, MATH_OPS))
        for leg, (th1, th2, th3) in enumerate(angles):
            margins = workspace_constraint_values(th1, th2, th3, det, self.limits, MATH_OPS)
            for name, margin in zip(CONSTRAINT_NAMES, margins):
                if margin < 0.0:
                    return (f"{name} margin {margin:.3g} < 0 at leg {leg} (theta1 "
                            f"{[round(math.degrees(a[0]), 1) for a in angles]} deg)")
        return ""

    def check(self, counts: Any) -> np.ndarray:
        """Measured position [m] (3,) of ``counts``; raises :class:`SafetyStop` naming the
        position and the reason when it is outside the (widened) workspace."""
        fast = self._fast
        if fast is not None and self._seeded:
            fast.inputs[0][:] = counts
            fast()
            p, residual, margins = fast.outputs
            if residual[0] < GUARD_RESIDUAL_M and margins.min() >= 0.0:   # NaN fails both
                fast.inputs[1][:] = p          # the next tick's seed
                self.fast_checks += 1
                return p.copy()
        self._seeded = False
        p = self.position(counts)
        reason = self.violation(p)
        if reason:
            raise SafetyStop(f"workspace guard: measured position {np.round(p * 1e3, 2).tolist()} mm "
                             f"(counts {np.asarray(counts).tolist()}) left the workspace: {reason}")
        if fast is not None:
            fast.inputs[1][:] = p
            self._seeded = True
        return p


MAX_LEG_SPEED_RAD_S = 50.0
"""An encoder step implying a faster leg than this is a bad reading, not motion [rad/s]
(planned moves peak at 8-18 rad/s). The speed is judged over the real time between the two
readings (their ``t_s``; never less than the loop periods between them), so that a host stall
during which the device went on moving is not mistaken for a bad reading."""


class TickGuard:
    """The checks on every reading of a loop that applies force (one set for every such loop):
    the counts moved no faster than :data:`MAX_LEG_SPEED_RAD_S` since the previous reading
    (:meth:`check`), and the point they give is inside the workspace (:class:`WorkspaceGuard`
    with ``params``' geometry, ``limits`` widened by ``slack_rad`` [rad]), and, given the
    loop's reference, no leg farther than ``max_tracking_error_counts`` [counts] from it.
    ``rate_hz`` is the loop's rate [Hz]. A loop that computes a tick again from the same
    reading puts the state back first (:meth:`state`, :meth:`restore`)."""

    def __init__(self, params: FalconParams, limits: WorkspaceLimits, slack_rad: float, rate_hz: float,
                 max_tracking_error_counts: float = MAX_TRACKING_ERROR_COUNTS) -> None:
        self.workspace = WorkspaceGuard(params, limits, slack_rad)
        self.max_tracking_error_counts = float(max_tracking_error_counts)
        self.period_s = 1.0 / rate_hz
        self.max_step_counts_s = MAX_LEG_SPEED_RAD_S * params.counts_per_rad   # [counts/s]
        self.prev_counts = np.zeros(3)
        self.prev_t_s = 0.0          # t_s of the reading prev_counts came from [s]
        self.prev_slots = 1          # periods between the exchange that read prev_counts and the one before

    def first(self, counts: np.ndarray) -> np.ndarray:
        """A loop's first reading ``counts`` (3,): its position [m] (the workspace checked);
        the next reading is judged against it, whenever it came."""
        self.prev_counts, self.prev_t_s, self.prev_slots = np.array(counts, dtype=float), -math.inf, 1
        return self.workspace.check(counts)

    def fresh(self, t_s: float) -> bool:
        """Whether a reading taken at device time ``t_s`` [s] is a new one (threaded I/O
        returns the last reading again when no new status came)."""
        return t_s != self.prev_t_s

    def check(self, counts: np.ndarray, t_s: float, slots: int, ref_counts: np.ndarray | None = None) -> np.ndarray:
        """Position [m] (3,) of ``counts`` read at device time ``t_s`` [s], ``slots`` loop
        periods after the exchange that read the previous counts; :class:`SafetyStop` for an
        implausible step, a point outside the workspace, or a leg farther than the tracking
        bound from ``ref_counts`` (3,) [counts], the reference the loop follows now (None: a
        loop without one). The counts become the previous ones."""
        self._check_step(counts, t_s, slots)
        position = self.workspace.check(counts)
        if ref_counts is not None:
            self._check_tracking(counts, ref_counts)
        self.prev_counts, self.prev_t_s, self.prev_slots = counts, t_s, slots
        return position

    def state(self) -> tuple[np.ndarray, float, int]:
        """The previous reading's counts, time and periods (for :meth:`restore`)."""
        return self.prev_counts, self.prev_t_s, self.prev_slots

    def restore(self, state: tuple[np.ndarray, float, int]) -> None:
        """Put back a :meth:`state`."""
        self.prev_counts, self.prev_t_s, self.prev_slots = state

    def _check_tracking(self, counts: np.ndarray, ref_counts: np.ndarray) -> None:
        """SafetyStop if a leg reads farther than the tracking bound from its reference."""
        error = np.abs(np.asarray(counts, dtype=float) - ref_counts)
        if error.max() > self.max_tracking_error_counts:
            leg = int(np.argmax(error))
            raise SafetyStop(
                f"tracking error of {error[leg]:.0f} counts on leg {leg} (allowed "
                f"{self.max_tracking_error_counts:g}): the controller has lost the device, or the grip is "
                f"held far off its path; counts {np.asarray(counts).astype(int).tolist()}, reference "
                f"{np.round(ref_counts).astype(int).tolist()}")

    def _check_step(self, counts: np.ndarray, t_s: float, slots: int) -> None:
        """SafetyStop if the counts moved faster than :data:`MAX_LEG_SPEED_RAD_S` since the
        previous reading, judged over the elapsed time: the readings' ``t_s`` difference,
        or the ``slots`` loop periods if longer, or the previous reading's if longer still [s]
        (a reading returned right after a host stall may predate it, when the driver's reader
        thread was held up too: then the next one shows the whole stall's motion)."""
        step = np.abs(counts - self.prev_counts).max()
        elapsed_s = max(t_s - self.prev_t_s, max(slots, self.prev_slots) * self.period_s)
        if step > self.max_step_counts_s * elapsed_s:
            raise SafetyStop(
                f"implausible encoder step of {step:.0f} counts in {elapsed_s * 1e3:.1f} ms ({slots} "
                f"loop period(s); a leg faster than {MAX_LEG_SPEED_RAD_S:g} rad/s): bad readings from "
                f"the device, counts {self.prev_counts.astype(int).tolist()} -> {counts.astype(int).tolist()}")
