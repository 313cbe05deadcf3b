"""UsbFalcon: the Novint Falcon over USB with pyusb.

Protocol (``/work/shared/FALCON-USB.md``; where the device is only known from the public
driver, libnifalcon, whose file is named at each point): the Falcon is an FTDI FT232R
(VID 0x0403, PID 0xCB48; interface 0, bulk OUT 0x02, bulk IN 0x81, 64-byte packets whose
first 2 IN bytes are FTDI status). FTDI settings are vendor control requests (0x40).

Opening (:meth:`UsbFalcon.open`) uploads the user's nVent image, as libnifalcon does:

- one set-up (``FalconCommLibUSB.cpp``, ``setFirmwareMode``): purge, 16 ms latency,
  9600 baud 8N1, no flow control, RTS low, DTR low then high; then the check ``0A 43 0D``
  is resent as it is, up to ``check_retries`` times, until ``0A 44 2C 0D`` comes back (no
  new DTR pulse per attempt); DTR low, divisor 0x15, ``'A'`` echoed, 62-byte chunks echoed
  and compared; then 1 ms latency, 1.5 Mbaud, purge (``setNormalMode``);
- a patient running-check (``FalconFirmware.cpp``, ``isFirmwareLoaded``): up to
  ``running_check_rounds`` rounds, each one zero command and up to ``running_check_reads``
  reads, until a status packet comes back;
- if any of that fails, the whole load is retried after closing and reopening the device,
  up to ``load_retries`` times (``FalconCLIBase.cpp`` does 10: users "often need to do it
  several times", libnifalcon issue #33).

Runtime, two I/O designs (``io``):

- ``"threaded"`` (default; libnifalcon ``FalconCommLibUSB.h``: non-blocking I/O was needed
  to come near 1 kHz): a writer thread sends each command as it is given (a newer command
  replaces one not yet sent) and a reader thread reads continuously and keeps the newest
  status packet; both run at real-time priority where the system allows it
  (:func:`falcon_plan.timing.realtime_thread`). :meth:`exchange` hands over the command,
  waits at most :data:`STATUS_WAIT_PERIODS` of a period for a status that arrives after the
  hand-over, and returns that reading, the first after the hand-over even when the caller
  woke later (its ``t_s`` is when the status arrived); the
  readings trail the commands by the device's delay.
  The loop never runs blind on stale readings: an exception of any type in either thread
  ends that thread and wakes the waiting exchange, which raises it at once as a
  :class:`~falcon_plan.errors.DeviceError` naming the thread, what it was doing and the
  exception (a non-USB exception becomes :class:`~falcon_plan.devices.base.IoThreadError`);
  and commands count as unanswered from the moment they are handed over, so a thread stuck
  in a transfer (or starved by the host) is a :class:`DeviceTimeoutError` after the silence
  bound ``(resends + 1) * reply_timeout_s``, whose message says which side made no progress.
  After such a failure the device stays failed (every tick raises) until it is reopened.
- ``"blocking"``: each tick writes one packet and reads until one whole status packet has
  arrived; if none comes within ``reply_timeout_s`` the packet is sent again, up to
  ``resends`` times. Each reading answers its own command (deterministic; used against the
  instant emulator), but on a real bus one round trip takes 2-3 USB frames.

Both resynchronise over short and misaligned reads
(:class:`~falcon_plan.devices.protocol.PacketStream`) and use the newest status packet.

Safety rules:

- Commands are clamped to +-4096 before packing (never wrapped to 16 bits).
- Homing (``FalconFirmware.h``, "Homing Mode": the homing bit must be set in each packet for
  the device to stay homed, and the homed bits are reported only while it is set): from the
  start of :meth:`home` on, every packet carries the homing flag, until the device is closed.
- No force before homing: until all three homed bits are set, a nonzero command sends zero
  force and raises :class:`~falcon_plan.errors.SafetyStop`.
- Nothing public says the firmware ever drops a command by itself, so the driver assumes it
  keeps the last one forever: :meth:`close` sends zero first, every error raised mid-run has
  tried to send zero force, a watchdog thread sends zero when the loop stalls
  (``watchdog_s``), and zero is sent on interpreter exit and SIGINT/SIGTERM
  (:mod:`falcon_plan.devices.base`). A cable pulled mid-run can leave the last command
  applied: nothing on the host can reach the device then.
- Zero force never depends on what failed: once the threaded I/O has failed, its threads
  are stopped (a writer still alive sends zero as its last packet) and zero is written from
  the calling thread, up to :data:`ZERO_WRITE_ATTEMPTS` times, then once more on a freshly
  opened handle (find, claim, write), so one transient USB error does not leave the force
  on. If none of that reaches the device, the error raised says "zero force could not be
  delivered" and to unplug the power supply (:class:`~falcon_plan.devices.base.ZeroForceError`).
  A write stuck in the host controller is joined again before its handle is closed, and
  closing the handle cancels it.
- Any exception of the USB backend, not only ``usb.core.USBError``, becomes a
  :class:`~falcon_plan.errors.DeviceError` naming its type and what was being done.
- Errors are :class:`~falcon_plan.errors.DeviceError` subclasses naming the cause and the fix
  (see :mod:`falcon_plan.devices.base`).
"""
from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from falcon_plan.devices import protocol as proto
from falcon_plan.devices.base import (BackendMissingError, BaseDevice, DeviceDisconnectedError,
                                      DeviceNotFoundError, DevicePermissionError, DeviceReading,
                                      DeviceTimeoutError, FirmwareError, IoThreadError,
                                      ZeroForceError)
