"""An emulated Novint Falcon behind a pyusb backend, with a SimPlant inside.

``usb.core.find(idVendor=0x0403, idProduct=0xCB48, backend=EmulatedFalconBackend(...))``
returns a real :class:`usb.core.Device` whose transfers reach this emulator, so the driver's
whole pyusb code path runs without hardware. Where the device's behaviour is only known from
the public driver, the emulator follows libnifalcon (file or issue named at each point), not
the project's own notes, so that the driver is tested against a world it did not write:

- descriptors: one configuration, interface 0 (vendor class), bulk IN 0x81 and bulk OUT 0x02,
  64-byte packets;
- FTDI vendor control requests (bmRequestType 0x40) are recorded: baud divisor, data format,
  flow control, latency timer, DTR/RTS; purge RX (wValue 1) clears the IN buffer, purge TX
  (wValue 2) the OUT buffer, reset (wValue 0) both;
- every IN read starts each 64-byte USB packet with 2 status bytes; a read with no data
  returns just those 2 bytes (never a timeout), like the FTDI chip;
- bootloader (libnifalcon ``FalconCommLibUSB.cpp``, ``setFirmwareMode``): DTR raised after
  being low at baud divisor 0x4138 resets the DSP into its bootloader (one set-up per load);
  every ``0A 43 0D`` is then answered, so a plain resend works: wrong bytes for the first
  ``FaultPlan.failed_checks`` requests, then ``0A 44 2C 0D`` (preceded by 0x00 on odd
  attempts: libnifalcon accepts both, its "Apple" and "Linux" cases). With DTR low and
  divisor 0x15, ``'A'`` is echoed and so is every following byte (the image); switching to
  divisor 2 ends the load and the firmware runs if the image is non-empty (and matches
  ``expected_image_sha256`` if given). ``FaultPlan.failed_loads`` makes the first loads fail
  as users report (libnifalcon issues #24, #33, #45: "you often need to do it several
  times"), at the check or after the upload (``FaultPlan.failed_load_stage``);
- runtime: each valid 16-byte command packet steps the plant by one control period (the
  plant applies its command delay; its clock is the packet stream, so a host that stops
  sending stops the plant too, unless ``UsbTiming(clock="wall")``: then the plant lives through
  the periods a stalled host missed, holding the last command) and
  queues one status packet: the plant's counts as 16 wire
  bits (offset by an arbitrary value per leg until that leg is homed), buttons, homed bits.
  Homing (libnifalcon ``FalconFirmware.h``, "Homing Mode", and the status layout in
  ``FalconFirmwareNovintSDK.h``): a leg homes after the homing flag has been seen in
  ``homing_packets + 5 * leg`` packets (the user's pull-out / push-in), and the homed bits
  are reported only in answers to packets that carry the homing flag;
- command hold: nothing public documents a firmware timeout, so by default the emulated
  firmware applies the last command *forever* (``command_hold_s=None``); a finite
  ``command_hold_s`` emulates a firmware that drops the force that long after the last
  packet. :attr:`EmulatedFalcon.held_commands` is the command applied now;
- timing (optional, :class:`UsbTiming`): full-speed USB completes a bulk transfer at a 1 ms
  frame boundary, the serial link takes 10 bits per byte at the set baud rate, and the FTDI
  chip holds fewer than 62 IN bytes until its latency timer expires (libnifalcon
  ``FalconCommLibUSB.h``: non-blocking I/O was needed to come near 1 kHz). Without it
  every transfer completes at once. ``UsbTiming(clock="wall")`` makes the plant live in
  wall-clock time (a real device does not wait for the host).

:class:`FaultPlan` injects the failures users report: short reads, garbage before packets,
dropped answers, failing firmware checks and loads, corrupted echoes, a disconnect mid-run
(every transfer then raises ``usb.core.USBError`` with errno ENODEV), permission denied on
open, and any byte in the undocumented byte 14 of status packets. :class:`TransferFault` makes
the bulk OUT or IN transfers raise a chosen exception (``usb.core.USBError`` with EIO or
EPIPE, ``USBTimeoutError``, or a non-USB ``RuntimeError``, ``ValueError``, ``OSError``, as a
backend can) or hang, once or every time, from a chosen packet on, so that the driver's I/O
threads can be made to fail mid-run; the emulator's own record (``held_commands``,
``wire_log``) then says whether zero force still reached the device.
If the plant itself fails (e.g. it left the reachable workspace), every transfer from then on
raises ``USBError`` with errno EIO naming the plant's error.
"""
from __future__ import annotations

import errno
import hashlib
import math
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import IO, TYPE_CHECKING, Any, Iterator

import numpy as np
import usb.backend
import usb.core

from falcon_plan.devices import protocol as proto
from falcon_plan.errors import FalconPlanError, InvalidParameterError
from falcon_plan.devices.protocol import (BAUD_BOOT, BAUD_LOADER, BAUD_RUN, CHECK_REPLY,
                                          CHECK_REQUEST, EP_IN, EP_OUT, FALCON_PID, FALCON_VID,
                                          FTDI_BAUD, FTDI_DATA, FTDI_FLOW_CTRL, FTDI_LATENCY,
                                          FTDI_MODEM_CTRL, FTDI_RESET, PURGE_RX, PURGE_TX)

if TYPE_CHECKING:
    from falcon_plan.sim.plant import SimPlant

