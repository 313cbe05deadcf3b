"""The Falcon's USB packet codec (nVent firmware), as pure functions: no I/O.

Wire format (``/work/shared/FALCON-USB.md``, "Runtime packets"): 16 bytes, ``'<'`` then 14
payload bytes each holding a 4-bit value plus 0x41 (``'A'`` is 0), then ``'>'``.

- Host to device: bytes 1-12 are three signed 16-bit motor commands, four nibbles each,
  least significant first; byte 13 holds flags (:data:`FLAG_HOMING` and the LED bits of
  :mod:`falcon_plan.devices.base`); byte 14 is 0. Commands are clamped to +-4096 (inside the
  int16 range) before packing, so a large value can never wrap around.
- Device to host: bytes 1-12 are three encoder counts, encoded the same way; byte 13 holds
  the grip buttons (low nibble) and the homed bits 0x10, 0x20, 0x40 (legs 0, 1, 2), so its
  value may exceed one nibble (up to 0x7F, byte up to 0xC0); byte 14 is not documented
  (libnifalcon's ``FalconFirmwareNovintSDK.h`` calls it "unknown" and its ``formatOutput``
  checks only the ``'<'``/``'>'`` framing), so any byte is accepted there when reading; the
  host sends it as 0.

Every known payload byte is >= 0x41, so ``'<'`` (0x3C) appears inside a valid packet at
most as the unknown byte 14: :class:`PacketStream` resynchronises on that (a rejected
candidate frame is dropped up to the next ``'<'`` after its start, so garbage can never
swallow a real packet).

Every 64-byte USB IN packet of the FTDI chip starts with 2 modem/line-status bytes that carry
no data: :func:`strip_ftdi_status` removes them (a read of only those 2 bytes means "no data").

Encoder counts are 16-bit on the wire and wrap around at +-32768. :func:`unwrap_counts`
makes them continuous: the new value is the one nearest the previous reading that matches the
16 wire bits (valid while a leg moves less than 32768 counts between two readings; the whole
leg travel is about 3000 counts, so a real device never wraps, but the code is safe if it
does).
"""
from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from falcon_plan.devices.base import COMMAND_LIMIT, LED_MASK, clamp_commands
from falcon_plan.errors import DeviceError, InvalidParameterError

PACKET_SIZE = 16
"""Bytes in one runtime packet."""
START_BYTE = 0x3C
"""``'<'``: first byte of a packet."""
END_BYTE = 0x3E
"""``'>'``: last byte of a packet."""
NIBBLE_OFFSET = 0x41
"""Added to every payload value (``'A'`` is 0)."""
FLAG_HOMING = 0x01
"""Host flag: homing mode. libnifalcon (``FalconFirmware.h``, "Homing Mode") says it must be
set in every packet for the device to stay homed, and its status packets carry the homed bits
only while it is set; the driver sets it from the start of homing on and never drops it."""
FLAGS_INDEX = 13
"""Byte holding the flags (host) or buttons and homed bits (device)."""
UNKNOWN_INDEX = 14
"""Byte the protocol leaves undocumented: checked for framing only."""
COMMAND_FLAGS_MASK = FLAG_HOMING | LED_MASK
"""Every flag bit a host packet may carry."""
BUTTONS_MASK = 0x0F
"""Grip buttons in the status flags byte."""
HOMED_BITS = (0x10, 0x20, 0x40)
"""Homed bit of legs 0, 1, 2 in the status flags byte."""
STATUS_FLAGS_MASK = BUTTONS_MASK | HOMED_BITS[0] | HOMED_BITS[1] | HOMED_BITS[2]
"""Every bit a status flags byte may carry."""
FTDI_STATUS_BYTES = 2
"""Modem/line-status bytes at the start of every USB IN packet."""
USB_PACKET_SIZE = 64
"""Bytes per USB bulk packet (the 2 status bytes included)."""

