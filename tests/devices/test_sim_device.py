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
        self.sent.append([int(c) for c in commands])
        self.time_s += 1.0 / self.rate_hz
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
