"""Fixtures for the device tests: a deterministic stand-in plant and a firmware file."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


class StubPlant:
    """A stand-in for SimPlant with a known response: each step moves every leg's counts by
    ``-command // 64`` (positive commands drive counts down, as on the Falcon)."""

    def __init__(self, rate_hz: float = 1000.0, start_counts=(0, 0, 0)) -> None:
        self.rate_hz = rate_hz
        self.time_s = 0.0
        self.counts = np.asarray(start_counts, dtype=np.int64)
        self.sent: list[list[int]] = []

    def reset(self, position_m=None, velocity_m_s=(0, 0, 0)) -> None:
        self.time_s = 0.0
        self.counts = np.zeros(3, dtype=np.int64)

    def step(self, commands) -> np.ndarray:
        cmd = np.asarray(commands, dtype=np.int64)
        self.sent.append(cmd.tolist())
        self.time_s += 1.0 / self.rate_hz
        self.counts = self.counts - cmd // 64
        return self.counts.copy()


@pytest.fixture
def stub_plant() -> StubPlant:
    return StubPlant()


@pytest.fixture
def firmware(tmp_path: Path) -> Path:
    """A stand-in firmware image (the emulator accepts any non-empty image), 1000 bytes so
    the last 62-byte chunk is partial."""
    path = tmp_path / "test_firmware.bin"
    path.write_bytes(np.random.default_rng(7).integers(0, 256, 1000, dtype=np.uint8).tobytes())
    return path


@pytest.fixture
def stub_plant_class() -> type[StubPlant]:
    """The StubPlant class (for plants with other start counts)."""
    return StubPlant
