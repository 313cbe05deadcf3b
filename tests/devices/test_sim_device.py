"""SimDevice and the shared BaseDevice rules (clamping, homing safety, zero force, pacing)."""
from __future__ import annotations

import time

import numpy as np
import pytest

from falcon_plan.devices.base import (COMMAND_LIMIT, LED_GREEN, Device, DeviceReading,
                                      clamp_commands)
from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.errors import DeviceError, InvalidParameterError, SafetyStop, WorkspaceError


class RecordingPlant:  # records what was sent; counts = command // 10
    """A stand-in plant: counts follow the command (so tests see what was sent)."""

    def __init__(self, rate_hz: float = 1000.0) -> None:
        self.rate_hz = rate_hz
        self.time_s = 0.0
        self.counts = np.zeros(3, dtype=np.int64)
        self.sent: list[list[int]] = []

    def reset(self, position_m=None, velocity_m_s=(0, 0, 0)) -> None:
        self.time_s = 0.0

    def step(self, commands) -> np.ndarray:
        """One period; ``commands`` None (a slot the loop skipped): nothing new, counts held."""
        self.sent.append(None if commands is None else [int(c) for c in commands])
        self.time_s += 1.0 / self.rate_hz
        if commands is not None:
            self.counts = np.asarray(commands, dtype=np.int64) // 10
        return self.counts.copy()


def test_clamp_commands_rounds_and_clamps() -> None:
    out = clamp_commands([1e9, -1e9, 2.6])
    assert out.tolist() == [COMMAND_LIMIT, -COMMAND_LIMIT, 3]
    assert out.dtype == np.int64
    for bad in ([1, 2], [np.nan, 0, 0], "abc", [[1, 2, 3]]):
        with pytest.raises(InvalidParameterError):
            clamp_commands(bad)


def test_sim_device_contract_and_safety() -> None:
    plant = RecordingPlant()
    dev = SimDevice(plant)
    assert isinstance(dev, Device)
    assert dev.rate_hz == 1000.0
    with pytest.raises(DeviceError, match="not open"):
        dev.exchange([0, 0, 0])
    with dev:
        reading = dev.exchange([0, 0, 0])
        assert isinstance(reading, DeviceReading) and reading.homed == (False,) * 3
        with pytest.raises(SafetyStop, match="home"):
            dev.exchange([100, 0, 0])
        assert plant.sent[-1] == [0, 0, 0]          # zero force sent instead
        dev.home()
        assert dev.homed
        reading = dev.exchange([100_000, -20, 5], leds=LED_GREEN)
        assert plant.sent[-1] == [COMMAND_LIMIT, -20, 5]
        assert reading.counts.tolist() == [409, -2, 0] and reading.all_homed
        assert reading.t_s == pytest.approx(plant.time_s)
        with pytest.raises(InvalidParameterError, match="LED"):
            dev.exchange([1, 1, 1], leds=0x01)       # the homing bit is not an LED
        assert plant.sent[-1] == [0, 0, 0]
        dev.exchange([50, 50, 50])
    assert plant.sent[-1] == [0, 0, 0]               # close() left zero force
    assert not dev.is_open
    dev.close()                                      # idempotent


def test_close_on_exception_leaves_zero_force() -> None:
    plant = RecordingPlant()
    with pytest.raises(RuntimeError):
        with SimDevice(plant) as dev:
            dev.home()
            dev.exchange([300, 300, 300])
            raise RuntimeError("caller failed")
    assert plant.sent[-1] == [0, 0, 0]


def test_realtime_paces_to_rate() -> None:
    plant = RecordingPlant(rate_hz=500.0)
    with SimDevice(plant, realtime=True) as dev:
        t0 = time.monotonic()
        for _ in range(25):
            dev.exchange([0, 0, 0])
        elapsed = time.monotonic() - t0
    assert elapsed >= 24 / 500.0 * 0.95             # 24 periods between 25 ticks
    assert elapsed < 25 / 500.0 * 10                # and not grossly slower (loose: a loaded machine)