from falcon_plan.devices.protocol import (BAUD_BOOT, BAUD_LOADER, BAUD_RUN, CHECK_REPLY,
                                          CHECK_REQUEST, DATA_8N1, DTR_HIGH, DTR_LOW, EP_IN,
                                          EP_OUT, FALCON_PID, FALCON_VID, FTDI_BAUD, FTDI_DATA,
                                          FTDI_FLOW_CTRL, FTDI_LATENCY, FTDI_MODEM_CTRL,
                                          FTDI_RESET, LOAD_START, PURGE_RX, PURGE_TX, RTS_LOW)
from falcon_plan.errors import DeviceError, InvalidParameterError
from falcon_plan.timing import DeadlineTimer, realtime_thread

log = logging.getLogger(__name__)

FIRMWARE_CHUNK = 62
"""Bytes per firmware upload chunk (the device echoes each one)."""
CHECK_RETRIES = 100
"""Default number of firmware-check attempts (libnifalcon ``setFirmwareMode``: 100)."""
LOAD_RETRIES = 10
"""Default number of whole-load attempts, closing and reopening the device in between
(libnifalcon ``FalconCLIBase.cpp``: 10)."""
RUNNING_CHECK_ROUNDS, RUNNING_CHECK_READS = 10, 100
"""Running-check after a load: rounds of one zero command and up to this many reads
(libnifalcon ``FalconFirmware::isFirmwareLoaded``: 10 x 100 I/O loops)."""
IO_MODES = ("threaded", "blocking")
"""Runtime I/O designs (see the module docstring)."""
WATCHDOG_S = 0.05
"""Default stall bound of the device's watchdog thread [s]."""
RUNTIME_LATENCY_MS = 1
"""The FTDI latency timer at runtime [ms] (libnifalcon ``setNormalMode``)."""
STATUS_WAIT_PERIODS = 0.85
"""How long a threaded :meth:`UsbFalcon.exchange` waits for a status newer than the last one
returned [loop periods]; then it returns the newest it has (its ``t_s`` repeats, so the
caller sees that it is not new). A loop computes its next command after the exchange, so a
wait of a whole period turned every late status (a reader thread held up on a busy host)
into a missed deadline; 0.85 leaves 0.15 ms at 1 kHz for the controller (its work is about
0.12 ms p50). Measured with the emulated Falcon (threaded USB, wall clock, one CPU-stress
process, 8 problems, 4 rounds a setting, together with :data:`~falcon_plan.timing.ARRIVAL_LEAD_S`
0.45 ms): 2-29 missed deadlines a round, against 0-330 waiting a whole period with the grid
0.3 ms after the arrivals."""
ZERO_WRITE_ATTEMPTS = 3
"""Writes of the zero packet from the calling thread, after the I/O failed, before the USB
handle is reopened for one more."""

INSTALL_LIBUSB_HINT = ("pyusb found no libusb backend: install libusb-1.0 (Debian/Ubuntu: "
                   "`sudo apt install libusb-1.0-0`; macOS: `brew install libusb`); on Windows "
                   "install the WinUSB driver for the Falcon with Zadig")
UDEV_RULE_HINT = ('add the udev rule SUBSYSTEM=="usb", ATTRS{idVendor}=="0403", '
             'ATTRS{idProduct}=="cb48", MODE="0666" to /etc/udev/rules.d/99-falcon.rules, '
             "run `sudo udevadm control --reload` and re-plug the Falcon")


