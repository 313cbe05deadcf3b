"""The paced loop a caller's own commands go through (the doctor's) applies the executor's
per-tick guards: an encoder step no leg can make stops it, as it stops a run; a device
failure is a DeviceError; leaving it gives the device zero force."""
from __future__ import annotations

import time

import numpy as np
import pytest

from falcon_plan.errors import DeviceError, SafetyStop
from falcon_plan.execution.paced import PacedLoop
from falcon_plan.execution.safety import MAX_LEG_SPEED_RAD_S

from .conftest import FaultyDevice


def _hold(loop: PacedLoop, ticks: int, commands: np.ndarray) -> None:
    """``ticks`` paced ticks sending ``commands`` (3,) [command units]."""
    for _ in range(ticks):
        slot = loop.wait(loop.slot)
        loop.send(commands, slot)
        loop.slot = slot + 1


def test_a_reading_that_jumps_stops_the_loop_and_leaves_zero_force(model, sim_device) -> None:
    rate = 1000.0
    jump = int(2 * MAX_LEG_SPEED_RAD_S * model.params.counts_per_rad / rate)
    dev = FaultyDevice(sim_device(rate), at=20, fault="jump", jump=jump)
    with pytest.raises(SafetyStop, match="implausible encoder step"):
        with PacedLoop(dev, model) as loop:
            _hold(loop, 40, np.zeros(3))
    assert dev.exchanges == 21                      # the initial read and 20 ticks; the 21st stopped it
    assert dev.zero_calls and dev.last_sent == [0, 0, 0]


def test_a_gravity_hold_passes_every_guard(model, sim_device) -> None:
    """200 ticks of the model's gravity compensation at the start: every reading passes the
    guards (each one new, the device's own), and the device is at zero force afterwards."""
    dev = FaultyDevice(sim_device(1000.0), at=10**9, fault="jump")
    with PacedLoop(dev, model) as loop:
        start = loop.guard.workspace.position(loop.counts)
        _hold(loop, 200, np.rint(model.holding_commands(start)))
        assert loop.guard.prev_slots >= 1 and loop.guard.prev_t_s > 0.19   # the 200th reading, 0.2 s in
    assert dev.exchanges == 201 and dev.sent[-1] == [int(c) for c in np.rint(model.holding_commands(start))]
    assert dev.last_sent == [0, 0, 0]


def test_a_failing_exchange_is_a_device_error(model, sim_device) -> None:
    dev = FaultyDevice(sim_device(1000.0), at=5, fault="raise", exc=OSError("unplugged"))
    with pytest.raises(DeviceError, match="device I/O failed: OSError: unplugged"):
        with PacedLoop(dev, model) as loop:
            _hold(loop, 20, np.zeros(3))
    assert dev.zero_calls


def test_the_device_follows_the_loops_deadlines_only_while_it_runs(model, sim_device) -> None:
    """A paced loop tells the device its deadlines once it has started and takes them back on
    leaving; a loop that fails to start (its first reading fails) never leaves its deadlines
    with the device (a later exchange outside any loop would be timed against them)."""
    told: list = []
    dev = FaultyDevice(sim_device(1000.0), at=10**9, fault="jump")
    dev.follow_deadlines = told.append
    with PacedLoop(dev, model) as loop:
        _hold(loop, 5, np.zeros(3))
        assert told == [loop.timer]
    assert told == [loop.timer, None]

    told.clear()
    failing = FaultyDevice(sim_device(1000.0), at=0, fault="raise", exc=OSError("unplugged"))
    failing.follow_deadlines = told.append
    with pytest.raises(DeviceError, match="unplugged"):
        with PacedLoop(failing, model):
            pass
    assert not told or told[-1] is None


def test_a_caller_that_stops_sending_has_its_force_zeroed_by_the_watchdog(model, sim_device) -> None:
    """A caller that holds force and then stops sending (a diagnostic stuck in its own work):
    the loop's watchdog zeroes the force once the bound has passed, and the next send is a
    SafetyStop naming the stall, as in an executor's run."""
    dev = FaultyDevice(sim_device(1000.0), at=10**9, fault="jump")
    with PacedLoop(dev, model) as loop:
        start = loop.guard.workspace.position(loop.counts)
        holding = np.rint(model.holding_commands(start))
        _hold(loop, 20, holding)
        assert dev.last_sent == [int(c) for c in holding] and any(holding)
        deadline = time.monotonic() + 5.0
        while not dev.zero_calls and time.monotonic() < deadline:
            time.sleep(0.005)
        assert [thread for _, thread in dev.zero_calls] == ["falcon-watchdog"]
        assert dev.last_sent == [0, 0, 0] and loop.exchange.watchdog.tripped
        with pytest.raises(SafetyStop, match="watchdog: the control loop stalled"):
            loop.send(holding, loop.wait(loop.slot))
    assert dev.exchanges == 21                      # nothing sent after the trip
