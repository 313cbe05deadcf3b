"""Every safety path of the executor, each with an injected failure: not homed, a stalled
loop (watchdog), leaving the workspace, device errors, a bad packet stream, Ctrl-C."""
from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest
import usb.core

from falcon_plan.devices.base import DeviceDisconnectedError
from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.errors import DeviceError, InvalidParameterError, SafetyStop
from falcon_plan.execution.executor import Executor
from falcon_plan.execution.safety import (SafetyConfig, Watchdog, WorkspaceGuard,
                                          require_finite_commands, zero_force_best_effort)
from falcon_plan.falconlog import read_log
from falcon_plan.model.effects import Effects

from .conftest import FaultyDevice


def _assert_stopped_cleanly(dev: FaultyDevice, report, path) -> None:
    """Zero force was the last thing sent and the log holds every sent command, readable."""
    assert dev.zero_calls, "zero force was never attempted"
    assert dev.last_sent == [0, 0, 0]
    log = read_log(path)
    assert len(log) == report.samples
    np.testing.assert_array_equal(log.tc, np.array(dev.sent[1:1 + report.samples]))


def test_refuses_to_run_before_homing(model, make_move):
    with SimDevice(model=model, rate_hz=800.0) as dev:
        with pytest.raises(SafetyStop, match="not homed"):
            Executor(dev, model).run(make_move())
        assert dev.plant.time_s == 0.0  # nothing was sent at all


class _TestClock:
    """A clock the test moves by hand [s]; counts the watchdog thread's looks at it."""

    def __init__(self) -> None:
        self.now = 0.0
        self.polls = 0

    def __call__(self) -> float:
        if threading.current_thread().name == "falcon-watchdog":
            self.polls += 1
        return self.now

    def advance(self, dt_s: float, dog: Watchdog) -> None:
        """Move the clock by ``dt_s`` [s], then wait until ``dog`` has looked at it twice or
        has tripped."""
        polls = self.polls
        self.now += dt_s
        deadline = time.monotonic() + 10.0
        while self.polls < polls + 2 and not dog.tripped and time.monotonic() < deadline:
            time.sleep(0.001)
        assert self.polls >= polls + 2 or dog.tripped, "the watchdog thread stopped looking"


def test_watchdog_trips_once_when_not_kicked():
    # the watchdog's clock is the test's, so a loaded machine can neither fake nor hide a stall
    clock = _TestClock()
    trips: list[float] = []
    dog = Watchdog(lambda: trips.append(clock.now), timeout_s=0.02, clock=clock)
    with dog:
        for _ in range(10):  # kicked every 5 ms of its clock: quiet
            clock.advance(0.005, dog)
            dog.kick()
        clock.advance(0.015, dog)            # 15 ms without a kick: within the bound
        assert not dog.tripped
        clock.advance(0.010, dog)            # 25 ms: trips
        assert dog.tripped
        deadline = time.monotonic() + 10.0   # the flag comes first, the trip action right after it
        while not trips and time.monotonic() < deadline:
            time.sleep(0.001)
        clock.now += 1.0                     # and only once
    assert trips == [pytest.approx(0.075)] and "stalled for 25.0 ms" in dog.reason


def test_stall_inside_the_device_call_zeroes_force_from_the_watchdog(model, sim_device, make_move, tmp_path):
    dev = FaultyDevice(sim_device(), at=10, fault="stall", stall_s=0.5)
    path = tmp_path / "stall.csv"
    report = Executor(dev, model, log_path=path, pace=True, preroll_s=1.0).run(make_move())
    assert dev.fault_time is not None  # the run lasted until the stall
    assert report.status == "safety_stop" and "watchdog" in report.reason
    by_dog = [t for t, thread in dev.zero_calls if thread == "falcon-watchdog"]
    assert by_dog, dev.zero_calls
    # caught while the device call was still stuck (the bound is 50 ms, polled every 10 ms; the
    # stall 0.5 s leaves a loaded machine room)
    assert by_dog[0] - dev.fault_time < 0.5
    _assert_stopped_cleanly(dev, report, path)


