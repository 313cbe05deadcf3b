"""The device contract the executor drives: :class:`Device`, :class:`DeviceReading`, and
:class:`BaseDevice`, the shared logic of every concrete device.

Safety rules every device keeps (see ``docs/ARCHITECTURE.md``, "Devices"):

- A device is a context manager; :meth:`Device.close` always leaves zero force (it sends a
  zero command while the device is reachable, whatever happened before).
- :meth:`Device.exchange` is one loop tick: it clamps the commands to +-:data:`COMMAND_LIMIT`
  (never wraps), sends them, and returns the reading of that tick.
- No force before homing: until :attr:`Device.homed` is true, ``exchange`` with a nonzero
  command sends zero force instead and raises :class:`~falcon_plan.errors.SafetyStop`
  (zero commands are allowed, so a caller can read the encoders before homing).
- A command that is not three finite numbers, or LED bits outside the LED mask, sends zero
  force and raises :class:`~falcon_plan.errors.InvalidParameterError`.
- Any :class:`~falcon_plan.errors.DeviceError` raised mid-run has already tried to leave zero
  force where the device is still reachable.

Threads: one loop thread drives ``exchange``; another thread (a watchdog) may call
``zero_force`` at any time. Ticks are serialised by a lock; if the loop holds it for longer
than :data:`ZERO_FORCE_LOCK_TIMEOUT_S` (stuck in I/O), ``zero_force`` falls back to
:meth:`BaseDevice._emergency_zero` (for USB: write one zero packet without reading).

Pacing: with ``realtime=True`` each ``exchange`` waits for its tick deadline
(``t_open + k / rate_hz``) before the transfer, so the caller need not sleep; a tick that
starts late counts in :attr:`BaseDevice.late_ticks` and restarts the deadline grid (no burst
of catch-up ticks). With ``realtime=False`` ticks run as fast as the device answers.
"""
from __future__ import annotations

import abc
import logging
import threading
import time
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Protocol, runtime_checkable

import numpy as np

from falcon_plan.errors import DeviceError, InvalidParameterError, SafetyStop

log = logging.getLogger(__name__)

COMMAND_LIMIT = 4096
"""Largest motor command magnitude the device accepts [command units]."""

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
    """

    counts: np.ndarray
    buttons: int
    homed: tuple[bool, bool, bool]
    t_s: float

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
        """Block until all three legs are homed, or raise ``DeviceTimeoutError`` [s]."""

    @property
    def homed(self) -> bool:
        """True once all three legs are homed."""

    def exchange(self, commands: Any, leds: int = 0) -> DeviceReading:
        """One loop tick: send the clamped commands (3 ints, command units), return the
        reading."""

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


@dataclass
class _Pacer:
    """Deadline grid for real-time ticks: deadline_k = start + k * period [s]."""

    period_s: float
    realtime: bool
    next_deadline_s: float | None = None
    late_ticks: int = 0
    clock: Any = field(default=time.monotonic)

    def restart(self) -> None:
        self.next_deadline_s = None
        self.late_ticks = 0

    def wait(self) -> None:
        """Sleep until the current tick's deadline (no-op when not real time)."""
        if not self.realtime:
            return
        now = self.clock()
        if self.next_deadline_s is None:
            self.next_deadline_s = now
        delay = self.next_deadline_s - now
        if delay > 0:
            time.sleep(delay)
        elif delay < -self.period_s:
            # More than one tick late: count it and restart the grid instead of bursting.
            self.late_ticks += 1
            self.next_deadline_s = now
        self.next_deadline_s += self.period_s


class BaseDevice(abc.ABC):
    """Shared logic: context manager, open/closed state, clamping, the homing safety rule,
    pacing, and zero force on close and on errors.

    Subclasses implement :meth:`_connect`, :meth:`_disconnect`, :meth:`_transfer` (one
    tick, already-checked commands), :meth:`_home` and :attr:`homed`.
    """

    def __init__(self, rate_hz: float, realtime: bool) -> None:
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidParameterError(f"rate_hz must be a positive number, got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        self.realtime = bool(realtime)
        self._pacer = _Pacer(1.0 / self.rate_hz, self.realtime)
        self._is_open = False
        self._lock = threading.RLock()
        self.last_commands = np.zeros(3, dtype=np.int64)
        """The last commands actually sent (after clamping / safety) [command units]."""

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
        return self._pacer.late_ticks

    def open(self) -> None:
        """Connect; idempotent."""
        with self._lock:
            if self._is_open:
                return
            self._pacer.restart()
            self._connect()
            self._is_open = True

    def close(self) -> None:
        """Send zero force if the device is reachable, then release it; idempotent."""
        with self._lock:
            if not self._is_open:
                return
            try:
                self.zero_force()
            except DeviceError as exc:
                log.warning("could not send zero force on close (%s)", exc)
            finally:
                self._is_open = False
                self._disconnect()

    def __enter__(self) -> "BaseDevice":
        self.open()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def home(self, timeout_s: float = 30.0) -> None:
        """Block until all three legs are homed [s]; zero force is sent throughout."""
        if not (timeout_s > 0):
            raise InvalidParameterError(f"timeout_s must be positive, got {timeout_s!r}")
        with self._lock:
            self._require_open()
            self._home(float(timeout_s))

    def exchange(self, commands: Any, leds: int = 0) -> DeviceReading:
        """One loop tick: send the commands clamped to +-COMMAND_LIMIT, return the reading.

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
            return self._tick(cmd, leds)

    def zero_force(self) -> None:
        """Send a zero command now (one tick). Safe from another thread: if a tick is in
        progress for longer than ZERO_FORCE_LOCK_TIMEOUT_S, the emergency path is used."""
        if not self._lock.acquire(timeout=ZERO_FORCE_LOCK_TIMEOUT_S):
            self._emergency_zero()
            return
        try:
            self._require_open()
            self._tick(np.zeros(3, dtype=np.int64), 0)
        finally:
            self._lock.release()

    # -- helpers -----------------------------------------------------------------------------
    def _tick(self, commands: np.ndarray, flags: int) -> DeviceReading:
        self._pacer.wait()
        try:
            reading = self._transfer(commands, flags)
        except DeviceError:
            self._zero_force_quietly()
            raise
        self.last_commands = commands.copy()
        return reading

    def _zero_force_quietly(self) -> None:
        """Best-effort zero force (used on error paths; logs instead of raising)."""
        if not self._is_open:
            return
        try:
            self._transfer(np.zeros(3, dtype=np.int64), 0)
            self.last_commands = np.zeros(3, dtype=np.int64)
        except DeviceError as exc:
            log.warning("could not send zero force (%s)", exc)

    def _require_open(self) -> None:
        if not self._is_open:
            raise DeviceError(
                f"{type(self).__name__} is not open: call open() or use it in a `with` block")