FTDI_MODEM_STATUS = bytes((0x31, 0x60))
"""The 2 status bytes at the start of every IN packet (values as an FT232R sends idle)."""
NEVER = sys.maxsize
"""``FaultPlan.failed_checks=NEVER``: the firmware check never passes."""
LOAD_FAILURE_STAGES = ("check", "run")
"""Where a failed load fails: the bootloader never answers the check, or the uploaded
firmware never starts (no status packets)."""
FTDI_BASE_CLOCK_HZ = 3_000_000
"""The FT232R's baud base clock: baud = base / divisor [Hz]."""
EMPTY_READ_S = 1e-4
"""Without :class:`UsbTiming`, a read that finds no data still takes this long (the chip
NAKs until its latency timer expires; kept short so tests stay fast) [s]."""


CLOCKS = ("packets", "wall")
"""The emulated device's clocks (:attr:`UsbTiming.clock`)."""
RELEASED_GRIPS = ("held", "falls")
"""What a wall-clock device's grip does while it has zero force (:attr:`UsbTiming.released_grip`)."""
MAX_CATCH_UP_PERIODS = 1000
"""Most periods a wall-clock device lives through at one packet (a longer host stall is cut)."""


def baud_rate(divisor_value: int) -> float:
    """Baud rate [bit/s] of ``divisor_value``, an FTDI baud request's wValue (14-bit divisor
    plus a fraction code in bits 14-15: 0, 1/2, 1/4, 1/8), e.g. 0x4138 -> 9600,
    0x15 -> 142857, 2 -> 1.5 M."""
    fraction = (0.0, 0.5, 0.25, 0.125)[(divisor_value >> 14) & 3]
    divisor = (divisor_value & 0x3FFF) + fraction
    return FTDI_BASE_CLOCK_HZ / max(divisor, 1.0)


@dataclass(frozen=True)
class UsbTiming:
    """Wall-clock timing of USB full speed, the serial link and the FTDI chip.

    Attributes
    ----------
    frame_s : a bulk transfer completes at the next USB frame boundary [s] (1 ms frames).
    dsp_s : the firmware's time to answer a command packet once it has arrived [s] (a longer
        one delays every status: a known extra delay for tests).
    clock : one of :data:`CLOCKS`: ``packets``, the plant steps one period per command packet
        (a host that stops sending stops the plant); ``wall``, the device keeps its own time:
        at each packet the plant first lives through the periods that passed without one
        (at most :data:`MAX_CATCH_UP_PERIODS`), the firmware holding the last command, as a
        real Falcon does while its host stalls (a sleeping host then sees the grip moved on).
    released_grip : one of :data:`RELEASED_GRIPS`, for the ``wall`` clock: ``held``, while the
        held command is zero force (between runs, while the host plans) the grip is held still,
        as a user holds a real one: that time is not lived through; ``falls``, once the device
        is homed nobody holds it (before, the user does: a Falcon homes when its grip is pulled
        out and pushed back in): the device lives through that time too and the grip falls
        under gravity (onto its stops), as a real Falcon let go.
    """

    frame_s: float = 1e-3
    dsp_s: float = 5e-5
    clock: str = "packets"
    released_grip: str = "held"

    def __post_init__(self) -> None:
        if self.clock not in CLOCKS:
            raise InvalidParameterError(f"clock must be one of {CLOCKS}, got {self.clock!r}")
        if self.released_grip not in RELEASED_GRIPS:
            raise InvalidParameterError(f"released_grip must be one of {RELEASED_GRIPS}, got {self.released_grip!r}")

    def next_frame(self, now_s: float) -> float:
        """The first frame boundary after ``now_s`` [s] (monotonic clock)."""
        return (math.floor(now_s / self.frame_s) + 1) * self.frame_s

    def link_delay_s(self, latency_ms: float) -> float:
        """How much longer than the firmware's own command delay a host loop with threaded I/O
        waits for a command's effect [s]: a command goes out in the frame after its tick, the
        status answering it is ready after the serial link both ways (a 16-byte packet at the
        runtime baud rate), the firmware's answer time ``dsp_s`` and the FTDI latency timer
        ``latency_ms`` [ms] (a status is shorter than the 62 bytes that go at once), and is
        read in the first frame after that: whole frames (2 at the defaults: 1 ms frames, the
        1 ms latency timer the driver sets)."""
        serial_s = 10.0 * proto.PACKET_SIZE / baud_rate(BAUD_RUN)
        ready_s = 2.0 * serial_s + self.dsp_s + latency_ms * 1e-3
        return math.ceil(ready_s / self.frame_s - 1e-9) * self.frame_s


def _usb_error(message: str, code: int, errno_value: int) -> Exception:
    return usb.core.USBError(message, error_code=code, errno=errno_value)


TRANSFER_ERRORS: dict[str, Any] = {
    "usb-eio": lambda: _usb_error("Input/Output Error", -1, errno.EIO),
    "usb-pipe": lambda: _usb_error("Pipe error", -9, errno.EPIPE),
    "usb-timeout": lambda: usb.core.USBTimeoutError("Operation timed out", error_code=-7,
                                                    errno=errno.ETIMEDOUT),
    "runtime": lambda: RuntimeError("emulated backend failure"),
    "value": lambda: ValueError("emulated backend got a bad buffer"),
    "os": lambda: OSError(errno.EIO, "emulated host I/O error"),
    "hang": None,
}
"""What a :class:`TransferFault` does, by name: raise the exception the factory makes, or
(``"hang"``) block inside the transfer, as a wedged host controller does, until
:meth:`EmulatedFalconBackend.release_hangs` or ``TransferFault.hang_s`` passed, then
complete normally (or, if the host closed the handle meanwhile, fail as cancelled: nothing
reaches the device)."""
TRANSFER_DIRECTIONS = ("write", "read")
"""Which bulk transfer a :class:`TransferFault` hits: OUT (``write``) or IN (``read``)."""