def test_a_stall_shorter_than_the_run_stops_it_for_good(model, sim_device, make_move, tmp_path):
    # The stall (0.3 s from about 0.05 s) ends long before the run would (1 s of pre-roll,
    # then the move): after the watchdog zeroed the force the loop must not go on applying
    # force. (A loaded machine may trip the watchdog earlier; the same must hold then.)
    dev = FaultyDevice(sim_device(), at=40, fault="stall", stall_s=0.3)
    path = tmp_path / "short-stall.csv"
    report = Executor(dev, model, log_path=path, pace=True, preroll_s=1.0).run(make_move())
    assert report.status == "safety_stop" and "watchdog" in report.reason
    assert report.samples <= 41 < report.planned_samples - 800
    by_dog = [t for t, thread in dev.zero_calls if thread == "falcon-watchdog"]
    assert by_dog, "the watchdog never zeroed the force"
    # at most the exchange that was already under way when the watchdog fired
    after = [t for t in dev.exchange_times if t > by_dog[0]]
    assert len(after) <= 1, f"{len(after)} exchanges went out after the watchdog stop"
    _assert_stopped_cleanly(dev, report, path)


def test_stall_outside_the_device_call_is_caught_too(model, sim_device, make_move):
    dev = FaultyDevice(sim_device(), at=-1, fault="none")
    stalled = threading.Event()

    def progress(done: int, total: int) -> None:
        if not stalled.is_set():  # the first call (a loaded machine may skip many slots)
            stalled.set()
            time.sleep(0.2)

    # a run much longer than the stall, so that a loaded machine's skipped slots do not end
    # it before the stall comes (its own stalls may trip the watchdog first: the same holds)
    report = Executor(dev, model, pace=True, preroll_s=1.0, progress_period_s=0.01).run(
        make_move(), progress=progress)
    assert stalled.is_set() and report.status == "safety_stop" and "watchdog" in report.reason
    assert any(thread == "falcon-watchdog" for _, thread in dev.zero_calls)
    assert dev.last_sent == [0, 0, 0]


def test_workspace_guard_stops_a_plant_dragged_out_by_a_payload(model, sim_device, tmp_path):
    # 0.5 kg that the plan does not know about sags the device; a plan held 40 counts inside
    # the top leg's upper limit (the guard's slack tightened to none) leaves the workspace
    # before the sag reaches the tracking guard's bound
    from falcon_plan.model.kinematics import counts_to_position
    from falcon_plan.planning.quintic import quintic_trajectory

    near_edge = counts_to_position(np.array([1044.0, 0.0, 0.0]))
    margins = model.workspace_margins(near_edge)
    assert 0.0 < margins.min() == margins[3] < 45.0 / model.params.counts_per_rad   # theta1_high, leg 0
    dev = FaultyDevice(sim_device(effects=Effects(payload_kg=0.5), start_position_m=near_edge), at=-1, fault="none")
    path = tmp_path / "guard.csv"
    report = Executor(dev, model, log_path=path, preroll_s=0.2, settle_s=1.0,
                      safety=SafetyConfig(workspace_slack_rad=0.0)).run(
        quintic_trajectory(near_edge, near_edge + [0.0, 0.0, 0.001], model, rate_hz=800.0))
    assert report.status == "safety_stop" and "workspace guard" in report.reason, report.reason
    assert "left the workspace" in report.reason and report.samples < report.planned_samples
    _assert_stopped_cleanly(dev, report, path)
    # the stop came from the measured state: the last logged counts are still inside
    guard = WorkspaceGuard(model.params, model.limits, 0.0)
    guard.check(read_log(path).enc[-1])


def test_a_controller_that_lost_the_device_is_stopped_by_the_tracking_guard(model, sim_device, make_move, tmp_path):
    """A loop delay eight periods longer than the controller was designed for (a slow link): the
    run rings at the command limit until a leg is 250 counts off its reference; the guard ends
    it there with zero force, long before the plan's end. Without the guard such a run rang on
    to the end and reported "completed" (a design that took friction for damping, on the
    emulated Falcon: 116 counts RMS, 326 peak)."""
    dev = FaultyDevice(sim_device(1000.0, effects=Effects(extra_delay_samples=8)), at=-1, fault="none")
    path = tmp_path / "ringing.csv"
    report = Executor(dev, model, log_path=path, preroll_s=0.3, settle_s=0.2).run(
        make_move((0.03, 0.02, 0.015), rate_hz=1000.0))
    assert report.status == "safety_stop" and "tracking error of" in report.reason, report.reason
    assert "(allowed 250)" in report.reason and report.samples < 0.8 * report.planned_samples
    _assert_stopped_cleanly(dev, report, path)
    log = read_log(path)                      # the loop stopped at the first reading past the bound
    assert np.abs(log.enc - log.ref).max() <= SafetyConfig().max_tracking_error_counts
    assert np.abs(np.abs(log.tc[-40:]).max(axis=1)).min() > 1000    # it was ringing: big commands to the end


