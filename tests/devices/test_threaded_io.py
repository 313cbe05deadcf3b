"""The threaded I/O design (writer and reader threads) against the emulated Falcon, with and
without real USB timing; and why it exists: blocking write-then-read cannot hold 1 kHz on a
bus with 1 ms frames and the FTDI latency timer."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from falcon_plan.devices.base import DeviceTimeoutError
from falcon_plan.devices.emulated import EmulatedFalconBackend, FaultPlan, UsbTiming, baud_rate
from falcon_plan.devices.protocol import BAUD_BOOT, BAUD_LOADER, BAUD_RUN
from falcon_plan.devices.usb_falcon import UsbFalcon

FAST = dict(realtime=False, check_timeout_s=0.05, echo_timeout_s=0.1, reply_timeout_s=0.01)


def test_ftdi_baud_divisors() -> None:
    assert baud_rate(BAUD_BOOT) == pytest.approx(9600.0)
    assert baud_rate(BAUD_LOADER) == pytest.approx(3e6 / 21)
    assert baud_rate(BAUD_RUN) == pytest.approx(1.5e6)


def _settle(dev: UsbFalcon, plant, ticks: int = 30):
    """Zero commands until the newest reading shows the plant's state."""
    for _ in range(ticks):
        reading = dev.exchange([0, 0, 0])
        if reading.counts.tolist() == plant.counts.tolist():
            return reading
    raise AssertionError(f"readings never caught up: {reading.counts} vs {plant.counts}")


@pytest.mark.parametrize("faults", [FaultPlan(), FaultPlan(max_read_bytes=5, garbage_every=3,
                                                           drop_every=7, byte14=0x3C, seed=2)],
                         ids=["clean", "faults"])
def test_threaded_stream_follows_the_plant(stub_plant, firmware: Path, faults: FaultPlan) -> None:
    backend = EmulatedFalconBackend(stub_plant, faults, homing_packets=3)
    # no watchdog thread and a silence bound of 1 s: this is the stream, and a loaded machine's
    # stall (the writer thread not run for 112 ms, seen in a full suite) would trip the 40 ms one
    with UsbFalcon(firmware, backend=backend, io="threaded", watchdog_s=None,
                   **{**FAST, "reply_timeout_s": 0.25}) as dev:
        dev.home()
        assert dev.homed and backend.falcon.last_flags & 0x01
        for _ in range(100):
            dev.exchange([128, -64, 0])
            time.sleep(2e-4)                  # ~ paced: the writer keeps up
        _settle(dev, stub_plant)
        moved = np.array(stub_plant.counts)
        assert moved[0] <= -2 * 60 and moved[1] >= 60 and moved[2] == 0
        assert dev.stats.written == backend.falcon.packets_received - 1   # all but the check
        assert dev.stats.statuses > 0
    np.testing.assert_array_equal(backend.falcon.held_commands, 0)      # the writer flushed 0


def test_threaded_io_reports_a_silent_device(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(silent_after=20), homing_packets=3)
    with UsbFalcon(firmware, backend=backend, io="threaded", watchdog_s=None, **FAST) as dev:
        dev.home()
        with pytest.raises(DeviceTimeoutError, match="no status packet for"):
            for _ in range(500):
                dev.exchange([0, 0, 0])


def test_blocking_io_cannot_hold_1khz_on_a_timed_bus(stub_plant, firmware: Path) -> None:
    # one round trip needs the OUT frame, the serial link both ways, the 1 ms latency timer
    # and an IN frame: at least two 1 ms frames (a lower bound, so a loaded machine only
    # makes it slower)
    backend = EmulatedFalconBackend(stub_plant, homing_packets=2, timing=UsbTiming())
    with UsbFalcon(firmware, backend=backend, io="blocking", **FAST) as dev:
        dev.home()
        t0 = time.perf_counter()
        for _ in range(40):
            dev.exchange([0, 0, 0])
        per_tick = (time.perf_counter() - t0) / 40
    assert per_tick >= 2e-3 * 0.95


