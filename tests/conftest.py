"""Shared fixtures. Tests mirror the package tree; all servers and sockets use loopback only."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import numpy as np
import pytest

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.params import ACRA2009


@pytest.fixture(scope="session")
def model() -> FalconModel:
    """The nominal model (acra2009), built once per test session."""
    return FalconModel(ACRA2009)


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded random generator (deterministic tests)."""
    return np.random.default_rng(12345)