def test_a_paced_device_lives_the_slots_its_loop_skips(model) -> None:
    """Told a loop's deadlines, each exchange steps the plant through the slots since the last
    one, the skipped ones under the command in force (the firmware holds it), at least one
    period an exchange; untold, one period an exchange. Checked against a twin plant stepped
    by hand (the clock is a fake one set by the test: no waiting on time)."""
    from falcon_plan.sim.plant import SimPlant
    from falcon_plan.timing import DeadlineTimer

    clock = [0.0]
    timer = DeadlineTimer(1000.0, spin_s=0.0, clock=lambda: clock[0], sleep=lambda s: clock.__setitem__(0, clock[0] + s))
    timer.start(0.0)
    twin = SimPlant(model, rate_hz=1000.0)
    commands = [[300, -200, 100], [500, 400, -300], [-600, 200, 250], [100, 100, 100]]
    with SimDevice(model=model, rate_hz=1000.0) as dev:
        dev.home()
        twin.reset()
        assert dev.device_clock == "slots"
        dev.follow_deadlines(timer)
        expected = []
        for wanted, cmd in zip([0, 1, 6, 7], commands):      # the host misses slots 2..5
            clock[0] = max(clock[0], wanted * 1e-3 + 1e-4)
            slot = timer.wait(1 if wanted == 6 else wanted)
            assert slot == wanted
            reading = dev.exchange(cmd)
            if wanted == 6:
                for _ in range(4):
                    twin.step(None)
            expected.append(twin.step(cmd))
            np.testing.assert_array_equal(reading.counts, expected[-1])
        assert reading.t_s == pytest.approx(8e-3) and dev.plant.time_s == twin.time_s
        np.testing.assert_allclose(dev.plant.position_m, twin.position_m, rtol=0, atol=1e-12)
        dev.exchange(commands[0])                   # a second exchange in slot 7: one period more
        dev.follow_deadlines(None)
        clock[0] += 0.05                            # no loop's deadlines: one period an exchange
        dev.exchange(commands[1])
        twin.step(commands[0])
        twin.step(commands[1])
        assert dev.plant.time_s == pytest.approx(10e-3) and dev.plant.time_s == twin.time_s
        np.testing.assert_allclose(dev.plant.position_m, twin.position_m, rtol=0, atol=1e-12)


def test_sim_device_with_real_plant(model) -> None:
    pytest.importorskip("falcon_plan.sim.plant")
    with SimDevice(model=model, rate_hz=800.0) as dev:
        assert dev.plant.rate_hz == 800.0
        first = dev.exchange([0, 0, 0])
        dev.home()
        for _ in range(40):
            reading = dev.exchange([-800, -800, -800])
        assert reading.t_s == pytest.approx(41 / 800.0)
        # positive Tc drives theta1 down (smaller counts): negative drives counts up
        assert np.all(reading.counts > first.counts + 50)
    for _ in range(4):                              # let the plant's command delay pass
        dev.plant.step(None)
    np.testing.assert_array_equal(dev.plant.acting_commands, 0)   # close() sent zero


class FallingPlant(RecordingPlant):
    """Leaves the workspace (raises like SimPlant) after a few steps."""

    def step(self, commands) -> np.ndarray:
        if len(self.sent) >= 5:
            raise WorkspaceError("the simulated device left the reachable workspace")
        return super().step(commands)


def test_plant_leaving_the_workspace_is_a_safety_stop() -> None:
    with SimDevice(FallingPlant()) as dev:
        dev.home()
        with pytest.raises(SafetyStop, match="left the reachable workspace"):
            for _ in range(10):
                dev.exchange([10, 10, 10])
        with pytest.raises(DeviceError, match="stopped.*open it again"):
            dev.exchange([0, 0, 0])
    assert not dev.is_open                           # close() did not raise