# --- USB device and FTDI bootloader facts (FALCON-USB.md) -------------------------------
FALCON_VID = 0x0403
"""FTDI's USB vendor id."""
FALCON_PID = 0xCB48
"""The Falcon's product id."""
EP_IN = 0x81
"""Bulk IN endpoint (device to host)."""
EP_OUT = 0x02
"""Bulk OUT endpoint (host to device)."""

FTDI_RESET, FTDI_MODEM_CTRL, FTDI_FLOW_CTRL, FTDI_BAUD, FTDI_DATA, FTDI_LATENCY = 0, 1, 2, 3, 4, 9
"""FTDI vendor bRequest codes."""
PURGE_RX, PURGE_TX = 1, 2
"""wValue of the reset request that purges the RX (device to host) or TX buffer."""
DTR_HIGH, DTR_LOW, RTS_LOW = 0x0101, 0x0100, 0x0200
"""wValue of the modem-control request."""
BAUD_BOOT, BAUD_LOADER, BAUD_RUN = 0x4138, 0x15, 0x02
"""Baud divisors: 9600 (handshake), about 140 kbaud (image upload), 1.5 Mbaud (runtime)."""
DATA_8N1 = 0x0008
"""wValue of the data-format request for 8 data bits, no parity, 1 stop bit."""

CHECK_REQUEST = bytes((0x0A, 0x43, 0x0D))
"""Bytes the host sends to check the bootloader."""
CHECK_REPLY = bytes((0x0A, 0x44, 0x2C, 0x0D))
"""The bootloader's answer (sometimes preceded by 0x00)."""
LOAD_START = 0x41
"""``'A'``: starts the image upload; echoed."""

INT16_MIN, INT16_MAX = -(1 << 15), (1 << 15) - 1


@dataclass(frozen=True)
class StatusPacket:
    """A decoded device-to-host packet.

    Attributes
    ----------
    counts : tuple[int, int, int]
        Encoder counts as on the wire: signed 16-bit, not unwrapped [counts].
    buttons : int
        Grip buttons bit mask (0..15).
    homed : tuple[bool, bool, bool]
        Per-leg homed bits.
    """

    counts: tuple[int, int, int]
    buttons: int
    homed: tuple[bool, bool, bool]


@dataclass(frozen=True)
class CommandPacket:
    """A decoded host-to-device packet: commands (signed 16-bit) and flags."""

    commands: tuple[int, int, int]
    flags: int

    @property
    def homing(self) -> bool:
        """True if the homing flag is set."""
        return bool(self.flags & FLAG_HOMING)


# --- nibble framing ------------------------------------------------------------------------
def _frame(words: Iterable[int], flags: int) -> bytes:
    """Pack three 16-bit words and a flags value (0..0x7F) into a 16-byte packet."""
    values: list[int] = []
    for word in words:
        w = int(word) & 0xFFFF
        values.extend((w >> shift) & 0xF for shift in (0, 4, 8, 12))
    values.extend((flags, 0))
    return bytes((START_BYTE, *(v + NIBBLE_OFFSET for v in values), END_BYTE))


def _is_nibble(b: int) -> bool:
    return NIBBLE_OFFSET <= b <= NIBBLE_OFFSET + 0xF


@functools.lru_cache(maxsize=None)
def _packet_pattern(flags_mask: int) -> re.Pattern[bytes]:
    """A whole valid packet whose flags use only ``flags_mask`` bits, as a compiled regular
    expression (the rule of :func:`is_valid_packet`, one C-level match per packet)."""
    flags = bytes(NIBBLE_OFFSET + v for v in range(256 - NIBBLE_OFFSET) if not v & ~flags_mask)
    nibble = re.escape(bytes(range(NIBBLE_OFFSET, NIBBLE_OFFSET + 0x10)))
    return re.compile(re.escape(bytes((START_BYTE,))) + b"[" + nibble + b"]{12}[" + re.escape(flags)
                      + b"]." + re.escape(bytes((END_BYTE,))), re.DOTALL)


def is_valid_packet(packet: bytes, flags_mask: int = STATUS_FLAGS_MASK) -> bool:
    """True if ``packet`` is one well-formed 16-byte packet whose flags byte only uses
    ``flags_mask`` bits (byte 14 is framing only: any value)."""
    return len(packet) == PACKET_SIZE and _packet_pattern(flags_mask).match(packet) is not None