@dataclass(frozen=True)
class TransferFault:
    """A bulk transfer that fails mid-run.

    Attributes
    ----------
    direction : one of :data:`TRANSFER_DIRECTIONS`.
    kind : one of :data:`TRANSFER_ERRORS` (the exception raised, or ``"hang"``).
    after_packets : the fault starts once the device has received this many runtime
        command packets (homing counts).
    times : transfers that fail, then the bus is healthy again (1: one transient error;
        :data:`NEVER`: every transfer from then on).
    cleared_by_reopen : the fault ends when the host opens the device again (a handle in a
        bad state); False: it outlives a reopen (the bus itself is broken).
    hang_s : longest a ``"hang"`` blocks [s].
    """

    direction: str
    kind: str = "usb-eio"
    after_packets: int = 0
    times: int = 1
    cleared_by_reopen: bool = True
    hang_s: float = 5.0

    def __post_init__(self) -> None:
        if self.direction not in TRANSFER_DIRECTIONS:
            raise InvalidParameterError(f"direction must be one of {TRANSFER_DIRECTIONS}, "
                                        f"got {self.direction!r}")
        if self.kind not in TRANSFER_ERRORS:
            raise InvalidParameterError(f"kind must be one of {tuple(TRANSFER_ERRORS)}, "
                                        f"got {self.kind!r}")
        if self.times < 1 or self.after_packets < 0:
            raise InvalidParameterError(f"times must be >= 1 and after_packets >= 0, got "
                                        f"{self.times!r}, {self.after_packets!r}")


@dataclass(frozen=True)
class FaultPlan:
    """Faults to inject; the defaults inject none.

    Attributes
    ----------
    max_read_bytes : int or None
        Short reads: at most this many data bytes per IN read (packets get split).
    garbage_every : int
        Misaligned reads: put ``garbage_bytes`` random bytes before every n-th status
        packet (0: never).
    garbage_bytes : int
        Garbage bytes per injection.
    drop_every : int
        Dropped packets: give no answer to every n-th command packet (0: never).
    silent_after : int or None
        After this many runtime packets, answer none (the device still obeys commands).
    timeout_after : int or None
        After this many runtime packets, every IN read raises ``USBTimeoutError``.
    failed_checks : int
        The first K firmware checks answer wrong bytes (:data:`NEVER`: always).
    failed_loads : int
        The first N firmware loads fail at ``failed_load_stage`` (a load starts with the
        DTR reset into the bootloader).
    failed_load_stage : str
        One of :data:`LOAD_FAILURE_STAGES`.
    corrupt_echo_at : int or None
        Image byte offset whose echo comes back altered (the host must reject the load).
    disconnect_after : int or None
        After this many runtime packets every transfer raises ``USBError`` (ENODEV).
    permission_denied : bool
        Opening the device raises ``USBError`` (EACCES), as without a udev rule.
    kernel_driver : bool
        The ftdi_sio kernel driver holds interface 0 until the host detaches it.
    byte14 : int or None
        Put this byte into byte 14 of every status packet (undocumented; any value).
    transfer : TransferFault or None
        A bulk transfer that raises or hangs mid-run.
    seed : int
        Seed of the garbage generator.
    """

    max_read_bytes: int | None = None
    garbage_every: int = 0
    garbage_bytes: int = 5
    drop_every: int = 0
    silent_after: int | None = None
    timeout_after: int | None = None
    failed_checks: int = 0
    failed_loads: int = 0
    failed_load_stage: str = "run"
    corrupt_echo_at: int | None = None
    disconnect_after: int | None = None
    permission_denied: bool = False
    kernel_driver: bool = False
    byte14: int | None = None
    transfer: TransferFault | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.failed_load_stage not in LOAD_FAILURE_STAGES:
            raise InvalidParameterError(f"failed_load_stage must be one of "
                                        f"{LOAD_FAILURE_STAGES}, got {self.failed_load_stage!r}")


def _no_device() -> usb.core.USBError:
    return usb.core.USBError("No such device (it may have been disconnected)",
                             error_code=-4, errno=errno.ENODEV)


