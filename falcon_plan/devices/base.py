"""The device contract the executor drives: :class:`Device`, :class:`DeviceReading`, and
:class:`BaseDevice`, the shared logic of every concrete device.

Safety rules every device keeps (see ``docs/ARCHITECTURE.md``, "Devices"):

- A device is a context manager; :meth:`Device.close` always leaves zero force (it sends a
  zero command while the device is reachable, whatever happened before).
- :meth:`Device.exchange` is one loop tick: it clamps the commands to +-:data:`COMMAND_LIMIT`
  (never wraps), sends them, and returns the newest reading (the answer to this command
  for blocking I/O and simulated devices; with the USB driver's threaded I/O, the newest
  status packet, which trails the commands by the bus delay).
- No force before homing: until :attr:`Device.homed` is true, ``exchange`` with a nonzero
  command sends zero force instead and raises :class:`~falcon_plan.errors.SafetyStop`
  (zero commands are allowed, so a caller can read the encoders before homing).
- A command that is not three finite numbers, or LED bits outside the LED mask, sends zero
  force and raises :class:`~falcon_plan.errors.InvalidParameterError`.
- Any :class:`~falcon_plan.errors.DeviceError` raised mid-run has already tried to leave zero
  force where the device is still reachable; if that failed, its message says so (it then
  contains the :class:`ZeroForceError`'s text, "zero force could not be delivered").
- Zero force goes out through :meth:`BaseDevice._deliver_zero`, a device's most reliable
  path, which must not depend on whatever just failed (the USB driver writes the zero packet
  from the calling thread, retried, and reopens the USB handle if that fails, when its I/O
  threads have failed).

Threads: one loop thread drives ``exchange``; another thread (a watchdog) may call
``zero_force`` at any time. Ticks are serialised by a lock; if the loop holds it for longer
than :data:`ZERO_FORCE_LOCK_TIMEOUT_S` (stuck in I/O), ``zero_force`` falls back to
:meth:`BaseDevice._emergency_zero` (for USB: write one zero packet without reading).

Force safety that does not rely on the firmware (which may keep the last command forever):

- a device opened with ``watchdog_s`` runs a watchdog thread that sends zero force itself
  when a nonzero command has been applied and no tick has run for ``watchdog_s``; the next
  nonzero ``exchange`` then raises :class:`~falcon_plan.errors.SafetyStop` naming the stall,
  and a tick that was stuck in I/O while the watchdog fired sends zero again when it returns;
- every open device is registered for the process's exit paths
  (:func:`install_exit_hooks`, done on the first open): at interpreter exit (``atexit``) each
  one still open is closed (zero force); on SIGINT, SIGTERM and every other signal whose
  default action ends the process (:data:`ENDING_SIGNALS`: a closed terminal's SIGHUP, the quit key's
  SIGQUIT, SIGUSR1, ...) one zero packet goes to each open device at once, then
  ``KeyboardInterrupt`` / ``SystemExit(128 + signal)`` is raised in the main thread so that the
  normal unwinding (``finally``, ``with``) closes them too. The handlers are installed only over
  the default ones, from the main thread. SIGKILL and a power loss of the host cannot be seen:
  then the device keeps what it last received.

Pacing: with ``realtime=True`` each ``exchange`` waits for its tick deadline
(``t_open + k / rate_hz``) before the transfer, so the caller need not sleep; a tick that
starts more than one period late counts in :attr:`BaseDevice.late_ticks` and skips the
slots it missed (no burst of catch-up ticks); the grid is :class:`falcon_plan.timing.DeadlineTimer`,
the executor's. With ``realtime=False`` ticks run as fast as the device answers.
"""
from __future__ import annotations

import abc
import atexit
import logging
import signal
import threading
import time
import weakref
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol, runtime_checkable

import numpy as np

from falcon_plan.errors import DeviceError, InvalidParameterError, SafetyStop
from falcon_plan.model.params import ACRA2009
from falcon_plan.timing import DeadlineTimer, realtime_thread

log = logging.getLogger(__name__)

