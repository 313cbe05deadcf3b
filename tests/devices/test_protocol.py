"""The packet codec: encode/decode round trips, clamping, wrap-around, resynchronisation."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from falcon_plan.devices import protocol as proto
from falcon_plan.errors import DeviceError, InvalidParameterError

ALL_HOMED = list(itertools.product((False, True), repeat=3))


def test_zero_packet_is_all_As() -> None:
    assert proto.encode_command_packet([0, 0, 0]) == b"<AAAAAAAAAAAAAA>"
    assert proto.encode_status_packet([0, 0, 0]) == b"<AAAAAAAAAAAAAA>"


def test_known_packet_nibble_order() -> None:
    # 1 -> nibbles 1,0,0,0; -1 -> 0xFFFF; 4096 -> 0x1000 (LS nibble first); homing | blue
    packet = proto.encode_command_packet([1, -1, 4096], proto.FLAG_HOMING | 0x04)
    assert packet == b"<BAAAPPPPAAABFA>"
    status = proto.decode_status_packet(b"<BAAAPPPPAAABQA>")   # flags 0x10: leg 0 homed
    assert status.counts == (1, -1, 4096)
    assert status.buttons == 0 and status.homed == (True, False, False)


def test_command_round_trip_random_values_and_all_flags(rng: np.random.Generator) -> None:
    values = rng.integers(-4096, 4097, size=(400, 3))
    values[:4] = [[-4096, 4096, 0], [-1, 1, 0], [4096, 4096, 4096], [-4096, -4096, -4096]]
    for row, flags in zip(values, itertools.cycle(range(16))):
        packet = proto.encode_command_packet(row, flags)
        assert len(packet) == 16 and proto.is_valid_packet(packet, proto.COMMAND_FLAGS_MASK)
        decoded = proto.decode_command_packet(packet)
        assert decoded.commands == tuple(int(v) for v in row)
        assert decoded.flags == flags and decoded.homing == bool(flags & 1)


@pytest.mark.parametrize("value, expected", [
    (4097, 4096), (-4097, -4096), (32767, 4096), (40000, 4096), (70000, 4096),
    (-70000, -4096), (2 ** 40, 4096), (-(2 ** 40), -4096), (12.4, 12), (-12.6, -13)])
def test_commands_are_clamped_never_wrapped(value: float, expected: int) -> None:
    decoded = proto.decode_command_packet(proto.encode_command_packet([value, 0, -value]))
    assert decoded.commands == (expected, 0, -expected)


def test_bad_commands_and_flags_raise() -> None:
    with pytest.raises(InvalidParameterError, match="finite"):
        proto.encode_command_packet([np.nan, 0, 0])
    with pytest.raises(InvalidParameterError, match="shape"):
        proto.encode_command_packet([1, 2])
    for flags in (16, -1, 0x10):
        with pytest.raises(InvalidParameterError, match="flags"):
            proto.encode_command_packet([0, 0, 0], flags)


def test_status_round_trip_all_buttons_and_homed_combos(rng: np.random.Generator) -> None:
    counts = rng.integers(-32768, 32768, size=(128, 3))
    combos = itertools.product(range(16), ALL_HOMED)
    for row, (buttons, homed) in zip(counts, combos):
        status = proto.decode_status_packet(proto.encode_status_packet(row, buttons, homed))
        assert status.counts == tuple(int(v) for v in row)
        assert status.buttons == buttons and status.homed == homed


@pytest.mark.parametrize("packet", [
    b"<AAAAAAAAAAAAAA", b"<AAAAAAAAAAAAAA)", b">AAAAAAAAAAAAAA<", b"<AAAA@AAAAAAAAA>",
    b"<AAAAAAAAAAAA\xc1A>", b"<AAAAAAAAAAAA@A>"])
def test_malformed_status_raises(packet: bytes) -> None:
    with pytest.raises(DeviceError, match="malformed status packet"):
        proto.decode_status_packet(packet)


@pytest.mark.parametrize("byte14", [0x41, 0x51, 0x00, 0xFF, 0x3C, 0x3E])
def test_unknown_byte_14_is_checked_for_framing_only(byte14: int) -> None:
    # libnifalcon's formatOutput checks only '<' and '>': byte 14 ("unknown") may hold anything
    packet = bytearray(proto.encode_status_packet([7, -8, 9], 3, (True, True, False)))
    packet[14] = byte14
    status = proto.decode_status_packet(bytes(packet))
    assert status.counts == (7, -8, 9) and status.buttons == 3
    assert status.homed == (True, True, False)


def test_stream_recovers_packets_whose_byte_14_looks_like_framing(
        rng: np.random.Generator) -> None:
    for _ in range(40):
        packets = []
        for p in _packets(rng, 30):
            p = bytearray(p)
            p[14] = int(rng.choice([0x3C, 0x3E, 0x00, 0x41, 0xFF]))
            packets.append(bytes(p))
        data = b"".join(_garbage(rng) + p for p in packets) + _garbage(rng)
        stream = proto.PacketStream()
        out = [p for chunk in _chunks(rng, data) for p in stream.feed(chunk)]
        assert out == packets


def test_unwrap_follows_counts_across_the_16_bit_wrap(rng: np.random.Generator) -> None:
    steps = rng.integers(-30000, 30001, size=(300, 3))
    truth = np.cumsum(steps, axis=0)                 # starts inside int16, then wanders off
    previous = None
    for true_counts in truth:
        wire = proto.decode_status_packet(proto.encode_status_packet(true_counts)).counts
        assert all(-32768 <= w < 32768 for w in wire)
        previous = proto.unwrap_counts(wire, previous)
        np.testing.assert_array_equal(previous, true_counts)
    assert np.abs(truth).max() > 65536               # the walk did cross several wraps


def test_strip_ftdi_status_from_every_usb_packet() -> None:
    data = bytes(range(150))
    stripped = proto.strip_ftdi_status(data)
    assert stripped == data[2:64] + data[66:128] + data[130:150]
    assert proto.strip_ftdi_status(b"\x31\x60") == b""


def _packets(rng: np.random.Generator, n: int) -> list[bytes]:
    return [proto.encode_status_packet(rng.integers(-32768, 32768, 3), int(rng.integers(16)),
                                       ALL_HOMED[int(rng.integers(8))]) for _ in range(n)]


def _garbage(rng: np.random.Generator) -> bytes:
    """Up to 15 random bytes, rich in '<' and '>' (fewer than 16, so never a packet)."""
    n = int(rng.integers(0, 16))
    pool = np.array([0x3C, 0x3E, 0x41, 0x45, 0x50, 0x00, 0xFF, 0xC0], dtype=np.uint8)
    mixed = np.where(rng.random(n) < 0.5, rng.choice(pool, n),
                     rng.integers(0, 256, n, dtype=np.uint8))
    return mixed.astype(np.uint8).tobytes()


def _chunks(rng: np.random.Generator, data: bytes) -> list[bytes]:
    cuts = np.sort(rng.choice(np.arange(1, len(data)), size=len(data) // 7, replace=False))
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)])]


def test_stream_recovers_every_packet_over_random_chunks_and_garbage(
        rng: np.random.Generator) -> None:
    for _ in range(40):
        packets = _packets(rng, 30)
        data = b"".join(_garbage(rng) + p for p in packets) + _garbage(rng)
        stream = proto.PacketStream()
        out = [p for chunk in _chunks(rng, data) for p in stream.feed(chunk)]
        assert out == packets
        assert stream.discarded + stream.pending + 16 * len(packets) == len(data)


def test_stream_drops_a_truncated_packet_and_resyncs(rng: np.random.Generator) -> None:
    a, b, c = _packets(rng, 3)
    stream = proto.PacketStream()
    assert stream.feed(a[:9]) == []                 # short read: wait for the rest
    assert stream.pending == 9
    assert stream.feed(b + c[:3]) == [b]            # a's tail was lost: a is dropped
    assert stream.feed(c[3:]) == [c]
    assert stream.discarded == 9


def test_stream_of_command_packets() -> None:
    stream = proto.PacketStream(proto.COMMAND_FLAGS_MASK)
    packet = proto.encode_command_packet([5, -6, 7], 0x0F)
    assert stream.feed(b"\x00>" + packet) == [packet]
    # a status-only flag value (homed bit) is not a valid command packet
    assert stream.feed(proto.encode_status_packet([0, 0, 0], 0, (True, False, False))) == []