@dataclass
class EmulatedFalcon:
    """The device's state: FTDI settings, bootloader/firmware state, buffers, plant.

    Read by tests: ``baud_divisor``, ``latency_ms``, ``dtr``, ``rts``, ``data_format``,
    ``flow_control``, ``control_log`` (every control request), ``check_attempts``,
    ``load_attempts``, ``image``, ``firmware_running``, ``packets_received``,
    ``last_commands`` and ``last_flags`` (of the last command packet), :attr:`held_commands`,
    ``disconnected``. Set by tests: ``buttons`` (grip buttons reported in every status packet).
    ``wire_log``, if set, receives one line per command packet (``t_s c0 c1 c2 flags``,
    flushed at once), so a test can read what reached the device after the process died.

    Set up by :class:`EmulatedFalconBackend` (see its parameters): ``plant`` (None: a
    nominal one built when the firmware first runs), ``faults`` (a :class:`FaultPlan`),
    ``homing_packets`` (homing-flag packets before leg 0 homes; legs 1, 2: +5, +10),
    ``expected_image_sha256`` (the only firmware image accepted; None: any non-empty one),
    ``command_hold_s`` (how long the firmware applies a command after the last packet [s];
    None: forever) and ``timing`` (a :class:`UsbTiming`; None: transfers complete at once).
    The other fields are the device's state, starting at power-on values: the FTDI
    settings above, the firmware-load counters and image, ``last_packet_s`` (monotonic time
    of the last command packet [s]; -inf before the first), ``plant_error`` (why the plant
    stopped, after which every transfer fails with EIO; None while it runs),
    ``in_buffer`` (device-to-host bytes waiting for a bulk IN read), ``transfer_faults``
    (transfers the :class:`TransferFault` has hit), ``first_fault_s`` (monotonic time of the
    first [s]) and ``transfer_fault_cleared`` (a reopen ended it). Underscored fields are
    internal and not constructor arguments.
    """

    plant: "SimPlant | None"
    faults: FaultPlan
    homing_packets: int = 20
    expected_image_sha256: str | None = None
    command_hold_s: float | None = None
    timing: UsbTiming | None = None
    wire_log: "IO[str] | None" = None
    baud_divisor: int = 0
    latency_ms: int = 16
    dtr: bool = False
    rts: bool = False
    data_format: int = 0
    flow_control: int = 0
    control_log: list[tuple[int, int, int, int]] = field(default_factory=list)
    check_attempts: int = 0
    load_attempts: int = 0
    image: bytearray = field(default_factory=bytearray)
    firmware_running: bool = False
    packets_received: int = 0
    last_commands: np.ndarray = field(default_factory=lambda: np.zeros(3, dtype=np.int64))
    last_flags: int = 0
    last_packet_s: float = -np.inf
    disconnected: bool = False
    buttons: int = 0
    plant_error: str | None = None
    in_buffer: bytearray = field(default_factory=bytearray)
    transfer_faults: int = 0
    first_fault_s: float | None = None
    transfer_fault_cleared: bool = False
    _pending: deque = field(init=False, default_factory=deque)  # (ready time [s], bytes) with timing
    _clock0_s: float | None = field(init=False, default=None)  # wall clock: monotonic time of plant time 0
    _stage: str = field(init=False, default="boot")  # boot -> armed -> loader -> loading -> running
    _failing_load: bool = field(init=False, default=False)
    _serial: bytearray = field(init=False, default_factory=bytearray)
    _stream: proto.PacketStream = field(
        init=False, default_factory=lambda: proto.PacketStream(proto.COMMAND_FLAGS_MASK))
    _homing_seen: np.ndarray = field(init=False, default_factory=lambda: np.zeros(3, dtype=np.int64))
    _homed: list[bool] = field(init=False, default_factory=lambda: [False, False, False])
    _home_offset: np.ndarray = field(
        init=False, default_factory=lambda: np.array([1234, -2345, 3456], dtype=np.int64))
    _rng: np.random.Generator = field(init=False)
    _clock0_s: float | None = field(init=False, default=None)  # wall-clock plant: its time origin
    _counts: np.ndarray | None = field(init=False, default=None)  # the plant's last reading

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.faults.seed)

    @property
    def held_commands(self) -> np.ndarray:
        """The command the firmware applies now [command units], shape (3,): the last one
        received, forever by default, or zero once ``command_hold_s`` has passed since the
        last packet."""
        hold = self.command_hold_s
        if hold is not None and time.monotonic() - self.last_packet_s > hold:
            return np.zeros(3, dtype=np.int64)
        return self.last_commands.copy()

    @property
    def reported_homed(self) -> tuple[bool, bool, bool]:
        """The homed bits the last status packet carried (libnifalcon: only while the
        homing flag is set)."""
        on = bool(self.last_flags & proto.FLAG_HOMING)
        return tuple(h and on for h in self._homed)  # type: ignore[return-value]

    # -- timing -------------------------------------------------------------------------------
    def _serial_s(self, n_bytes: int) -> float:
        """Time to move ``n_bytes`` over the serial link at the current baud [s]."""
        return 10.0 * n_bytes / baud_rate(self.baud_divisor or BAUD_BOOT)

    def _emit(self, data: bytes, now_s: float) -> None:
        """Queue device-to-host bytes produced at ``now_s`` [s]: readable at once without
        timing; with it, after the serial link and the FTDI latency timer (62 bytes or
        more go at once)."""
        if self.timing is None:
            self.in_buffer.extend(data)
            return
        ready = now_s + self._serial_s(len(data))
        if len(data) < proto.USB_PACKET_SIZE - proto.FTDI_STATUS_BYTES:
            ready += self.latency_ms * 1e-3
        self._pending.append((ready, bytes(data)))

    def release(self, now_s: float) -> None:
        """Move the bytes ready by ``now_s`` [s] into the IN buffer."""
        while self._pending and self._pending[0][0] <= now_s:
            self.in_buffer.extend(self._pending.popleft()[1])

    # -- control requests ---------------------------------------------------------------------
    def control(self, request_type: int, request: int, value: int, index: int) -> None:
        """Apply one FTDI vendor request: ``request_type`` is bmRequestType (only 0x40, vendor
        OUT, is supported; anything else is a pipe error), ``request`` bRequest (FTDI_RESET,
        FTDI_MODEM_CTRL, ...), ``value`` wValue (its argument, e.g. the baud divisor) and
        ``index`` wIndex (the FTDI port; recorded only)."""
        self.control_log.append((request_type, request, value, index))
        if request_type != 0x40:
            raise usb.core.USBError("Pipe error (request not supported)", error_code=-9,
                                    errno=errno.EPIPE)
        if request == FTDI_RESET:
            if value in (0, PURGE_RX):
                self.in_buffer.clear()
                self._pending.clear()
            if value in (0, PURGE_TX):
                self._serial.clear()
                self._stream.clear()
        elif request == FTDI_MODEM_CTRL:
            if value & 0x0100:
                was_low = not self.dtr
                self.dtr = bool(value & 0x01)
                if self.dtr and was_low and self.baud_divisor == BAUD_BOOT:
                    self._reset_into_bootloader()
            if value & 0x0200:
                self.rts = bool(value & 0x02)
        elif request == FTDI_FLOW_CTRL:
            self.flow_control = value
        elif request == FTDI_BAUD:
            self.baud_divisor = value
            if value == BAUD_RUN and self._stage == "loading":
                self._finish_load()
        elif request == FTDI_DATA:
            self.data_format = value
        elif request == FTDI_LATENCY:
            self.latency_ms = value

    def _reset_into_bootloader(self) -> None:
        """A DTR rise at 9600 baud resets the DSP (a running firmware stops): one load
        begins (libnifalcon ``setFirmwareMode``: RTS low, DTR low, DTR high, once)."""
        self.firmware_running = False
        self._stage = "armed"
        self._serial.clear()
        self.load_attempts += 1
        self._failing_load = self.load_attempts <= self.faults.failed_loads

    # -- OUT data -----------------------------------------------------------------------------
    def receive(self, data: bytes, now_s: float) -> None:
        """``data``, bytes written by the host to the bulk OUT endpoint, arriving at ``now_s``
        [s] (monotonic clock)."""
        if self.firmware_running:
            arrive = now_s + (0.0 if self.timing is None
                              else self._serial_s(proto.PACKET_SIZE) + self.timing.dsp_s)
            for packet in self._stream.feed(data):
                self._run_packet(packet, arrive)
            return
        if self._stage == "armed":
            self._serial.extend(data)
            if len(self._serial) >= len(CHECK_REQUEST):
                request = bytes(self._serial[:len(CHECK_REQUEST)])
                del self._serial[:len(CHECK_REQUEST)]
                self.check_attempts += 1
                if self._failing_load and self.faults.failed_load_stage == "check":
                    return                                          # this load never answers
                if request == CHECK_REQUEST and self.check_attempts > self.faults.failed_checks:
                    # the leading 0x00 comes only sometimes: here on odd attempts
                    lead = b"\x00" if self.check_attempts % 2 else b""
                    self._emit(lead + CHECK_REPLY, now_s)
                    self._stage = "loader"
                else:
                    # A wrong answer; the bootloader stays armed, so a plain resend of the
                    # check can pass (libnifalcon resends up to 100 times, no new DTR pulse).
                    self._emit(b"\x0a\x45\x2e\x0d", now_s)
        elif self._stage == "loader":
            if self.baud_divisor == BAUD_LOADER and not self.dtr and data[:1] == b"A":
                self._emit(b"A", now_s)
                self._stage = "loading"
                self.image.clear()
                if len(data) > 1:
                    self.receive(data[1:], now_s)
        elif self._stage == "loading":
            echo = bytearray(data)
            at = self.faults.corrupt_echo_at
            if at is not None and len(self.image) <= at < len(self.image) + len(data):
                echo[at - len(self.image)] ^= 0xFF
            self.image.extend(data)
            self._emit(bytes(echo), now_s)
        # stage "boot": the DSP ignores bytes until it is reset by a DTR pulse

    def _finish_load(self) -> None:
        ok = bool(self.image) and not self._failing_load
        if ok and self.expected_image_sha256 is not None:
            ok = hashlib.sha256(bytes(self.image)).hexdigest() == self.expected_image_sha256
        self.firmware_running = ok
        self._stage = "running" if ok else "boot"

    def _run_packet(self, packet: bytes, now_s: float) -> None:
        command = proto.decode_command_packet(packet)
        self.packets_received += 1
        held = self.last_commands
        self.last_commands = np.array(command.commands, dtype=np.int64)
        self.last_flags = command.flags
        self.last_packet_s = time.monotonic()
        if self.wire_log is not None:
            self.wire_log.write(f"{self.last_packet_s:.6f} {command.commands[0]} "
                                f"{command.commands[1]} {command.commands[2]} {command.flags}\n")
            self.wire_log.flush()
        try:
            if self.timing is not None and self.timing.clock == "wall":
                self._catch_up(held, now_s)
            if self._user_holds(held) and not np.any(self.last_commands) and self._counts is not None:
                # zero force before and in this packet, the grip held still (e.g. a service polling
                # its idle device's state; stepped once a poll instead, the grip fell onto its
                # stops within seconds): nothing moves
                counts = self._counts
            else:
                counts = np.asarray(self._plant().step(self.last_commands), dtype=np.int64)
            self._counts = counts
        except FalconPlanError as exc:
            # The plant cannot go on (e.g. it left the reachable workspace): the
            # emulated device fails like hardware does, with an I/O error on the bus.
            self.plant_error = str(exc)
            raise usb.core.USBError(f"Input/Output Error (emulated Falcon: {exc})",
                                    error_code=-1, errno=errno.EIO) from exc
        if command.homing:
            self._homing_seen += 1
            for leg in range(3):
                if self._homing_seen[leg] >= self.homing_packets + 5 * leg:
                    self._homed[leg] = True
        wire = counts.reshape(3) + np.where(self._homed, 0, self._home_offset)
        silent_after = self.faults.silent_after
        if silent_after is not None and self.packets_received > silent_after:
            return
        if self.faults.drop_every and self.packets_received % self.faults.drop_every == 0:
            return
        out = bytearray()
        if self.faults.garbage_every and self.packets_received % self.faults.garbage_every == 0:
            out += self._rng.integers(0, 256, self.faults.garbage_bytes, dtype=np.uint8).tobytes()
        status = bytearray(proto.encode_status_packet(wire, self.buttons, self.reported_homed))
        if self.faults.byte14 is not None:
            status[proto.UNKNOWN_INDEX] = self.faults.byte14
        self._emit(bytes(out + status), now_s)

    def _user_holds(self, held: np.ndarray) -> bool:
        """Whether the user holds the grip while the firmware's ``held`` command is zero force: a
        wall-clock device whose released grip is ``held``, or one not homed yet (the user homes
        it)."""
        timing = self.timing
        if timing is None or timing.clock != "wall" or np.any(held):
            return False
        return timing.released_grip == "held" or not all(self._homed)

    def _catch_up(self, held: np.ndarray, now_s: float) -> None:
        """Wall clock: step the plant through the periods that passed since the last packet
        (``now_s`` [s], monotonic) with no new command (the firmware keeps acting on the
        ``held`` one until its command hold runs out, then drops the force, as a real Falcon
        does when its host stalls), so that this packet's step is the period in progress now.
        With zero force held (unless ``UsbTiming.released_grip`` is ``falls``), or a stall
        longer than :data:`MAX_CATCH_UP_PERIODS`, the device clock starts again from here
        instead (a user holds a released grip still). The device's periods start half a period away from a
        packet that (re)starts its clock, so that packets arriving once a period with some
        jitter fall into one period each (with a period boundary at the packets' own phase,
        the jitter would have the plant live one period more or fewer at random, and the
        delay of every later command change by a period)."""
        plant = self._plant()
        lived = int(round(plant.time_s / plant.dt_s))
        if self._clock0_s is None:                 # the first packet: the device clock starts
            self._clock0_s = now_s - (lived + 0.5) * plant.dt_s
            return
        behind = int((now_s - self._clock0_s) / plant.dt_s) - lived
        if behind > 0 and (self._user_holds(held) or behind > MAX_CATCH_UP_PERIODS):
            self._clock0_s = now_s - (lived + 0.5) * plant.dt_s   # the device clock starts again
            return
        for _ in range(behind):
            plant.step(None)

    def _plant(self) -> "SimPlant":
        if self.plant is None:
            from falcon_plan.sim.plant import SimPlant

            self.plant = SimPlant(rate_hz=1000.0)
        return self.plant

    # -- IN data ------------------------------------------------------------------------------
    def send(self, size: int) -> bytes:
        """One bulk IN read of up to ``size`` bytes: 2 status bytes per 64-byte USB packet."""
        room = min(len(self.in_buffer), self.faults.max_read_bytes or len(self.in_buffer))
        out = bytearray()
        while len(out) + proto.FTDI_STATUS_BYTES <= size:
            take = min(room, proto.USB_PACKET_SIZE - proto.FTDI_STATUS_BYTES,
                       size - len(out) - proto.FTDI_STATUS_BYTES)
            out += FTDI_MODEM_STATUS + self.in_buffer[:take]
            del self.in_buffer[:take]
            room -= take
            if room <= 0:
                break
        return bytes(out)

    def check_reachable(self) -> None:
        """Raise ENODEV once the injected disconnect has happened."""
        limit = self.faults.disconnect_after
        if limit is not None and self.packets_received >= limit:
            self.disconnected = True
        if self.disconnected:
            raise _no_device()
        if self.plant_error is not None:
            raise usb.core.USBError(f"Input/Output Error (emulated Falcon: {self.plant_error})",
                                    error_code=-1, errno=errno.EIO)