_DENIBBLE = bytes((b - NIBBLE_OFFSET) & 0xFF for b in range(256))
"""Translation table: a payload byte to its value (byte - 0x41)."""


def _unframe(packet: bytes, flags_mask: int, what: str) -> tuple[tuple[int, int, int], int]:
    """Split a packet into three signed 16-bit words and the flags value."""
    packet = bytes(packet)
    if not is_valid_packet(packet, flags_mask):
        raise DeviceError(f"malformed {what} packet {packet!r}: expected 16 bytes '<' + 14 "
                          f"values (+0x41) + '>' with flags in {flags_mask:#x}")
    v = packet.translate(_DENIBBLE)
    words = [v[j] | v[j + 1] << 4 | v[j + 2] << 8 | v[j + 3] << 12 for j in (1, 5, 9)]
    words = [w - 0x10000 if w & 0x8000 else w for w in words]
    return (words[0], words[1], words[2]), v[FLAGS_INDEX]


# --- host to device ------------------------------------------------------------------------
def encode_command_packet(commands: Any, flags: int = 0) -> bytes:
    """Encode three motor commands and the flags into a 16-byte packet.

    Parameters
    ----------
    commands : array-like
        Three numbers [command units]; rounded, then clamped to the int16 range and to
        +-COMMAND_LIMIT (never wrapped).
    flags : int
        :data:`FLAG_HOMING` and LED bits (:data:`COMMAND_FLAGS_MASK`).
    """
    if isinstance(flags, bool) or not 0 <= int(flags) <= COMMAND_FLAGS_MASK:
        raise InvalidParameterError(
            f"command flags must be within {COMMAND_FLAGS_MASK:#x} (homing 0x01, LEDs "
            f"0x02/0x04/0x08), got {flags!r}")
    return _frame(clamp_commands(commands).tolist(), int(flags))   # +-4096: inside int16


def decode_command_packet(packet: bytes) -> CommandPacket:
    """Decode a host-to-device packet (the emulated device's side)."""
    words, flags = _unframe(packet, COMMAND_FLAGS_MASK, "command")
    return CommandPacket(words, flags)


# --- device to host ------------------------------------------------------------------------
def encode_status_packet(counts: Any, buttons: int = 0,
                         homed: Iterable[bool] = (False, False, False)) -> bytes:
    """Encode a device-to-host packet: ``counts`` (3 integers [counts]) are sent as their low
    16 bits (the wire wraps, as the real encoders' registers do); ``buttons`` is the grip
    buttons bit mask (0..15); ``homed`` the three per-leg homed flags (legs 0, 1, 2)."""
    if not 0 <= int(buttons) <= BUTTONS_MASK:
        raise InvalidParameterError(f"buttons must be within 0..15, got {buttons!r}")
    c = [int(v) for v in np.asarray(counts, dtype=np.int64).reshape(3)]
    flags = int(buttons)
    for bit, h in zip(HOMED_BITS, homed, strict=True):
        flags |= bit if h else 0
    return _frame(c, flags)


def decode_status_packet(packet: bytes) -> StatusPacket:
    """Decode a device-to-host packet into counts (signed 16-bit), buttons and homed bits.

    Raises
    ------
    DeviceError
        The bytes are not one well-formed status packet.
    """
    words, flags = _unframe(packet, STATUS_FLAGS_MASK, "status")
    homed = tuple(bool(flags & bit) for bit in HOMED_BITS)
    return StatusPacket(words, flags & BUTTONS_MASK, homed)  # type: ignore[arg-type]