COMMAND_LIMIT = ACRA2009.command_limit
"""Largest motor command magnitude the device accepts [command units] (the parameter set's
``command_limit``: the firmware's range, the same for every Falcon)."""

LED_GREEN = 0x02
"""Green LED bit of the ``leds`` argument (same bit as on the wire)."""
LED_BLUE = 0x04
"""Blue LED bit."""
LED_RED = 0x08
"""Red LED bit."""
LED_MASK = LED_GREEN | LED_BLUE | LED_RED
"""Every LED bit; ``leds`` must have no other bit set."""
ZERO_FORCE_LOCK_TIMEOUT_S = 0.005
"""How long ``zero_force`` waits for a tick in progress before the emergency path [s]."""


# --- errors --------------------------------------------------------------------------------
class BackendMissingError(DeviceError):
    """No libusb backend could be loaded (pyusb found no libusb-1.0)."""


class DeviceNotFoundError(DeviceError):
    """No Falcon (VID 0x0403, PID 0xCB48) is on the bus."""


class DevicePermissionError(DeviceError, PermissionError):
    """The Falcon is there but the user may not open it (no udev rule)."""


class FirmwareError(DeviceError):
    """Loading the firmware failed: missing file, handshake never passed, echo mismatch, or
    no status packet after the load."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """The device did not answer in time."""


class DeviceDisconnectedError(DeviceError, ConnectionError):
    """The device went away mid-run (unplugged, powered off, reset)."""


class IoThreadError(DeviceError):
    """A background I/O thread of the device (the USB writer or reader) stopped on an
    exception that was not a :class:`DeviceError`; the message names the thread, what it
    was doing and the exception."""


class ZeroForceError(DeviceError):
    """Zero force could not be delivered to the device by any path: it may still apply its
    last command."""


# --- value type and contract ---------------------------------------------------------------
@dataclass(frozen=True)
class DeviceReading:
    """What one loop tick read back.

    Attributes
    ----------
    counts : np.ndarray
        Encoder counts, shape (3,), int64, one per leg (0 top, 1 right, 2 left); unwrapped
        (continuous across the 16-bit wire wrap-around) [counts].
    buttons : int
        Grip buttons bit mask (0x1, 0x2, 0x4, 0x8).
    homed : tuple[bool, bool, bool]
        Per-leg homed flags.
    t_s : float
        Time of the reading since the device was opened [s] (simulated time for a
        simulated device).
    arrived_s : float or None
        When the reading arrived at the host [s, :func:`time.monotonic`] where the driver
        knows it (the threaded USB reader keeps the newest packet's arrival); None: the
        caller's time of receipt is as good (blocking I/O, simulated devices).
    """

    counts: np.ndarray
    buttons: int
    homed: tuple[bool, bool, bool]
    t_s: float
    arrived_s: float | None = None

    def __post_init__(self) -> None:
        counts = np.asarray(self.counts, dtype=np.int64).reshape(3).copy()
        counts.setflags(write=False)
        object.__setattr__(self, "counts", counts)
        object.__setattr__(self, "homed", tuple(bool(h) for h in self.homed))

    @property
    def all_homed(self) -> bool:
        """True when all three legs report homed."""
        return all(self.homed)


@runtime_checkable
class Device(Protocol):
    """A Falcon the executor can drive; a context manager whose close() leaves zero force."""

    rate_hz: float
    """Nominal loop rate [Hz]."""

    def open(self) -> None:
        """Connect (and for the USB device load the firmware); idempotent."""

    def close(self) -> None:
        """Send zero force (if reachable) and release the device; idempotent, never raises
        for a device that is already gone."""

    def home(self, timeout_s: float = 30.0) -> None:
        """Block until all three legs are homed, or raise ``DeviceTimeoutError`` after
        ``timeout_s`` [s] (> 0)."""

    @property
    def homed(self) -> bool:
        """True once all three legs are homed."""

    def exchange(self, commands: Any, leds: int = 0) -> DeviceReading:
        """One loop tick: send the ``commands`` (3 numbers [command units], clamped to
        +-COMMAND_LIMIT) with the LED bits ``leds`` (:data:`LED_MASK` bits only; 0: all off),
        return the reading."""

    def zero_force(self) -> None:
        """Send a zero command now (one tick)."""

    def __enter__(self) -> "Device": ...

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None: ...


def clamp_commands(commands: Any) -> np.ndarray:
    """Check and clamp motor commands.

    Parameters
    ----------
    commands : array-like
        Three finite numbers [command units]; non-integers are rounded to the nearest integer.

    Returns
    -------
    np.ndarray
        Shape (3,), int64, each in [-COMMAND_LIMIT, COMMAND_LIMIT].

    Raises
    ------
    InvalidParameterError
        Not three numbers, or a NaN/inf among them.
    """
    try:
        arr = np.asarray(commands, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidParameterError(
            f"motor commands must be three numbers, got {commands!r}") from exc
    if arr.shape != (3,):
        raise InvalidParameterError(
            f"motor commands must have shape (3,), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidParameterError(f"motor commands must be finite, got {arr.tolist()}")
    return np.clip(np.rint(arr), -COMMAND_LIMIT, COMMAND_LIMIT).astype(np.int64)


def check_leds(leds: int) -> int:
    """Return ``leds`` as an int if it only holds LED bits (:data:`LED_MASK`), else raise
    :class:`InvalidParameterError`."""
    if isinstance(leds, bool) or not isinstance(leds, (int, np.integer)):
        raise InvalidParameterError(f"leds must be an int bit mask, got {leds!r}")
    if int(leds) & ~LED_MASK:
        raise InvalidParameterError(
            f"leds={leds:#x} has bits outside the LED mask {LED_MASK:#x} "
            "(use LED_GREEN | LED_BLUE | LED_RED)")
    return int(leds)


class BaseDevice(abc.ABC):
    """Shared logic: context manager, open/closed state, clamping, the homing safety rule,
    pacing, and zero force on close and on errors.

    Subclasses implement :meth:`_connect`, :meth:`_disconnect`, :meth:`_transfer` (one
    tick, already-checked commands), :meth:`_home` and :attr:`homed`.

    Parameters
    ----------
    rate_hz : nominal loop rate [Hz], > 0.
    realtime : each ``exchange`` waits for its tick deadline (True) or runs at once (False).
    watchdog_s : run a watchdog thread that sends zero force when a nonzero command has been
        applied and no tick has run for this long [s], > 0; None: no watchdog thread.
    """

    def __init__(self, rate_hz: float, realtime: bool, watchdog_s: float | None = None) -> None:
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidParameterError(f"rate_hz must be a positive number, got {rate_hz!r}")
        if watchdog_s is not None and not (np.isfinite(watchdog_s) and watchdog_s > 0):
            raise InvalidParameterError(f"watchdog_s must be positive or None, got {watchdog_s!r}")
        self.rate_hz = float(rate_hz)
        self.realtime = bool(realtime)
        self.watchdog_s = None if watchdog_s is None else float(watchdog_s)
        self._timer: DeadlineTimer | None = None
        self._slot = 0
        self._is_open = False
        self._lock = threading.RLock()
        self.last_commands = np.zeros(3, dtype=np.int64)
        """The last commands actually sent (after clamping / safety) [command units]."""
        self.watchdog_trips = 0
        """Times the watchdog thread zeroed the force since open."""
        self.stall_reason = ""
        """Why the watchdog last zeroed the force ("" if it never did)."""
        self._in_flight = np.zeros(3, dtype=np.int64)
        self._last_tick_s = time.monotonic()
        self._unreported_trip = False
        self._watchdog: _ForceWatchdog | None = None

    # -- subclass hooks ----------------------------------------------------------------------
    @abc.abstractmethod
    def _connect(self) -> None:
        """Acquire the device (the object is not yet marked open)."""

    @abc.abstractmethod
    def _disconnect(self) -> None:
        """Release the device; must not raise for a device that is already gone."""

    @abc.abstractmethod
    def _transfer(self, commands: np.ndarray, flags: int) -> DeviceReading:
        """Send one packet (commands int64 (3,), already clamped; LED/homing flags) and return
        the reading."""

    @abc.abstractmethod
    def _home(self, timeout_s: float) -> None:
        """Run the homing procedure until all legs are homed."""

    @property
    @abc.abstractmethod
    def homed(self) -> bool:
        """True once all three legs are homed."""

    def _deliver_zero(self) -> None:
        """Send a zero command by the device's most reliable path (default: one tick of
        zero); raise :class:`DeviceError` (:class:`ZeroForceError` when every path failed)
        if it could not be delivered."""
        self._transfer(np.zeros(3, dtype=np.int64), 0)

    def _emergency_zero(self) -> None:
        """Send zero force while another thread is inside a tick (default: not possible)."""
        raise DeviceError(f"{type(self).__name__} is busy in a tick and has no emergency "
                          "zero-force path; the tick in progress must finish first")

    # -- public API --------------------------------------------------------------------------
    @property
    def is_open(self) -> bool:
        """True between a successful open() and close()."""
        return self._is_open

    @property
    def late_ticks(self) -> int:
        """Real-time ticks that started more than one period late since open()."""
        return 0 if self._timer is None else self._timer.missed_deadlines

    def open(self) -> None:
        """Connect; idempotent."""
        with self._lock:
            if self._is_open:
                return
            self._restart_pacing()
            install_exit_hooks()
            self._connect()
            self.last_commands = self._in_flight = np.zeros(3, dtype=np.int64)
            self.watchdog_trips, self.stall_reason, self._unreported_trip = 0, "", False
            self._last_tick_s = time.monotonic()
            self._is_open = True
            _OPEN_DEVICES.add(self)
            if self.watchdog_s is not None:
                self._watchdog = _ForceWatchdog(self, self.watchdog_s)

    def close(self) -> None:
        """Send zero force if the device is reachable, then release it; idempotent."""
        with self._lock:
            if not self._is_open:
                return
            watchdog, self._watchdog = self._watchdog, None
            if watchdog is not None:
                watchdog.stop()
            try:
                self.zero_force()
            except DeviceError as exc:
                log.error("could not send zero force on close (%s)", exc)
            finally:
                self._is_open = False
                _OPEN_DEVICES.discard(self)
                self._disconnect()

    def __enter__(self) -> "BaseDevice":
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def home(self, timeout_s: float = 30.0) -> None:
        """Block until all three legs are homed, at most ``timeout_s`` [s] (> 0); zero force
        is sent throughout."""
        if not (timeout_s > 0):
            raise InvalidParameterError(f"timeout_s must be positive, got {timeout_s!r}")
        with self._lock:
            self._require_open()
            self._home(float(timeout_s))

    def exchange(self, commands: Any, leds: int = 0) -> DeviceReading:
        """One loop tick: send the ``commands`` (3 finite numbers [command units], rounded and
        clamped to +-COMMAND_LIMIT) with the LED bits ``leds`` (:data:`LED_MASK` bits only),
        return the reading.

        Raises
        ------
        InvalidParameterError
            Commands not three finite numbers, or bad LED bits (zero force is sent first).
        SafetyStop
            A nonzero command before homing (zero force is sent instead).
        DeviceError
            The transfer failed (zero force was attempted).
        """
        with self._lock:
            self._require_open()
            try:
                cmd = clamp_commands(commands)
                leds = check_leds(leds)
            except InvalidParameterError:
                self._zero_force_quietly()
                raise
            if np.any(cmd != 0) and not self.homed:
                self._zero_force_quietly()
                raise SafetyStop(
                    f"refusing nonzero force {cmd.tolist()} before homing: the encoder zero is "
                    "meaningless until all three legs are homed; call home() first")
            if np.any(cmd != 0) and self._unreported_trip:
                self._unreported_trip = False
                self._zero_force_quietly()
                raise SafetyStop(self.stall_reason)
            return self._tick(cmd, leds)

    def zero_force(self) -> None:
        """Send a zero command now (one tick, by :meth:`_deliver_zero`). Safe from another
        thread: if a tick is in progress for longer than ZERO_FORCE_LOCK_TIMEOUT_S, the
        emergency path is used."""
        if not self._lock.acquire(timeout=ZERO_FORCE_LOCK_TIMEOUT_S):
            self._emergency_zero()
            return
        try:
            self._require_open()
            self._pace()
            self._deliver_zero()
            self._zero_delivered()
        finally:
            self._lock.release()

    # -- helpers -----------------------------------------------------------------------------
    def _restart_pacing(self) -> None:
        """A fresh deadline grid (real time only), its slot 0 at the next tick."""
        self._slot = 0
        self._timer = (DeadlineTimer(self.rate_hz, spin_s=0.0, clock=time.monotonic, record=False)
                       if self.realtime else None)

    def _pace(self) -> None:
        """Wait for this tick's deadline on the device's grid (no-op when not real time)."""
        if self._timer is None:
            return
        if self._slot == 0:
            self._timer.start()
        self._slot = self._timer.wait(self._slot) + 1

    def _tick(self, commands: np.ndarray, flags: int) -> DeviceReading:
        self._pace()
        trips = self.watchdog_trips
        self._in_flight = commands
        try:
            reading = self._transfer(commands, flags)
        except DeviceError as exc:
            problem = self._zero_force_quietly()
            if problem is None:
                raise
            raise _amended(exc, problem) from (exc.__cause__ or exc)
        self.last_commands = commands.copy()
        self._last_tick_s = time.monotonic()
        if self.watchdog_trips != trips and np.any(commands != 0):
            # The watchdog fired while this tick was stuck: its command may have gone out
            # after the watchdog's zero, so send zero again and stop.
            self._unreported_trip = False
            self._zero_force_quietly()
            raise SafetyStop(self.stall_reason)
        return reading

    @property
    def force_applied(self) -> bool:
        """True if the device may be applying a nonzero command: the last one sent, or one
        being sent now."""
        return bool(np.any(self.last_commands != 0) or np.any(self._in_flight != 0))

    def _watchdog_trip(self, stalled_s: float) -> None:
        """Called by the watchdog thread: zero the force and remember why."""
        self.stall_reason = (f"watchdog: no device tick for {stalled_s * 1e3:.0f} ms (bound "
                             f"{(self.watchdog_s or 0.0) * 1e3:.0f} ms) while commands "
                             f"{self.last_commands.tolist()} / {self._in_flight.tolist()} were "
                             "applied; force zeroed")
        log.error(self.stall_reason)
        self.watchdog_trips += 1
        self._unreported_trip = True
        try:
            self.zero_force()
        except DeviceError as exc:
            log.error("watchdog could not send zero force (%s)", exc)
        self._last_tick_s = time.monotonic()     # if the stall goes on: again one bound later

    def emergency_zero(self) -> None:
        """Send one zero command at once without waiting for a tick in progress (signal
        handlers); never raises."""
        try:
            self._emergency_zero()
            self.last_commands = self._in_flight = np.zeros(3, dtype=np.int64)
        except Exception as exc:  # noqa: BLE001 - best effort on an exit path, by design
            log.warning("emergency zero force failed (%s: %s)", type(exc).__name__, exc)

    def _zero_force_quietly(self) -> DeviceError | None:
        """Best-effort zero force (used on error paths): returns (and logs) the error that
        kept zero from the device, None when it was delivered."""
        if not self._is_open:
            return None
        try:
            self._deliver_zero()
        except DeviceError as exc:
            log.error("could not send zero force (%s)", exc)
            return exc
        self._zero_delivered()
        return None

    def _zero_delivered(self) -> None:
        """Record that a zero command went out (no force applied, the loop is not stalled)."""
        self.last_commands = self._in_flight = np.zeros(3, dtype=np.int64)
        self._last_tick_s = time.monotonic()

    def _require_open(self) -> None:
        if not self._is_open:
            raise DeviceError(
                f"{type(self).__name__} is not open: call open() or use it in a `with` block")


def _amended(error: DeviceError, zero_problem: DeviceError) -> DeviceError:
    """``error`` with the reason zero force did not reach the device added to its message
    (same type where it can be rebuilt from a message)."""
    message = f"{error}; then {zero_problem}"
    try:
        return type(error)(message)
    except TypeError:
        return DeviceError(message)


class _ForceWatchdog:
    """A daemon thread that calls ``device._watchdog_trip`` when a nonzero command has been
    applied and no tick has run for ``timeout_s`` [s]; it polls every ``timeout_s / 5``, so
    a stall is caught within 1.2 x ``timeout_s`` (it needs the GIL: I/O and sleeps release
    it). It keeps watching after a trip (the force is zero then, so it stays quiet)."""

    def __init__(self, device: BaseDevice, timeout_s: float) -> None:
        self._device = weakref.ref(device)
        self._timeout_s = timeout_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="falcon-device-watchdog",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)

    def _watch(self) -> None:
        realtime_thread()   # as the loop it watches: a normal thread holding the GIL would hold it back
        while not self._stop.wait(self._timeout_s / 5.0):
            device = self._device()
            if device is None or not device.is_open:
                return
            stalled = time.monotonic() - device._last_tick_s
            if stalled > self._timeout_s and device.force_applied:
                device._watchdog_trip(stalled)
            del device


# --- process exit paths --------------------------------------------------------------------
_OPEN_DEVICES: set[BaseDevice] = set()
"""Every open device (strong references: an open device stays reachable for the exit paths
even if its owner dropped it; close() removes it)."""
_HOOKS = {"atexit": False, "signals": False}


def open_devices() -> list[BaseDevice]:
    """The devices open in this process."""
    return list(_OPEN_DEVICES)


def _close_all_at_exit() -> None:
    """atexit: close every device still open (close sends zero force)."""
    for device in open_devices():
        try:
            device.close()
        except Exception as exc:  # noqa: BLE001 - exit path: try the rest, then a raw zero
            log.warning("closing %s at exit failed (%s); sending a raw zero",
                        type(device).__name__, exc)
            device.emergency_zero()


ENDING_SIGNALS = tuple(getattr(signal, name) for name in (
    "SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGXCPU", "SIGVTALRM",
    "SIGPROF") if hasattr(signal, name))
"""Signals whose default action ends the process (with a core dump, for SIGQUIT and SIGXCPU)
without unwinding it, so that without a handler a device would keep its last command: each
gets :func:`_on_signal` where its default handler is in place. (Python itself ignores SIGPIPE
and SIGXFSZ; SIGKILL and SIGSTOP cannot be caught.)"""


class SignalExit(SystemExit):
    """The process is ending on the signal ``signum`` of :data:`ENDING_SIGNALS` (exit status
    128 + signum): raised in the main thread so that the normal unwinding closes every device."""

    def __init__(self, signum: int) -> None:
        super().__init__(128 + signum)
        self.signum = signum


def _on_signal(signum: int, frame: Any) -> None:
    """A signal of :data:`ENDING_SIGNALS`: one zero packet to every open device with force on,
    then unwind (KeyboardInterrupt for SIGINT, else SystemExit(128 + signum))."""
    for device in open_devices():
        if device.force_applied:
            device.emergency_zero()
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise SignalExit(signum)


def leave_signals_to_parent() -> None:
    """In a worker process whose parent decides when it ends (a batch worker): devices opened
    here install no signal handlers (``atexit`` still closes them), so the parent's
    ``terminate`` ends the worker at once and silently, even inside a solver."""
    _HOOKS["signals"] = True


def install_exit_hooks() -> None:
    """Register the exit paths (see the module docstring): ``atexit`` always; handlers of
    :data:`ENDING_SIGNALS` only where the default handler is in place and only from the main
    thread. Idempotent; called by :meth:`BaseDevice.open`."""
    if not _HOOKS["atexit"]:
        _HOOKS["atexit"] = True
        atexit.register(_close_all_at_exit)
    if _HOOKS["signals"] or threading.current_thread() is not threading.main_thread():
        return
    _HOOKS["signals"] = True
    for signum in ENDING_SIGNALS:
        default = signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL
        if signal.getsignal(signum) is default:
            signal.signal(signum, _on_signal)
