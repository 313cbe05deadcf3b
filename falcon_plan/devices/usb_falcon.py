"""UsbFalcon: the Novint Falcon over USB with pyusb.

Protocol (``/work/shared/FALCON-USB.md``): the Falcon is an FTDI FT232R (VID 0x0403,
PID 0xCB48; interface 0, bulk OUT 0x02, bulk IN 0x81, 64-byte packets whose first 2 IN bytes
are FTDI status). FTDI settings are vendor control requests (0x40). The DSP has no firmware
at power-up: :meth:`UsbFalcon.open` uploads the user's nVent image (steps 1-8: purge, 16 ms
latency, 9600 baud 8N1, RTS low, DTR low->high, check ``0A 43 0D`` -> ``0A 44 2C 0D`` with
retries, DTR low, divisor 0x15, ``'A'`` echo, 62-byte chunks echoed and compared, then 1 ms
latency, 1.5 Mbaud, purge, and a valid status packet). At runtime every tick sends one
16-byte command packet and reads until one whole 16-byte status packet has arrived
(:class:`~falcon_plan.devices.protocol.PacketStream` resynchronises over short and misaligned
reads); if no reply comes within ``reply_timeout_s`` the same packet is sent again, up to
``resends`` times (the gap shows in the readings' ``t_s``). If a read holds several status
packets, the newest is used.

Safety rules:

- Commands are clamped to +-4096 before packing (never wrapped to 16 bits).
- No force before homing: until all three homed bits are set, a nonzero command sends zero
  force and raises :class:`~falcon_plan.errors.SafetyStop`; :meth:`home` sends zero force with
  the homing flag until the user has pulled the grip out and pushed it back in.
- :meth:`close` always sends a zero command first (if the device is reachable); every error
  raised mid-run has tried to send zero force first. The firmware itself drops a command
  100 ms after the last packet, so a host that dies or a cable that is pulled also ends in
  zero force.
- Errors are :class:`~falcon_plan.errors.DeviceError` subclasses naming the cause and the fix
  (see :mod:`falcon_plan.devices.base`).
"""
from __future__ import annotations

import contextlib
import errno
import logging
import os
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from falcon_plan.devices import protocol as proto
from falcon_plan.devices.base import (BackendMissingError, BaseDevice, DeviceDisconnectedError,
                                      DeviceNotFoundError, DevicePermissionError, DeviceReading,
                                      DeviceTimeoutError, FirmwareError)
from falcon_plan.devices.protocol import (BAUD_BOOT, BAUD_LOADER, BAUD_RUN, CHECK_REPLY,
                                          CHECK_REQUEST, DATA_8N1, DTR_HIGH, DTR_LOW, EP_IN,
                                          EP_OUT, FALCON_PID, FALCON_VID, FTDI_BAUD, FTDI_DATA,
                                          FTDI_FLOW_CTRL, FTDI_LATENCY, FTDI_MODEM_CTRL,
                                          FTDI_RESET, LOAD_START, PURGE_RX, PURGE_TX, RTS_LOW)
from falcon_plan.errors import DeviceError, InvalidParameterError

log = logging.getLogger(__name__)

FIRMWARE_CHUNK = 62
"""Bytes per firmware upload chunk (the device echoes each one)."""
CHECK_RETRIES = 100
"""Default number of firmware-check attempts (as public drivers)."""

_INSTALL_LIBUSB = ("pyusb found no libusb backend: install libusb-1.0 (Debian/Ubuntu: "
                   "`sudo apt install libusb-1.0-0`; macOS: `brew install libusb`); on Windows "
                   "install the WinUSB driver for the Falcon with Zadig")