@pytest.mark.slow
def test_threaded_io_keeps_pace_on_a_timed_bus(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, homing_packets=2, timing=UsbTiming())
    with UsbFalcon(firmware, backend=backend, io="threaded", **FAST) as dev:
        dev.home()
        before = backend.falcon.packets_received
        spans = []
        for _ in range(300):                  # unpaced: each tick waits for a new status
            t0 = time.perf_counter()
            reading = dev.exchange([64, 0, 0])
            spans.append(time.perf_counter() - t0)
        sent = backend.falcon.packets_received - before
    # about one status per 1 ms frame (not 2-3 frames per tick; the median, which a loaded
    # machine's stalls do not move), and the readings trail
    assert np.median(spans) < 2e-3, np.median(spans)
    assert sent >= 200 and reading.counts[0] > stub_plant.counts[0]


def _staged_exchanges(dev: UsbFalcon, stage, times: int = 5) -> list:
    """Exchanges made by a caller thread while this thread holds the driver's lock: ``stage()``
    runs, still under the lock, once the caller has handed over and waits (it cannot wake
    before the lock is let go). The emulated bus answers on its own after a frame or two and
    can now and then answer the caller first (on a loaded machine this thread wakes late):
    such a try is not staged and is made again, until ``times`` staged readings are had.
    Returns the (reading, what ``stage`` returned) pairs."""
    import math
    import threading

    io, staged = dev._io, []
    for _ in range(20 * times):
        result: list = []
        caller = threading.Thread(target=lambda: result.append(dev.exchange([0, 0, 0])))
        with io._cv:
            caller.start()
            assert io._cv.wait_for(lambda: math.isfinite(io._handed_over_s) or result, timeout=5.0)
            staged_now = None if result else stage(io)
        caller.join(timeout=5.0)
        assert result, "the exchange never returned"
        if staged_now is not None:
            staged.append((result[0], staged_now))
            if len(staged) == times:
                return staged
    raise AssertionError(f"only {len(staged)} of {times} exchanges could be staged")


def test_a_late_waking_exchange_takes_the_first_status_after_its_hand_over(stub_plant, firmware: Path) -> None:
    """When the caller of an exchange wakes late (a host stall) and two statuses arrived after
    its hand-over meanwhile, it gets the first of them, whose age the loop's delay model
    assumes, not the newest (a reading younger than assumed reads the device's motion in
    the meantime as a tracking error). The stall is made by holding the driver's lock across
    both arrivals, so that the exchange can only wake after the second."""
    from falcon_plan.devices.protocol import StatusPacket

    homed = (True, True, True)
    first, second = StatusPacket((111, 222, 333), 0, homed), StatusPacket((444, 555, 666), 0, homed)

    def two_arrive(io) -> float:
        io._arrived(first)
        first_s = io._status_t
        io._arrived(second)
        return first_s

    backend = EmulatedFalconBackend(stub_plant, homing_packets=2, timing=UsbTiming())
    with UsbFalcon(firmware, backend=backend, io="threaded", **{**FAST, "rate_hz": 500.0}) as dev:
        dev.home()
        for reading, first_s in _staged_exchanges(dev, two_arrive):
            assert reading.arrived_s <= first_s                # the first after the hand-over
            assert tuple(reading.counts) != (444, 555, 666)    # never the newer one