@pytest.mark.parametrize("exc, name", [
    (DeviceDisconnectedError("the Falcon went away (unplugged)"), "DeviceDisconnectedError"),
    (usb.core.USBError("Pipe error", errno=32), "USBError"),
])
def test_device_error_mid_run_is_reported_with_zero_force_and_a_closed_log(
        model, sim_device, make_move, tmp_path, exc, name):
    dev = FaultyDevice(sim_device(), at=120, fault="raise", exc=exc)
    path = tmp_path / "deverr.csv"
    report = Executor(dev, model, log_path=path, preroll_s=0.05).run(make_move())
    assert report.status == "device_error" and name in report.reason
    assert isinstance(report.error, DeviceError)
    assert report.samples == 119  # commands 0..118 went out; the 120th exchange failed
    _assert_stopped_cleanly(dev, report, path)


def test_keyboard_interrupt_is_reraised_after_zero_force(model, sim_device, make_move, tmp_path):
    dev = FaultyDevice(sim_device(), at=60, fault="raise", exc=KeyboardInterrupt())
    path = tmp_path / "ctrlc.csv"
    with pytest.raises(KeyboardInterrupt):
        Executor(dev, model, log_path=path, preroll_s=0.05).run(make_move())
    assert dev.zero_calls and dev.last_sent == [0, 0, 0]
    assert len(read_log(path)) == 59


def test_failing_zero_force_does_not_mask_the_original_error(model, sim_device, make_move):
    dev = FaultyDevice(sim_device(), at=30, fault="raise", exc=DeviceDisconnectedError("gone"))

    def broken_zero() -> None:
        raise DeviceDisconnectedError("cannot send zero: gone")

    dev.zero_force = broken_zero  # type: ignore[method-assign]
    report = Executor(dev, model, preroll_s=0.05).run(make_move())
    assert report.status == "device_error" and "gone" in report.reason
    assert "cannot send zero" not in report.reason
    assert zero_force_best_effort(dev) is not None  # never raises


def test_a_run_whose_final_zero_fails_is_a_device_error_not_completed(model, sim_device, make_move, tmp_path):
    dev = FaultyDevice(sim_device(), at=-1, fault="none")

    def undeliverable_zero() -> None:
        raise DeviceError("zero force could not be delivered (test)")

    dev.zero_force = undeliverable_zero  # type: ignore[method-assign]
    path = tmp_path / "final-zero.csv"
    report = Executor(dev, model, log_path=path, preroll_s=0.05).run(make_move())
    assert report.samples == report.planned_samples == len(read_log(path))
    assert report.status == "device_error" and "zero force at the end failed" in report.reason
    assert isinstance(report.error, DeviceError)


def test_bad_packet_stream_jump_is_a_safety_stop(model, sim_device, make_move):
    dev = FaultyDevice(sim_device(), at=80, fault="jump", jump=400)
    report = Executor(dev, model, preroll_s=0.05).run(make_move())
    assert report.status == "safety_stop" and "implausible encoder step" in report.reason
    assert dev.last_sent == [0, 0, 0]


def test_commands_are_clamped_to_the_configured_limit(model, sim_device, make_move, tmp_path):
    path = tmp_path / "clamp.csv"
    report = Executor(sim_device(), model, log_path=path, preroll_s=0.05,
                      safety=SafetyConfig(command_limit=1200)).run(make_move())
    log = read_log(path)
    assert np.abs(log.tc).max() == 1200 and report.saturated_samples > 0


def test_safety_config_and_command_checks():
    for bad in (dict(command_limit=5000), dict(command_limit=0), dict(watchdog_timeout_s=0.2),
                dict(workspace_slack_rad=-0.1), dict(max_start_error_m=0.0), dict(max_tracking_error_counts=0.0),
                dict(max_tracking_error_counts=300.0)):
        with pytest.raises(InvalidParameterError):
            SafetyConfig(**bad)
    assert SafetyConfig().to_dict()["workspace_slack_deg"] == pytest.approx(2.0)
    with pytest.raises(SafetyStop, match="finite"):
        require_finite_commands([1.0, math.nan, 0.0])


def test_workspace_guard_agrees_with_check_workspace(model, rng):
    from falcon_plan.model.workspace import check_workspace

    slack = math.radians(2.0)
    guard = WorkspaceGuard(model.params, model.limits, slack)
    wide = model.limits.scaled(-slack)
    points = rng.uniform((-0.1, -0.1, 0.03), (0.1, 0.1, 0.22), size=(400, 3))
    inside = check_workspace(points, model.params, wide).inside
    assert 50 < inside.sum() < 350  # both kinds are tested
    for p, ok in zip(points, inside):
        assert (guard.violation(p) == "") == bool(ok), (p, guard.violation(p))