_UDEV_FIX = ('add the udev rule SUBSYSTEM=="usb", ATTRS{idVendor}=="0403", '
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
    check_retries : int
        Firmware-check attempts (step 3) before giving up.
    check_timeout_s : float
        Time to wait for the check answer per attempt [s].
    echo_timeout_s : float
        Time to wait for each upload echo [s].
    reply_timeout_s : float
        Time to wait for a status packet before resending the command [s].
    resends : int
        Resends of an unanswered command before :class:`DeviceTimeoutError`.
    usb_timeout_ms : int
        pyusb timeout of each bulk transfer [ms].
    """

    def __init__(self, firmware_path: str | os.PathLike[str] | None = None, *,
                 backend: Any = None, rate_hz: float = 1000.0, realtime: bool = True,
                 check_retries: int = CHECK_RETRIES, check_timeout_s: float = 0.1,
                 echo_timeout_s: float = 0.5, reply_timeout_s: float = 0.01, resends: int = 3,
                 usb_timeout_ms: int = 100) -> None:
        super().__init__(rate_hz, realtime)
        if check_retries < 1 or resends < 0:
            raise InvalidParameterError(
                f"check_retries must be >= 1 and resends >= 0, got {check_retries}, {resends}")
        self.firmware_path = None if firmware_path is None else Path(firmware_path)
        self.backend = backend
        self.check_retries = int(check_retries)
        self.check_timeout_s = float(check_timeout_s)
        self.echo_timeout_s = float(echo_timeout_s)
        self.reply_timeout_s = float(reply_timeout_s)
        self.resends = int(resends)
        self.usb_timeout_ms = int(usb_timeout_ms)
        self.check_attempts = 0
        """Firmware-check attempts used by the last load."""
        self.resent_packets = 0
        """Commands sent again because no status packet came back."""
        self._dev: Any = None
        self._stream = proto.PacketStream()
        self._counts: np.ndarray | None = None
        self._homed_bits = (False, False, False)
        self._t0 = 0.0
        self._gone = False

    @property
    def homed(self) -> bool:
        """True when the last status packet had all three homed bits set."""
        return all(self._homed_bits)

    # -- connect ------------------------------------------------------------------------------
    def _connect(self) -> None:
        image = self._read_firmware() if self.firmware_path is not None else None
        self._dev = self._find()
        self._gone = False
        self._stream.clear()
        self._counts = None
        self._homed_bits = (False, False, False)
        try:
            self._claim()
            if image is not None:
                self._load_firmware(image)
            self._set_runtime_mode()
            self._t0 = time.monotonic()
            self._first_status(loaded=image is not None)
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
            raise BackendMissingError(_INSTALL_LIBUSB) from exc
        if dev is None:
            raise DeviceNotFoundError(
                f"no Novint Falcon found (USB {FALCON_VID:04x}:{FALCON_PID:04x}): check that "
                "it is plugged in and powered, connect it directly rather than through a hub, "
                "and check that `lsusb` lists 0403:cb48")
        return dev

    def _claim(self) -> None:
        with self._usb_errors("opening the Falcon"):
            with contextlib.suppress(NotImplementedError):
                if self._dev.is_kernel_driver_active(0):
                    self._dev.detach_kernel_driver(0)     # ftdi_sio would hold the interface
            self._dev.set_configuration()
            import usb.util

            usb.util.claim_interface(self._dev, 0)

    def _disconnect(self) -> None:
        dev, self._dev = self._dev, None
        if dev is None:
            return
        import usb.core
        import usb.util

        with contextlib.suppress(usb.core.USBError):
            usb.util.dispose_resources(dev)

    # -- FTDI primitives ----------------------------------------------------------------------
    def _ctrl(self, request: int, value: int) -> None:
        with self._usb_errors("an FTDI control request"):
            self._dev.ctrl_transfer(0x40, request, value, 0, None, self.usb_timeout_ms)

    def _write(self, data: bytes) -> None:
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
        """Translate pyusb errors into DeviceError subclasses naming the cause and fix."""
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
                    f"the Falcon disconnected while {what} ({exc.strerror}): the firmware drops "
                    "the force 100 ms after the last packet; re-plug it, then open it again "
                    "(the firmware must be loaded again after a power cycle)") from exc
            if exc.errno in (errno.EACCES, errno.EPERM):
                raise DevicePermissionError(
                    f"permission denied while {what} ({exc.strerror}): {_UDEV_FIX}") from exc
            if exc.errno == errno.EBUSY:
                raise DeviceError(
                    f"the Falcon's interface is busy while {what}: another program or the "
                    "ftdi_sio kernel driver holds it; close the other program or "
                    "`sudo rmmod ftdi_sio`") from exc
            raise DeviceError(f"USB error while {what}: {exc.strerror or exc}") from exc

    # -- firmware -----------------------------------------------------------------------------
    def _load_firmware(self, image: bytes) -> None:
        """Steps 1-7 of FALCON-USB.md "Loading the firmware"."""
        self._purge()
        self._ctrl(FTDI_LATENCY, 16)
        self.check_attempts = 0
        reply = b""
        for attempt in range(1, self.check_retries + 1):
            self.check_attempts = attempt
            reply = self._bootloader_check()
            if reply.lstrip(b"\x00")[:len(CHECK_REPLY)] == CHECK_REPLY:
                break
            log.debug("firmware check %d failed: %s", attempt, reply.hex(" "))
        else:
            raise FirmwareError(
                f"firmware check failed {self.check_retries} times (sent "
                f"{CHECK_REQUEST.hex(' ')}, expected {CHECK_REPLY.hex(' ')}, last answer "
                f"{reply.hex(' ') or 'nothing'}): power-cycle the Falcon (unplug its power "
                "supply), connect it directly rather than through a hub, and retry")
        self._ctrl(FTDI_MODEM_CTRL, DTR_LOW)
        self._ctrl(FTDI_BAUD, BAUD_LOADER)
        self._expect_echo(bytes((LOAD_START,)), offset=None)
        for offset in range(0, len(image), FIRMWARE_CHUNK):
            self._expect_echo(image[offset:offset + FIRMWARE_CHUNK], offset)
        log.info("firmware loaded (%d bytes, %d check attempts)", len(image),
                 self.check_attempts)

    def _bootloader_check(self) -> bytes:
        """Steps 2-3 once: 9600 baud 8N1, RTS low, DTR low->high, send the check, read the
        answer (returns what came back)."""
        self._ctrl(FTDI_BAUD, BAUD_BOOT)
        self._ctrl(FTDI_DATA, DATA_8N1)
        self._ctrl(FTDI_FLOW_CTRL, 0)
        self._ctrl(FTDI_MODEM_CTRL, RTS_LOW)
        self._ctrl(FTDI_MODEM_CTRL, DTR_LOW)
        self._ctrl(FTDI_MODEM_CTRL, DTR_HIGH)
        self._ctrl(FTDI_RESET, PURGE_RX)
        self._write(CHECK_REQUEST)
        data = bytearray()
        deadline = time.monotonic() + self.check_timeout_s
        while time.monotonic() < deadline:
            data += self._read()
            body = data.lstrip(b"\x00")
            if len(body) >= len(CHECK_REPLY):
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
        self._ctrl(FTDI_LATENCY, 1)
        self._ctrl(FTDI_BAUD, BAUD_RUN)
        self._purge()

    def _first_status(self, loaded: bool) -> None:
        """Step 8: the firmware counts as running once a status packet comes back."""
        try:
            self._transfer(np.zeros(3, dtype=np.int64), 0)
        except DeviceTimeoutError as exc:
            if loaded:
                raise FirmwareError(
                    "the firmware was uploaded but the Falcon sends no status packets: the "
                    "file is probably not the nVent firmware image; check firmware_path") from exc
            raise FirmwareError(
                "the Falcon answers no status packets: its firmware is not running (it is "
                "lost at every power cycle); pass firmware_path= to load it") from exc

    # -- runtime ------------------------------------------------------------------------------
    def _transfer(self, commands: np.ndarray, flags: int) -> DeviceReading:
        packet = proto.encode_command_packet(commands, flags)
        for attempt in range(self.resends + 1):
            if attempt:
                self.resent_packets += 1
            self._write(packet)
            status = self._await_status()
            if status is not None:
                if attempt:
                    status = self._drain(status)
                return self._reading(status)
        raise DeviceTimeoutError(
            f"the Falcon did not answer {self.resends + 1} command packets in a row (waited "
            f"{self.reply_timeout_s * 1e3:.0f} ms each): check the USB cable, connect directly "
            "rather than through a hub, and check the power supply")

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

    def _reading(self, status: proto.StatusPacket) -> DeviceReading:
        self._counts = proto.unwrap_counts(status.counts, self._counts)
        self._homed_bits = status.homed
        return DeviceReading(self._counts, status.buttons, status.homed,
                             time.monotonic() - self._t0)

    def _emergency_zero(self) -> None:
        """Write one zero packet without reading (another thread is inside a tick and owns
        the read side; it will consume the answer)."""
        if self._dev is None:
            raise DeviceError("UsbFalcon is not open: nothing to send zero force to")
        self._write(proto.encode_command_packet((0, 0, 0)))

    def _home(self, timeout_s: float) -> None:
        """Send zero force with the homing flag until all three homed bits are set."""
        deadline = time.monotonic() + timeout_s
        reading = None
        while not self.homed:
            if time.monotonic() > deadline:
                missing = [leg for leg, h in enumerate(self._homed_bits) if not h]
                raise DeviceTimeoutError(
                    f"homing timed out after {timeout_s} s, legs {missing} not homed: pull the "
                    "grip fully out, push it back in, and call home() again")
            reading = self._tick(np.zeros(3, dtype=np.int64), proto.FLAG_HOMING)
        log.info("homed (counts %s)", None if reading is None else reading.counts.tolist())