def test_threaded_exchange_takes_the_status_after_its_hand_over(stub_plant, firmware: Path) -> None:
    """An exchange that returns before its wait is up returns a status that arrived after its
    hand-over, never one that was already waiting (that one came late for the last exchange:
    taking it would keep every later reading a frame older than the loop's delay assumes).
    Staged deterministically: a status arrives while no exchange waits (it waits), then the
    caller hands over and a fresh one arrives while it still waits. Then, on the bus's own
    timing with random pauses between exchanges (which leave a status waiting now and then),
    every exchange that ends early takes a status from after its hand-over, until some have
    (a condition waited for, not a count out of a fixed number of tries)."""
    from falcon_plan.devices.protocol import StatusPacket
    from falcon_plan.devices.usb_falcon import STATUS_WAIT_PERIODS

    homed = (True, True, True)
    waiting, fresh = StatusPacket((111, 222, 333), 0, homed), StatusPacket((444, 555, 666), 0, homed)

    def wait_then_fresh(io) -> float:
        handed_over = io._handed_over_s
        io._arrived(fresh)
        return handed_over

    backend = EmulatedFalconBackend(stub_plant, homing_packets=2, timing=UsbTiming())
    rng = np.random.default_rng(5)
    with UsbFalcon(firmware, backend=backend, io="threaded", **{**FAST, "rate_hz": 500.0}) as dev:
        dev.home()
        io = dev._io
        for _ in range(5):
            with io._cv:
                io._arrived(waiting)                        # no exchange waits: it waits
            (reading, handed_over), = _staged_exchanges(dev, wait_then_fresh, times=1)
            assert tuple(reading.counts) != (111, 222, 333)  # never the waiting one
            assert reading.arrived_s >= handed_over, (reading.arrived_s, handed_over)
        wait_s = STATUS_WAIT_PERIODS / dev.rate_hz
        early, deadline = 0, time.monotonic() + 30.0
        while early < 20 and time.monotonic() < deadline:
            time.sleep(rng.uniform(0.0, 1.5e-3))
            called = time.monotonic()
            reading = dev.exchange([0, 0, 0])
            if time.monotonic() - called < 0.9 * wait_s:   # a status ended the wait
                early += 1
                assert reading.arrived_s >= called, (reading.arrived_s, called)
        assert early > 0                   # statuses come once a frame: waits do end early


def test_a_late_hand_over_takes_the_status_that_arrived_after_its_ticks_deadline(stub_plant, firmware: Path) -> None:
    """A loop that hands over after its tick's deadline (it fell behind) gets, at once, the status
    that arrived since that deadline: on the device's frame grid that is the tick's own reading.
    Waiting for the next frame's instead kept the loop behind for good. Staged under the
    driver's lock (the bus cannot answer meanwhile): a status arrives, then the exchange is
    handed over with a deadline before that arrival; and the same with a deadline after it,
    where the status answered an earlier tick and must not be taken at once."""
    from falcon_plan.devices.protocol import StatusPacket

    homed = (True, True, True)
    waiting = StatusPacket((111, 222, 333), 0, homed)

    class Deadlines:          # a loop's deadlines, as DeadlineTimer.current_deadline gives them
        due_s = 0.0

        def current_deadline(self) -> float:
            return self.due_s

    deadlines = Deadlines()
    backend = EmulatedFalconBackend(stub_plant, homing_packets=2, timing=UsbTiming())
    with UsbFalcon(firmware, backend=backend, io="threaded", **{**FAST, "rate_hz": 500.0}) as dev:
        dev.home()
        dev.follow_deadlines(deadlines)
        io = dev._io
        for _ in range(5):
            with io._cv:      # re-entrant: the exchange below takes it too and never waits
                io._arrived(waiting)
                deadlines.due_s = io._status_t - 1e-4          # the tick was due before it came
                called = time.monotonic()
                reading = dev.exchange([0, 0, 0])
            assert tuple(reading.counts) == (111, 222, 333)
            assert deadlines.due_s < reading.arrived_s <= called
        for _ in range(3):
            with io._cv:
                io._arrived(waiting)
                deadlines.due_s = io._status_t + 1e-4          # it came before the tick was due
                seq = io._seq
                called = time.monotonic()
                reading = dev.exchange([0, 0, 0])
            # it waited for the bus (statuses come every frame): a status after the hand-over,
            # or, had none come in the wait, the waiting one with nothing newer
            assert reading.arrived_s >= called or io._seq == seq, (reading.arrived_s, called)
        dev.follow_deadlines(None)