def unwrap_counts(wire_counts: Any, previous: Any | None) -> np.ndarray:
    """Continuous counts from 16-bit wire counts.

    Parameters
    ----------
    wire_counts : array-like
        Three counts as decoded (any integers; only the low 16 bits matter) [counts].
    previous : array-like or None
        The previous unwrapped reading; None for the first reading (taken as signed 16-bit).

    Returns
    -------
    np.ndarray
        int64 (3,): for each leg the value congruent to the wire value modulo 65536 that is
        nearest ``previous`` [counts].
    """
    wire = np.asarray(wire_counts, dtype=np.int64).reshape(3)
    if previous is None:
        return ((wire + 0x8000) & 0xFFFF) - 0x8000
    prev = np.asarray(previous, dtype=np.int64).reshape(3)
    delta = ((wire - prev + 0x8000) & 0xFFFF) - 0x8000
    return prev + delta


# --- FTDI framing --------------------------------------------------------------------------
def strip_ftdi_status(data: bytes, packet_size: int = USB_PACKET_SIZE) -> bytes:
    """Remove the 2 FTDI status bytes from every ``packet_size``-byte USB packet of ``data``,
    the bytes of one bulk read (a read may return several USB packets back to back)."""
    data = bytes(data)
    return b"".join(data[i + FTDI_STATUS_BYTES: i + packet_size]
                    for i in range(0, len(data), packet_size))


class PacketStream:
    """Reassemble whole packets from arbitrary chunks of the byte stream.

    ``feed`` accepts any chunk (short, misaligned, with garbage) and returns the valid
    packets it completed, in order. Bytes that cannot belong to a valid packet are dropped
    and counted in :attr:`discarded`. At most one partial packet is kept.

    Parameters
    ----------
    flags_mask : int
        Flag bits a valid packet may carry (status packets by default; pass
        :data:`COMMAND_FLAGS_MASK` to parse host packets).
    """

    def __init__(self, flags_mask: int = STATUS_FLAGS_MASK) -> None:
        self.flags_mask = flags_mask
        self._buf = bytearray()
        self.discarded = 0
        """Bytes dropped while resynchronising."""

    @property
    def pending(self) -> int:
        """Bytes held waiting for the rest of a packet."""
        return len(self._buf)

    def clear(self) -> None:
        """Forget any partial packet (after a purge)."""
        self._buf.clear()

    def _payload_ok(self, b: int, index: int) -> bool:
        if index == FLAGS_INDEX:
            v = b - NIBBLE_OFFSET
            return v >= 0 and not v & ~self.flags_mask
        return index == UNKNOWN_INDEX or _is_nibble(b)

    def feed(self, chunk: bytes) -> list[bytes]:
        """Add bytes; return the whole valid packets completed by them."""
        buf = self._buf
        buf.extend(chunk)
        packets: list[bytes] = []
        while buf:
            start = buf.find(START_BYTE)
            if start < 0:
                self.discarded += len(buf)
                buf.clear()
                break
            if start:
                self.discarded += start
                del buf[:start]
            if self._valid_prefix(buf):
                if len(buf) < PACKET_SIZE:
                    break                      # a good partial packet: wait for more
                packets.append(bytes(buf[:PACKET_SIZE]))
                del buf[:PACKET_SIZE]
            else:
                # Not a packet: drop up to the next '<' (the next possible start).
                cut = buf.find(START_BYTE, 1)
                cut = len(buf) if cut < 0 else cut
                self.discarded += cut
                del buf[:cut]
        return packets

    def _valid_prefix(self, buf: bytearray) -> bool:
        """True if ``buf[:16]`` (which starts with '<') is a valid packet or the start of one."""
        if len(buf) >= PACKET_SIZE and _packet_pattern(self.flags_mask).match(buf) is not None:
            return True                        # the usual case: one whole packet
        for i in range(1, min(len(buf), PACKET_SIZE)):
            b = buf[i]
            if not (b == END_BYTE if i == PACKET_SIZE - 1 else self._payload_ok(b, i)):
                return False
        return True


__all__ = [
    "COMMAND_FLAGS_MASK", "COMMAND_LIMIT", "CommandPacket", "FLAG_HOMING", "HOMED_BITS",
    "PACKET_SIZE", "PacketStream", "StatusPacket", "decode_command_packet",
    "decode_status_packet", "encode_command_packet", "encode_status_packet",
    "is_valid_packet", "strip_ftdi_status", "unwrap_counts",
]