class UsbFalcon(BaseDevice):
    """A Novint Falcon on USB.

    Parameters
    ----------
    firmware_path : str or Path, optional
        The nVent firmware image (not shipped with the project). None: expect the firmware
        to be running already (no power cycle since the last load).
    backend : usb.backend.IBackend, optional
        pyusb backend (default: pyusb's choice, libusb-1.0 first); tests pass
        :class:`~falcon_plan.devices.emulated.EmulatedFalconBackend`.
    rate_hz : float
        Loop rate [Hz] (nominal 1000).
    realtime : bool
        Pace each tick to ``1 / rate_hz`` (True) or run as fast as the device answers.
    io : str
        Runtime I/O design, one of :data:`IO_MODES`.
    check_retries : int
        Firmware-check sends per load before the load counts as failed.
    load_retries : int
        Whole-load attempts (close and reopen in between) before :class:`FirmwareError`.
    running_check_rounds, running_check_reads : int
        Patience of the running-check after a load (rounds x reads).
    check_timeout_s : float
        Time to wait for the check answer per attempt [s].
    echo_timeout_s : float
        Time to wait for each upload echo [s].
    reply_timeout_s : float
        Time to wait for a status packet before resending the command (blocking I/O) [s];
        with threaded I/O no status for ``(resends + 1) * reply_timeout_s`` is a timeout.
    resends : int
        Resends of an unanswered command before :class:`DeviceTimeoutError`.
    usb_timeout_ms : int
        pyusb timeout of each bulk transfer [ms].
    watchdog_s : float or None
        Zero force when no tick has run for this long while a force is applied [s]
        (None: no watchdog thread).
    """

    def __init__(self, firmware_path: str | os.PathLike[str] | None = None, *,
                 backend: Any = None, rate_hz: float = 1000.0, realtime: bool = True,
                 io: str = "threaded", check_retries: int = CHECK_RETRIES,
                 load_retries: int = LOAD_RETRIES,
                 running_check_rounds: int = RUNNING_CHECK_ROUNDS,
                 running_check_reads: int = RUNNING_CHECK_READS,
                 check_timeout_s: float = 0.1, echo_timeout_s: float = 0.5,
                 reply_timeout_s: float = 0.01, resends: int = 3, usb_timeout_ms: int = 100,
                 watchdog_s: float | None = WATCHDOG_S) -> None:
        super().__init__(rate_hz, realtime, watchdog_s=watchdog_s)
        if io not in IO_MODES:
            raise InvalidParameterError(f"io must be one of {IO_MODES}, got {io!r}")
        counts = dict(check_retries=check_retries, load_retries=load_retries,
                      running_check_rounds=running_check_rounds,
                      running_check_reads=running_check_reads)
        for name, value in counts.items():
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise InvalidParameterError(f"{name} must be a whole number >= 1, got {value!r}")
        if isinstance(resends, bool) or int(resends) != resends or resends < 0:
            raise InvalidParameterError(f"resends must be a whole number >= 0, got {resends!r}")
        self.firmware_path = None if firmware_path is None else Path(firmware_path)
        self.backend = backend
        self.io = io
        self.check_retries = int(check_retries)
        self.load_retries = int(load_retries)
        self.running_check_rounds = int(running_check_rounds)
        self.running_check_reads = int(running_check_reads)
        self.check_timeout_s = float(check_timeout_s)
        self.echo_timeout_s = float(echo_timeout_s)
        self.reply_timeout_s = float(reply_timeout_s)
        self.resends = int(resends)
        self.usb_timeout_ms = int(usb_timeout_ms)
        self.check_attempts = 0
        """Firmware-check sends used by the last load."""
        self.load_attempts = 0
        """Whole-load attempts used by the last open."""
        self.kernel_driver_detached = False
        """True if the last open had to detach a kernel driver (ftdi_sio) from interface 0."""
        self.resent_packets = 0
        """Commands sent again because no status packet came back (blocking I/O)."""
        self.stats = IoStats()
        """Counters of the threaded I/O since open."""
        self._dev: Any = None
        self._stream = proto.PacketStream()
        self._counts: np.ndarray | None = None
        self._homed_bits = (False, False, False)
        self._homing_mode = False
        self._t0 = 0.0
        self._gone = False
        self._io: _IoThreads | None = None
        self._retired_io: _IoThreads | None = None   # failed threads that may not have ended
        self._failure: DeviceError | None = None
        self._deadlines: DeadlineTimer | None = None

    @property
    def homed(self) -> bool:
        """True when the last status packet had all three homed bits set."""
        return all(self._homed_bits)

    @property
    def device_clock(self) -> str:
        """How the device keeps time: "wall" for a Falcon (it lives through the time between
        ticks), or what an emulating backend says (its ``device_clock``)."""
        return getattr(self.backend, "device_clock", "wall")

    @property
    def link_delay_s(self) -> float:
        """How much later than the firmware's own command delay the readings show a command,
        as the USB path makes it [s]: 0 with blocking I/O (each reading answers its own
        command); with threaded I/O what an emulating backend says (its ``link_delay_s``), else
        the bus's known timing (:meth:`~falcon_plan.devices.emulated.UsbTiming.link_delay_s`
        at 1 ms frames and the 1 ms latency timer the driver sets: 2 ms). ``doctor`` measures
        the real figure (host included)."""
        if self.io == "blocking":
            return 0.0
        known = getattr(self.backend, "link_delay_s", None)
        if known is not None:
            return float(known)
        from falcon_plan.devices.emulated import UsbTiming

        return UsbTiming().link_delay_s(RUNTIME_LATENCY_MS)

    @property
    def homing_mode(self) -> bool:
        """True once :meth:`home` has started: every packet carries the homing flag."""
        return self._homing_mode

    # -- connect ------------------------------------------------------------------------------
    def _connect(self) -> None:
        image = self._read_firmware() if self.firmware_path is not None else None
        attempts = self.load_retries if image is not None else 1
        failures: list[str] = []
        for attempt in range(1, attempts + 1):
            self.load_attempts = attempt
            self._open_usb()
            try:
                if image is not None:
                    self._load_firmware(image)
                self._set_runtime_mode()
                self._wait_running(loaded=image is not None)
            except (FirmwareError, DeviceTimeoutError) as exc:    # a flaky load: retry it
                self._disconnect()
                failures.append(str(exc))
                log.warning("firmware load %d of %d failed: %s", attempt, attempts, exc)
                continue
            except BaseException:
                self._disconnect()
                raise
            if self.io == "threaded":
                self._io = _IoThreads(self)
            return
        if attempts == 1:
            raise FirmwareError(failures[-1])
        raise FirmwareError(
            f"firmware load failed {attempts} times, closing and reopening the Falcon in "
            f"between (last: {failures[-1]}); unplug the Falcon's power supply and USB cable, "
            "plug them back in, connect directly rather than through a hub, and retry")

    def _open_usb(self) -> None:
        """Find the device and claim interface 0 (fresh state for one load attempt)."""
        self._dev = self._find()
        self._gone = False
        self._failure = None
        self._stream.clear()
        self._counts = None
        self._homed_bits = (False, False, False)
        self._homing_mode = False
        self.stats = IoStats()
        try:
            self._claim()
        except BaseException:
            self._disconnect()
            raise

    def _read_firmware(self) -> bytes:
        path = self.firmware_path
        assert path is not None
        try:
            image = path.read_bytes()
        except FileNotFoundError:
            raise FirmwareError(
                f"firmware file not found: {path}; falcon-plan does not ship Novint's "
                "proprietary image: pass the path of the nVent firmware file from your "
                "Falcon's driver installation") from None
        except OSError as exc:
            raise FirmwareError(f"cannot read firmware file {path}: {exc.strerror}") from exc
        if not image:
            raise FirmwareError(f"firmware file {path} is empty; pass the nVent firmware image")
        return image

    def _find(self) -> Any:
        try:
            import usb.core
        except ImportError as exc:
            raise BackendMissingError(
                "pyusb is not installed: `pip install pyusb`, then install libusb-1.0 "
                "(`sudo apt install libusb-1.0-0`)") from exc

        try:
            dev = usb.core.find(idVendor=FALCON_VID, idProduct=FALCON_PID, backend=self.backend)
        except usb.core.NoBackendError as exc:
            raise BackendMissingError(INSTALL_LIBUSB_HINT) from exc
        if dev is None:
            raise DeviceNotFoundError(
                f"no Novint Falcon found (USB {FALCON_VID:04x}:{FALCON_PID:04x}): check that "
                "it is plugged in and powered, connect it directly rather than through a hub, "
                "and check that `lsusb` lists 0403:cb48")
        return dev

    def _claim(self, configure: bool = True) -> None:
        """Claim interface 0 (detaching ftdi_sio if it holds it); ``configure``: set the
        configuration first (a fresh open; not when reopening a running device)."""
        with self._usb_errors("opening the Falcon"):
            with contextlib.suppress(NotImplementedError):
                self.kernel_driver_detached = bool(self._dev.is_kernel_driver_active(0))
                if self.kernel_driver_detached:
                    self._dev.detach_kernel_driver(0)     # ftdi_sio would hold the interface
            if configure:
                self._dev.set_configuration()
            import usb.util

            usb.util.claim_interface(self._dev, 0)

    def _disconnect(self) -> None:
        io, self._io = self._io, None
        if io is not None:
            io.stop()                 # the writer sends the last command (zero) first
        retired, self._retired_io = self._retired_io, None
        if retired is not None and not retired.stop(timeout_s=self.usb_timeout_ms * 1e-3 + 0.1):
            log.error("a USB I/O thread is still stuck in a transfer; closing its handle "
                      "cancels it")
        self._dispose_handle()

    def _dispose_handle(self) -> None:
        """Release the USB handle (never raises: the device may be gone)."""
        dev, self._dev = self._dev, None
        if dev is None:
            return
        import usb.util

        try:
            usb.util.dispose_resources(dev)
        except Exception as exc:  # noqa: BLE001 - a handle in a bad state is released anyway
            log.debug("releasing the USB handle: %s: %s", type(exc).__name__, exc)

    # -- FTDI primitives ----------------------------------------------------------------------
    def _ctrl(self, request: int, value: int) -> None:
        with self._usb_errors("an FTDI control request"):
            self._dev.ctrl_transfer(0x40, request, value, 0, None, self.usb_timeout_ms)

    def _write(self, data: bytes) -> None:
        if self._dev is None:
            raise DeviceError("the Falcon's USB handle is closed: nothing to write to")
        with self._usb_errors("writing to the Falcon"):
            written = self._dev.write(EP_OUT, data, self.usb_timeout_ms)
        if written != len(data):
            raise DeviceError(f"short USB write: {written} of {len(data)} bytes")

    def _read(self) -> bytes:
        """One bulk IN read, FTDI status bytes stripped (b'' means no data yet)."""
        with self._usb_errors("reading from the Falcon"):
            raw = self._dev.read(EP_IN, proto.USB_PACKET_SIZE, self.usb_timeout_ms)
        return proto.strip_ftdi_status(bytes(raw))

    def _read_exactly(self, n: int, timeout_s: float) -> bytes:
        """Read until ``n`` data bytes have arrived or ``timeout_s`` passed [s] (returns what
        arrived)."""
        data = bytearray()
        deadline = time.monotonic() + timeout_s
        while len(data) < n and time.monotonic() < deadline:
            data += self._read()
        return bytes(data)

    def _purge(self) -> None:
        self._ctrl(FTDI_RESET, PURGE_RX)
        self._ctrl(FTDI_RESET, PURGE_TX)
        self._stream.clear()

    @contextlib.contextmanager
    def _usb_errors(self, what: str) -> Iterator[None]:
        """Translate pyusb errors into DeviceError subclasses naming the cause and fix, and
        any other exception of the backend into a DeviceError naming its type."""
        import usb.core

        if self._gone:
            raise DeviceDisconnectedError(
                "the Falcon was disconnected; re-plug it and open it again")
        try:
            yield
        except usb.core.USBTimeoutError as exc:
            raise DeviceTimeoutError(
                f"USB timeout while {what} (after {self.usb_timeout_ms} ms): check the cable "
                "and the power supply") from exc
        except usb.core.USBError as exc:
            if exc.errno == errno.ENODEV:
                self._gone = True
                raise DeviceDisconnectedError(
                    f"the Falcon disconnected while {what} ({exc.strerror}): it may still apply "
                    "the last command, so unplug its power supply; then re-plug it and open it "
                    "again (the firmware must be loaded again after a power cycle)") from exc
            if exc.errno in (errno.EACCES, errno.EPERM):
                raise DevicePermissionError(
                    f"permission denied while {what} ({exc.strerror}): {UDEV_RULE_HINT}") from exc
            if exc.errno == errno.EBUSY:
                raise DeviceError(
                    f"the Falcon's interface is busy while {what}: another program or the "
                    "ftdi_sio kernel driver holds it; close the other program or "
                    "`sudo rmmod ftdi_sio`") from exc
            raise DeviceError(f"USB error while {what}: {type(exc).__name__}: "
                              f"{exc.strerror or exc}") from exc
        except DeviceError:
            raise
        except Exception as exc:  # noqa: BLE001 - pyusb and libusb raise more than USBError
            raise DeviceError(f"the USB backend failed while {what}: "
                              f"{type(exc).__name__}: {exc}") from exc

    # -- firmware -----------------------------------------------------------------------------
    def _load_firmware(self, image: bytes) -> None:
        """One load (libnifalcon ``setFirmwareMode`` then the upload): set up once, resend
        the check until it is answered, then upload the image against its echo."""
        self._purge()
        self._ctrl(FTDI_LATENCY, 16)          # shorter makes the checks fail (libnifalcon)
        self._ctrl(FTDI_BAUD, BAUD_BOOT)
        self._ctrl(FTDI_DATA, DATA_8N1)
        self._ctrl(FTDI_FLOW_CTRL, 0)
        self._ctrl(FTDI_MODEM_CTRL, RTS_LOW)
        self._ctrl(FTDI_MODEM_CTRL, DTR_LOW)
        self._ctrl(FTDI_MODEM_CTRL, DTR_HIGH)     # resets the DSP into its bootloader
        self.check_attempts = 0
        reply = b""
        for attempt in range(1, self.check_retries + 1):
            self.check_attempts = attempt
            reply = self._bootloader_check()
            if CHECK_REPLY in reply:
                break
            log.debug("firmware check %d failed: %s", attempt, reply.hex(" "))
        else:
            raise FirmwareError(
                f"firmware check failed {self.check_retries} times (sent "
                f"{CHECK_REQUEST.hex(' ')}, expected {CHECK_REPLY.hex(' ')}, last answer "
                f"{reply.hex(' ') or 'nothing'})")
        self._ctrl(FTDI_MODEM_CTRL, DTR_LOW)
        self._ctrl(FTDI_BAUD, BAUD_LOADER)
        self._expect_echo(bytes((LOAD_START,)), offset=None)
        for offset in range(0, len(image), FIRMWARE_CHUNK):
            self._expect_echo(image[offset:offset + FIRMWARE_CHUNK], offset)
        log.info("firmware uploaded (%d bytes, %d check sends)", len(image),
                 self.check_attempts)

    def _bootloader_check(self) -> bytes:
        """Send the check bytes once and return what came back within ``check_timeout_s``
        (reading stops once a whole answer may be there)."""
        self._write(CHECK_REQUEST)
        data = bytearray()
        deadline = time.monotonic() + self.check_timeout_s
        while time.monotonic() < deadline:
            data += self._read()
            if len(data.lstrip(b"\x00")) >= len(CHECK_REPLY):
                break
        return bytes(data)

    def _expect_echo(self, chunk: bytes, offset: int | None) -> None:
        self._write(chunk)
        echo = self._read_exactly(len(chunk), self.echo_timeout_s)
        if echo == chunk:
            return
        where = "the load start byte 'A'" if offset is None else f"image bytes {offset}.." \
            f"{offset + len(chunk) - 1}"
        if len(echo) < len(chunk):
            raise FirmwareError(
                f"firmware rejected: no echo of {where} within {self.echo_timeout_s} s "
                f"({len(echo)} of {len(chunk)} bytes); power-cycle the Falcon and retry")
        bad = next(i for i, (a, b) in enumerate(zip(echo, chunk)) if a != b)
        raise FirmwareError(
            f"firmware rejected: echo mismatch in {where} at byte "
            f"{(offset or 0) + bad} (sent {chunk[bad]:#04x}, got {echo[bad]:#04x}); "
            "power-cycle the Falcon and retry; if it persists, check the firmware file")

    def _set_runtime_mode(self) -> None:
        """Step 7: 1 ms latency, 1.5 Mbaud, purge."""
        self._ctrl(FTDI_LATENCY, RUNTIME_LATENCY_MS)
        self._ctrl(FTDI_BAUD, BAUD_RUN)
        self._purge()

    def _wait_running(self, loaded: bool) -> None:
        """The firmware counts as running once a status packet comes back (libnifalcon
        ``isFirmwareLoaded``: rounds of one command and many reads, patient because the
        first answer can be slow)."""
        self._t0 = time.monotonic()
        packet = proto.encode_command_packet((0, 0, 0))
        for _ in range(self.running_check_rounds):
            self._write(packet)
            for _ in range(self.running_check_reads):
                packets = self._stream.feed(self._read())
                if packets:
                    self._reading(proto.decode_status_packet(packets[-1]), time.monotonic())
                    return
        waited = f"{self.running_check_rounds} x {self.running_check_reads} reads"
        if loaded:
            raise FirmwareError(
                f"the firmware was uploaded but the Falcon sent no status packet ({waited}): "
                "a flaky load, or the file is not the nVent firmware image")
        raise FirmwareError(
            f"the Falcon answers no status packets ({waited}): its firmware is not running "
            "(it is lost at every power cycle); pass firmware_path= to load it")

    # -- runtime ------------------------------------------------------------------------------
    def follow_deadlines(self, timer: DeadlineTimer | None) -> None:
        """``timer``: the deadlines of the loop that exchanges now (None: no loop's). With threaded I/O an
        exchange handed over after its tick's deadline then returns at once a status that
        arrived since that deadline: the tick's own reading on the device's frame grid (see
        ``_IoThreads.exchange``). Measured on the emulated Falcon (wall clock, 6 benchmark
        problems, each 23rd hand-over made 0.7 ms late): 4 missed deadlines a round instead of
        93-295, tracking RMS max 0.17-0.18 mm instead of 0.30-0.66."""
        self._deadlines = timer

    def _flags(self, flags: int) -> int:
        """Add the homing flag once homing has started (libnifalcon: in every packet)."""
        return flags | (proto.FLAG_HOMING if self._homing_mode else 0)

    def _transfer(self, commands: np.ndarray, flags: int) -> DeviceReading:
        if self._failure is not None:
            failure = self._failure
            raise type(failure)(f"the Falcon's USB I/O failed earlier and was stopped "
                                f"({failure}); close the device and open it again") from failure
        packet = proto.encode_command_packet(commands, self._flags(flags))
        if self._io is not None:
            try:
                due_s = None if self._deadlines is None else self._deadlines.current_deadline()
                status, t_status = self._io.exchange(packet, wait_s=STATUS_WAIT_PERIODS / self.rate_hz,
                                                     due_s=due_s)
            except DeviceError as exc:
                self._stop_failed_io(exc)
                raise
            return self._reading(status, t_status)
        for attempt in range(self.resends + 1):
            if attempt:
                self.resent_packets += 1
            self._write(packet)
            status = self._await_status()
            if status is not None:
                if attempt:
                    status = self._drain(status)
                return self._reading(status, time.monotonic())
        raise DeviceTimeoutError(self._silence_message())

    def _silence_message(self) -> str:
        return (f"the Falcon did not answer {self.resends + 1} command packets in a row "
                f"(waited {self.reply_timeout_s * 1e3:.0f} ms each): check the USB cable, "
                "connect directly rather than through a hub, and check the power supply")

    def _await_status(self) -> proto.StatusPacket | None:
        """Read until a whole status packet arrives (the newest if several), or None after
        ``reply_timeout_s``."""
        deadline = time.monotonic() + self.reply_timeout_s
        while True:
            packets = self._stream.feed(self._read())
            if packets:
                return proto.decode_status_packet(packets[-1])
            if time.monotonic() >= deadline:
                return None

    def _drain(self, status: proto.StatusPacket) -> proto.StatusPacket:
        """After a resend, the answer to the earlier send may still arrive: read until a read
        brings no data (or ``reply_timeout_s``) and keep the newest packet, so the readings
        do not stay one tick behind. (Status packets carry no sequence number, so an answer
        later than that can still make one reading one tick old.)"""
        deadline = time.monotonic() + self.reply_timeout_s
        while time.monotonic() < deadline:
            chunk = self._read()
            if not chunk:
                break
            packets = self._stream.feed(chunk)
            if packets:
                status = proto.decode_status_packet(packets[-1])
        return status

    def _reading(self, status: proto.StatusPacket, t_status: float) -> DeviceReading:
        self._counts = proto.unwrap_counts(status.counts, self._counts)
        self._homed_bits = status.homed
        return DeviceReading(self._counts, status.buttons, status.homed, t_status - self._t0, t_status)

    def _zero_packet(self) -> bytes:
        return proto.encode_command_packet((0, 0, 0), self._flags(0))

    def _stop_failed_io(self, error: DeviceError) -> None:
        """The threaded I/O failed with ``error``: stop its threads (a writer still alive
        sends zero as its last packet), remember the failure (every later tick raises it
        until the device is reopened) and use the calling thread for zero force from now
        on."""
        io, self._io = self._io, None
        self._failure = error
        log.info("threaded USB I/O stopped: %s", error)    # raised to the caller too
        if io is not None and not io.stop(final_packet=self._zero_packet(),
                                          timeout_s=self.usb_timeout_ms * 1e-3 + 0.1):
            log.error("a USB I/O thread is stuck in a transfer and did not stop; its last "
                      "packet will be zero")
            self._retired_io = io     # joined again before its handle is closed

    def _deliver_zero(self) -> None:
        """Zero force by a path that does not depend on what failed: a normal tick while
        the I/O is healthy; otherwise (the I/O threads failed, or the tick failed) the zero
        packet written from this thread, up to :data:`ZERO_WRITE_ATTEMPTS` times, then once
        more on a reopened USB handle (find, claim, write). Raises :class:`ZeroForceError`
        when none of that reached the device."""
        if self._failure is None:
            try:
                self._transfer(np.zeros(3, dtype=np.int64), 0)
                return
            except DeviceError as exc:
                log.warning("zero-force tick failed (%s); writing zero directly", exc)
        packet = self._zero_packet()
        errors: list[DeviceError] = []
        for _ in range(ZERO_WRITE_ATTEMPTS):
            try:
                self._write(packet)
                return
            except DeviceError as exc:
                errors.append(exc)
        try:
            self._dispose_handle()
            self._dev = self._find()
            self._gone = False
            self._claim(configure=False)
            self._write(packet)
            log.warning("zero force delivered after reopening the USB handle (%d writes "
                        "failed: %s)", len(errors), errors[0])
            return
        except DeviceError as exc:
            errors.append(exc)
        raise ZeroForceError(
            f"zero force could not be delivered ({ZERO_WRITE_ATTEMPTS} writes failed: "
            f"{errors[0]}; after reopening the USB handle: {errors[-1]}): the Falcon may still "
            f"apply its last command {self.last_commands.tolist()}, so unplug its power supply")

    def _emergency_zero(self) -> None:
        """Write one zero packet now without reading (another thread, or the interrupted
        code of this one, owns the read side); with threaded I/O the writer's next packet is
        made zero too, so a command it still holds cannot follow."""
        if self._dev is None:
            raise DeviceError("UsbFalcon is not open: nothing to send zero force to")
        packet = self._zero_packet()
        io = self._io
        if io is not None:
            io.post(packet)
        self._write(packet)

    def _home(self, timeout_s: float) -> None:
        """Send zero force with the homing flag until all three homed bits are set; the flag
        stays on in every later packet."""
        self._homing_mode = True
        deadline = time.monotonic() + timeout_s
        reading = None
        while not self.homed:
            if time.monotonic() > deadline:
                missing = [leg for leg, h in enumerate(self._homed_bits) if not h]
                raise DeviceTimeoutError(
                    f"homing timed out after {timeout_s} s, legs {missing} not homed: pull the "
                    "grip fully out, push it back in, and call home() again")
            reading = self._tick(np.zeros(3, dtype=np.int64), 0)
        log.info("homed (counts %s)", None if reading is None else reading.counts.tolist())



