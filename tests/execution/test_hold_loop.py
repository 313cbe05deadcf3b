"""The hold before a run applies force as every loop does: the executor's per-tick guards on
each reading and the loop's watchdog on each command (issue 23: one set of guards for all force
on a device). Each test waits for the hold's thread to end, never for a fixed time."""
from __future__ import annotations

import time

import numpy as np
import pytest

from falcon_plan.errors import SafetyStop
from falcon_plan.execution.executor import Executor
from falcon_plan.execution.holding import HOLD_WATCHDOG_S, HoldLoop
from falcon_plan.execution.safety import MAX_LEG_SPEED_RAD_S

from .conftest import FaultyDevice

RATE = 1000.0


def _ended(hold: HoldLoop, within_s: float = 10.0) -> bool:
    """Whether the hold's thread has ended, waiting at most ``within_s`` [s]."""
    deadline = time.monotonic() + within_s
    while hold._running() and time.monotonic() < deadline:
        time.sleep(0.005)
    return not hold._running()


def _homed(sim_device, **fault) -> FaultyDevice:
    device = sim_device(RATE)
    device.home()
    return FaultyDevice(device, realtime=True, **fault)


def test_a_reading_that_jumps_ends_the_hold_with_zero_force(model, sim_device) -> None:
    jump = int(2 * MAX_LEG_SPEED_RAD_S * model.params.counts_per_rad / RATE)
    dev = _homed(sim_device, at=40, fault="jump", jump=jump)
    hold = HoldLoop(Executor(dev, model, pace=True))
    with hold:
        assert _ended(hold)
        with pytest.raises(SafetyStop, match="implausible encoder step"):
            hold.release()
    assert dev.exchanges == 41                 # the jump was read at exchange 40: no command sent from it
    assert dev.zero_calls and dev.last_sent == [0, 0, 0]


def test_a_hold_stuck_in_the_device_has_its_force_zeroed_by_the_loops_watchdog(model, sim_device) -> None:
    """The hold's thread stuck 1 s inside an exchange (past its 0.5 s bound): the loop's
    watchdog zeroes the force while it is stuck, and the hold ends with the watchdog's stop."""
    dev = _homed(sim_device, at=40, fault="stall", stall_s=1.0)
    hold = HoldLoop(Executor(dev, model, pace=True))
    with hold:
        assert _ended(hold)
        with pytest.raises(SafetyStop, match="watchdog: the control loop stalled"):
            hold.release()
    assert dev.fault_time is not None
    by_watchdog = [t for t, thread in dev.zero_calls if thread == "falcon-watchdog"]
    assert by_watchdog and dev.fault_time + HOLD_WATCHDOG_S - 0.01 < by_watchdog[0] < dev.fault_time + 1.0
    assert by_watchdog[0] - dev.fault_time <= 1.2 * HOLD_WATCHDOG_S + 0.05
    assert dev.exchanges == 41 and dev.last_sent == [0, 0, 0]   # nothing sent after the stall


def test_a_hold_starting_outside_the_workspace_is_refused(model, sim_device) -> None:
    """The hold's first reading is checked as a run's is: a device reading outside the workspace
    gets no force."""
    dev = _homed(sim_device, at=0, fault="jump", jump=-4000)     # 68 mm below the home pose
    hold = HoldLoop(Executor(dev, model, pace=True))
    try:
        with pytest.raises(SafetyStop, match="workspace guard"):
            hold.start()
    finally:
        hold.__exit__(None, None, None)          # (stops a hold that did start)
    assert dev.sent == [[0, 0, 0]]             # the first reading only, at zero force
    assert np.all(np.asarray(dev.last_sent) == 0)


def test_a_hold_that_loses_the_device_ends_with_zero_force(model, sim_device) -> None:
    """A loop delay eight periods longer than the hold's law was designed for: the hold rings
    until a leg is past the tracking bound, then the per-tick guard ends it with zero force and
    the run that would take over learns why (a hold that rang on at the command limit for three
    seconds, refusing the run after it, was the failure this guards against)."""
    from falcon_plan.model.effects import Effects

    dev = FaultyDevice(sim_device(RATE, effects=Effects(extra_delay_samples=8)), at=-1, fault="none", realtime=True)
    hold = HoldLoop(Executor(dev, model, pace=True))
    with hold:
        assert _ended(hold)
        with pytest.raises(SafetyStop, match=r"tracking error of \d+ counts on leg \d \(allowed 250\)"):
            hold.release()
    assert dev.zero_calls and dev.last_sent == [0, 0, 0]
    # it rang: the last commands before the stop were large and of both signs
    last = np.asarray(dev.sent[-60:])
    assert np.abs(last).max() > 2000 and (last > 0).any() and (last < 0).any()


def test_the_preparation_is_rehearsed_before_any_force_and_skipped_where_it_cannot_be(model, sim_device,
                                                                                      monkeypatch) -> None:
    """``rehearse_after_homing`` prepares, before homing, the approach from the home pose and
    the hold at the start (loading what the real preparation, beside the hold, would load first:
    the batched kernels of more than a few points), and sends nothing to the device; a start
    the run will refuse (outside the workspace) skips the rehearsal instead of failing it."""
    from falcon_plan.approach import rehearse_after_homing
    from falcon_plan.model import dynamics

    monkeypatch.setattr(dynamics, "_batch_cache", {})      # nothing loaded in this process yet
    dev = FaultyDevice(sim_device(RATE), at=-1, fault="none", realtime=True)
    executor = Executor(dev, model, pace=True)
    start = np.array([0.0, 0.0, 0.12])
    rehearse_after_homing(executor, start, model)
    assert dev.sent == []
    assert any(key[0] == id(model.functions) and key[2] == dynamics.BATCH_CHUNK and batch is not None
               for key, batch in dynamics._batch_cache.items())
    rehearse_after_homing(executor, np.array([0.0, 0.0, 1.0]), model)     # a metre away: skipped
    assert dev.sent == []