class EmulatedFalconBackend(usb.backend.IBackend):
    """A pyusb backend with one emulated Falcon on it.

    Parameters
    ----------
    plant : SimPlant, optional
        The plant behind the device (default: a nominal ``SimPlant(rate_hz=1000)`` built
        when the firmware first runs).
    faults : FaultPlan
        Faults to inject.
    homing_packets : int
        Packets with the homing flag before leg 0 reports homed (legs 1, 2: +5, +10).
    expected_image_sha256 : str, optional
        Accept only this firmware image (default: any non-empty image).
    present : bool
        False: the bus is empty (no device to find).
    firmware_running : bool
        True: the firmware is already loaded (a re-open without power cycle).
    command_hold_s : float, optional
        The firmware drops the force this long after the last packet [s]; None (default):
        it applies the last command forever (nothing public says otherwise).
    timing : UsbTiming, optional
        Wall-clock USB/serial/FTDI timing (default: every transfer completes at once).
    wire_log : str or Path, optional
        File that receives one line per command packet (see :class:`EmulatedFalcon`).
    port_numbers : tuple of int
        The USB port path (more than one number: behind a hub).

    The ``usb.backend.IBackend`` methods take pyusb's arguments: ``dev`` is the enumerated
    device (the string "falcon"), ``dev_handle`` what :meth:`open_device` returned, ``intf``
    the interface number (only 0 exists), ``ep`` an endpoint (address for transfers and
    ``clear_halt``, index for descriptors), ``timeout`` pyusb's limit [ms] (not used: an
    emulated transfer waits at most one USB frame).
    """

    def __init__(self, plant: "SimPlant | None" = None, faults: FaultPlan = FaultPlan(), *,
                 homing_packets: int = 20, expected_image_sha256: str | None = None,
                 present: bool = True, firmware_running: bool = False,
                 command_hold_s: float | None = None, timing: UsbTiming | None = None,
                 wire_log: str | Path | None = None,
                 port_numbers: tuple[int, ...] = (1,)) -> None:
        super().__init__()
        log_file = None if wire_log is None else open(wire_log, "a", encoding="utf-8")  # noqa: SIM115
        self.falcon = EmulatedFalcon(plant, faults, homing_packets, expected_image_sha256,
                                     command_hold_s, timing, log_file)
        """The emulated device's state (for tests)."""
        if firmware_running:
            self.falcon.firmware_running = True
            self.falcon._stage = "running"
        self.present = present
        self.port_numbers = tuple(port_numbers)
        self.configuration = 0
        self.claimed: set[int] = set()
        self.open_handles = 0
        self.open_count = 0
        """Times the device was opened (a whole-load retry closes and reopens it)."""
        self.kernel_driver_active = faults.kernel_driver
        self._lock = threading.RLock()     # re-entrant: a signal handler may write
        self._release = threading.Event()
        self._closes = 0                   # handles closed so far

    @property
    def device_clock(self) -> str:
        """How the emulated Falcon keeps time: "wall" (``UsbTiming(clock="wall")``: it lives
        through the time between packets, as a real one does) or "ticks" (one period per packet)."""
        timing = self.falcon.timing
        return "wall" if timing is not None and timing.clock == "wall" else "ticks"

    @property
    def link_delay_s(self) -> float:
        """What the USB path adds to the firmware's command delay for a threaded host [s]
        (:meth:`UsbTiming.link_delay_s` at the FTDI latency timer now set; 0 without timing:
        every transfer completes at once)."""
        timing = self.falcon.timing
        return 0.0 if timing is None else timing.link_delay_s(self.falcon.latency_ms)

    def release_hangs(self) -> None:
        """End every ``"hang"`` transfer fault now (and any later one at once)."""
        self._release.set()

    def _transfer_fault(self, direction: str) -> None:
        """Raise (or hang) here if the fault plan's :class:`TransferFault` hits this bulk
        transfer (``direction``: "write" or "read")."""
        fault = self.falcon.faults.transfer
        if fault is None or fault.direction != direction:
            return
        with self._lock:
            falcon = self.falcon
            if (falcon.transfer_fault_cleared or falcon.packets_received < fault.after_packets
                    or falcon.transfer_faults >= fault.times):
                return
            falcon.transfer_faults += 1
            if falcon.first_fault_s is None:
                falcon.first_fault_s = time.monotonic()
        make_error = TRANSFER_ERRORS[fault.kind]
        if make_error is None:
            closes = self._closes
            self._release.wait(fault.hang_s)
            if self._closes != closes:     # libusb cancels what is pending on a closed handle
                raise usb.core.USBError("Transfer cancelled (its handle was closed)",
                                        error_code=-10, errno=errno.ECANCELED)
            return
        raise make_error()

    # -- enumeration and descriptors ----------------------------------------------------------
    def enumerate_devices(self) -> Iterator[str]:
        if self.present and not self.falcon.disconnected:
            yield "falcon"

    def get_device_descriptor(self, dev: Any) -> SimpleNamespace:
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=8, idVendor=FALCON_VID, idProduct=FALCON_PID,
            bcdDevice=0x0600, iManufacturer=1, iProduct=2, iSerialNumber=3,
            bNumConfigurations=1, address=2, bus=1, port_number=self.port_numbers[-1],
            port_numbers=self.port_numbers, speed=2)

    def get_configuration_descriptor(self, dev: Any, config: int) -> SimpleNamespace:
        if config != 0:
            raise IndexError(f"configuration index {config} out of range")
        return SimpleNamespace(
            bLength=9, bDescriptorType=2, wTotalLength=32, bNumInterfaces=1,
            bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80, bMaxPower=45,
            extra_descriptors=[])

    def get_interface_descriptor(self, dev: Any, intf: int, alt: int,
                                 config: int) -> SimpleNamespace:
        if (intf, alt, config) != (0, 0, 0):
            raise IndexError(f"interface {intf} alt {alt} config {config} out of range")
        return SimpleNamespace(
            bLength=9, bDescriptorType=4, bInterfaceNumber=0, bAlternateSetting=0,
            bNumEndpoints=2, bInterfaceClass=0xFF, bInterfaceSubClass=0xFF,
            bInterfaceProtocol=0xFF, iInterface=2, extra_descriptors=[])

    def get_endpoint_descriptor(self, dev: Any, ep: int, intf: int, alt: int,
                                config: int) -> SimpleNamespace:
        if (intf, alt, config) != (0, 0, 0) or ep not in (0, 1):
            raise IndexError(f"endpoint {ep} out of range")
        return SimpleNamespace(
            bLength=7, bDescriptorType=5, bEndpointAddress=(EP_IN, EP_OUT)[ep],
            bmAttributes=0x02, wMaxPacketSize=proto.USB_PACKET_SIZE, bInterval=0,
            bRefresh=0, bSynchAddress=0, extra_descriptors=[])

    # -- handles ------------------------------------------------------------------------------
    def open_device(self, dev: Any) -> str:
        self.falcon.check_reachable()
        if self.falcon.faults.permission_denied:
            raise usb.core.USBError("Access denied (insufficient permissions)",
                                    error_code=-3, errno=errno.EACCES)
        self.open_handles += 1
        self.open_count += 1
        fault = self.falcon.faults.transfer
        if fault is not None and fault.cleared_by_reopen and self.falcon.transfer_faults:
            self.falcon.transfer_fault_cleared = True
        return "handle"

    def close_device(self, dev_handle: Any) -> None:
        self.open_handles = max(0, self.open_handles - 1)
        self._closes += 1

    def set_configuration(self, dev_handle: Any, config_value: int) -> None:
        self.falcon.check_reachable()
        self.configuration = config_value

    def get_configuration(self, dev_handle: Any) -> int:
        self.falcon.check_reachable()
        return self.configuration

    def set_interface_altsetting(self, dev_handle: Any, intf: int, altsetting: int) -> None:
        self.falcon.check_reachable()

    def claim_interface(self, dev_handle: Any, intf: int) -> None:
        self.falcon.check_reachable()
        if self.kernel_driver_active:
            raise usb.core.USBError("Resource busy (ftdi_sio holds the interface)",
                                    error_code=-6, errno=errno.EBUSY)
        self.claimed.add(intf)

    def release_interface(self, dev_handle: Any, intf: int) -> None:
        self.claimed.discard(intf)
        self.falcon.check_reachable()

    def is_kernel_driver_active(self, dev_handle: Any, intf: int) -> bool:
        return self.kernel_driver_active

    def detach_kernel_driver(self, dev_handle: Any, intf: int) -> None:
        self.kernel_driver_active = False

    def attach_kernel_driver(self, dev_handle: Any, intf: int) -> None:
        self.kernel_driver_active = True

    def clear_halt(self, dev_handle: Any, ep: int) -> None:
        self.falcon.check_reachable()

    def reset_device(self, dev_handle: Any) -> None:
        self.falcon.check_reachable()

    # -- transfers ----------------------------------------------------------------------------
    # Transfers may come from two threads (the driver's reader and writer): the device state
    # is locked, the waits for a USB frame happen outside the lock.
    def _wait_frame(self) -> float:
        """With timing, sleep to the next USB frame boundary; return the time [s]. A thread that
        wakes a whole frame or more after it (a host stall) gets the frame it woke in: the
        transfer went then, and a wall-clock device lives to that time (returning the missed
        boundary had the plant lag the wall clock by the stall and then catch up several
        periods in one status, a step of 125 counts in 1.5 ms that the encoder-step guard
        stopped, and readings two periods old dated as new)."""
        now = time.monotonic()
        timing = self.falcon.timing
        if timing is None:
            return now
        boundary = timing.next_frame(now)
        time.sleep(max(0.0, boundary - time.monotonic()))
        woke = time.monotonic()
        return boundary if woke < boundary + timing.frame_s else timing.next_frame(woke) - timing.frame_s

    def bulk_write(self, dev_handle: Any, ep: int, intf: int, data: Any, timeout: int) -> int:
        with self._lock:
            self.falcon.check_reachable()
        self._transfer_fault("write")
        if ep != EP_OUT:
            raise usb.core.USBError(f"Invalid endpoint {ep:#x} for writing", errno=errno.EINVAL)
        payload = bytes(data)
        now = self._wait_frame()                  # the OUT packet goes in the next frame
        with self._lock:
            self.falcon.check_reachable()
            self.falcon.receive(payload, now)
        return len(payload)

    def bulk_read(self, dev_handle: Any, ep: int, intf: int, buff: Any, timeout: int) -> int:
        with self._lock:
            self.falcon.check_reachable()
            limit = self.falcon.faults.timeout_after
            if limit is not None and self.falcon.packets_received >= limit:
                raise usb.core.USBTimeoutError("Operation timed out", error_code=-7,
                                               errno=errno.ETIMEDOUT)
        self._transfer_fault("read")
        if ep != EP_IN:
            raise usb.core.USBError(f"Invalid endpoint {ep:#x} for reading", errno=errno.EINVAL)
        now = self._wait_frame()                  # the IN packet comes in the next frame
        with self._lock:
            self.falcon.check_reachable()
            self.falcon.release(now)
            empty = not self.falcon.in_buffer
            chunk = self.falcon.send(len(buff) * buff.itemsize)
        if empty and self.falcon.timing is None:
            time.sleep(EMPTY_READ_S)
        buff[:len(chunk)] = type(buff)(buff.typecode, chunk)
        return len(chunk)

    def ctrl_transfer(self, dev_handle: Any, bmRequestType: int, bRequest: int, wValue: int,
                      wIndex: int, data: Any, timeout: int) -> int:
        with self._lock:
            self.falcon.check_reachable()
            self.falcon.control(bmRequestType, bRequest, wValue, wIndex)
        return 0 if data is None else len(data)