@dataclass
class IoStats:
    """Counters of the threaded I/O since open.

    Attributes
    ----------
    written : command packets written by the writer thread.
    replaced : commands replaced by a newer one before they were written.
    statuses : status packets received by the reader thread.
    stale : readings returned without a new status packet since the previous one.
    """

    written: int = 0
    replaced: int = 0
    statuses: int = 0
    stale: int = 0


class _IoThreads:
    """The reader and writer threads of ``io="threaded"`` (see the module docstring).

    The writer sends the newest command handed over (one mailbox slot); the reader reads
    continuously and keeps the newest status packet with its arrival time. Any exception in
    either thread (of any type) ends that thread and is kept, as a :class:`DeviceError`
    naming the thread, what it was doing and the exception; :meth:`exchange` raises it at
    once (a waiting exchange is woken), and so does a thread found dead. Commands count as
    unanswered from the moment they are handed over until a status packet arrives, so a
    writer or reader that is stuck (no new status while commands keep coming) is a timeout
    too.
    """

    def __init__(self, falcon: UsbFalcon) -> None:
        self._falcon = falcon
        self._cv = threading.Condition()
        self._outbox: bytes | None = None
        self._status: proto.StatusPacket | None = None
        self._status_t = time.monotonic()
        self._handed_over_s = math.inf       # the last hand-over (monotonic); inf: none waits
        self._answer: tuple[proto.StatusPacket, float] | None = None   # first status after it
        self._seq = 0
        self._returned = 0
        self._unanswered_since: float | None = None   # first hand-over after the newest status
        self._written_at_handover = 0
        self._last_read_s = time.monotonic()             # when the reader last finished a read
        self._error: DeviceError | None = None
        self._stopping = False
        self._threads = {"writer": threading.Thread(target=self._write_loop,
                                                    name="falcon-usb-writer", daemon=True),
                         "reader": threading.Thread(target=self._read_loop,
                                                    name="falcon-usb-reader", daemon=True)}
        for thread in self._threads.values():
            thread.start()

    def exchange(self, packet: bytes, wait_s: float,
                 due_s: float | None = None) -> tuple[proto.StatusPacket, float]:
        """Hand ``packet`` to the writer; return the first status that arrives after the
        hand-over and its arrival time [s], waiting up to ``wait_s`` [s] for it (else the newest
        there is). Taking a status that was already waiting instead would, once one status
        came late, keep every later reading one frame older than the loop's delay assumes
        (a second stable timing, seen as 0.2 mm RMS instead of 0.03 on the emulated Falcon).
        Taking a newer one than the first, when the caller woke late (a host stall), would
        hand the loop a reading younger than its delay assumes: its observer would read the
        device's motion in the meantime as an error (5-20 counts at speed).

        ``due_s``: when the caller's tick was due [s, monotonic]. A status not yet returned
        that arrived after it, before a hand-over that came late, is the tick's reading (it
        came on the device's frame grid) and is returned at once. Waiting for the next one
        instead kept a loop that fell 0.6 ms behind once behind for good: every later hand-over
        came after its frame's status, every exchange waited out ``wait_s``, and the ticks ran
        late or missed (see :meth:`UsbFalcon.follow_deadlines`)."""
        falcon = self._falcon
        with self._cv:
            self._raise_error()
            if self._outbox is not None:
                falcon.stats.replaced += 1
            self._outbox = packet
            handed_over = self._handed_over_s = time.monotonic()
            if self._unanswered_since is None:
                self._unanswered_since = handed_over
                self._written_at_handover = falcon.stats.written
            self._cv.notify_all()
            if due_s is not None and self._seq != self._returned and self._status_t > due_s:
                self._answer = (self._status, self._status_t)     # the late tick's own reading
            # a status that came before the hand-over was not taken by the last exchange (it came
            # late): the one after it, due within the wait, is a frame newer; take that one
            self._cv.wait_for(lambda: self._answer is not None or self._error is not None,
                              timeout=wait_s)
            if self._status is None:        # nothing yet since open: wait like a reply
                self._cv.wait_for(lambda: self._status is not None or self._error is not None,
                                  timeout=falcon.reply_timeout_s * (falcon.resends + 1))
            self._raise_error()
            if self._answer is not None:
                status, t_status = self._answer
            else:   # none after the hand-over in time: the newest there is
                status, t_status = self._status, self._status_t
                if self._seq == self._returned:
                    falcon.stats.stale += 1
            self._returned = self._seq
            self._answer, self._handed_over_s = None, math.inf   # no answer until the next hand-over
            since = self._unanswered_since
        # Silent: commands were handed over and no status came back for the whole bound (the
        # device answers only commands, so a pause of the loop alone is not silence).
        silent_s = 0.0 if since is None else time.monotonic() - since
        if status is None or silent_s > falcon.reply_timeout_s * (falcon.resends + 1):
            raise DeviceTimeoutError(self._silence_message(silent_s))
        return status, t_status

    def _silence_message(self, silent_s: float) -> str:
        """Why no status came for ``silent_s`` [s] of commands, from what each thread did
        meanwhile: a thread that made no transfer is stuck (or the host too busy to run it);
        otherwise the device is silent."""
        written = self._falcon.stats.written - self._written_at_handover
        unread_s = time.monotonic() - self._last_read_s
        head = (f"no status packet for {silent_s * 1e3:.0f} ms of commands (meanwhile "
                f"{written} packets written; last read ended {unread_s * 1e3:.0f} ms ago)")
        if written == 0:
            return (f"{head}: the USB writer thread sent nothing, so it is stuck in a "
                    "transfer or the host is too busy to run it; the loop cannot go on blind")
        if unread_s > 0.5 * silent_s:         # a working reader ends one every ~1 ms
            return (f"{head}: the USB reader thread read nothing, so it is stuck in a "
                    "transfer or the host is too busy to run it; the loop cannot go on blind")
        return (f"the Falcon sent {head}: check the USB cable, connect directly rather than "
                "through a hub, and check the power supply")

    def post(self, packet: bytes) -> None:
        """Make ``packet`` the writer's next packet without waiting (emergency zero)."""
        with self._cv:
            self._outbox = packet
            self._cv.notify_all()

    def stop(self, final_packet: bytes | None = None, timeout_s: float = 1.0) -> bool:
        """Stop both threads (idempotent): the writer first sends ``final_packet`` if given,
        else a command still waiting; wait up to ``timeout_s`` [s] for each thread. Returns
        True when both have ended."""
        with self._cv:
            self._stopping = True
            if final_packet is not None:
                self._outbox = final_packet
            self._cv.notify_all()
        for thread in self._threads.values():
            if thread is not threading.current_thread():
                thread.join(timeout=timeout_s)
        return not any(thread.is_alive() for thread in self._threads.values())

    def _raise_error(self) -> None:
        """Raise the kept thread error, or one for a thread that ended by itself (call with
        the condition held)."""
        if self._error is None and not self._stopping:
            for role, thread in self._threads.items():
                if not thread.is_alive():
                    self._error = IoThreadError(f"the USB {role} thread ended unexpectedly")
        if self._error is not None:
            error = self._error
            raise type(error)(str(error)) from error

    def _fail(self, role: str, doing: str, exc: BaseException) -> None:
        """Keep the first thread failure as a DeviceError naming the ``role`` ("writer" or
        "reader"), what it was ``doing`` and ``exc``; wake a waiting exchange."""
        text = f"the USB {role} thread stopped while {doing}"
        error: DeviceError
        if isinstance(exc, DeviceError):
            try:
                error = type(exc)(f"{text}: {exc}")
            except TypeError:
                error = IoThreadError(f"{text}: {type(exc).__name__}: {exc}")
        else:
            error = IoThreadError(f"{text}: {type(exc).__name__}: {exc}")
        error.__cause__ = exc
        with self._cv:
            if self._error is None and not self._stopping:
                self._error = error
            self._cv.notify_all()

    def _write_loop(self) -> None:
        falcon = self._falcon
        doing = "waiting for a command"
        realtime_thread()
        try:
            while True:
                with self._cv:
                    self._cv.wait_for(lambda: self._outbox is not None or self._stopping)
                    packet, self._outbox = self._outbox, None
                    if packet is None:
                        return
                doing = "writing a command packet"
                falcon._write(packet)
                doing = "counting a written packet"
                with self._cv:
                    falcon.stats.written += 1
                doing = "waiting for a command"
        except BaseException as exc:  # noqa: BLE001 - any death of the thread must be seen
            self._fail("writer", doing, exc)

    def _arrived(self, status: proto.StatusPacket, count: int = 1) -> None:
        """Keep ``status``, the newest of ``count`` status packets that just arrived; the first
        to arrive after a hand-over is that exchange's answer."""
        with self._cv:
            self._status, self._status_t = status, time.monotonic()
            if self._answer is None and self._status_t > self._handed_over_s:
                self._answer = (status, self._status_t)
            self._unanswered_since = None
            self._seq += count
            self._falcon.stats.statuses += count
            self._cv.notify_all()

    def _read_loop(self) -> None:
        falcon = self._falcon
        stream = proto.PacketStream()
        doing = "reading status packets"
        realtime_thread()
        try:
            while not self._stopping:
                doing = "reading status packets"
                packets = stream.feed(falcon._read())
                self._last_read_s = time.monotonic()    # only this thread writes it
                if packets:
                    doing = "decoding a status packet"
                    self._arrived(proto.decode_status_packet(packets[-1]), len(packets))
        except BaseException as exc:  # noqa: BLE001 - any death of the thread must be seen
            self._fail("reader", doing, exc)
