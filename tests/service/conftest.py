"""Fixtures for the service tests: real Zenoh sessions on loopback only (random free ports,
multicast scouting off), the real planner and a real-time SimDevice behind the Executor
(helpers in :mod:`service.testing`).

One service with a simulated device is shared by the service tests (starting one costs a
device, a session and threads, and its plan cache saves repeated plans); each test opens and
closes its own client session.
"""
from __future__ import annotations

from typing import Any, Iterator

import pytest

from service.client import FalconClient
from service.server import FalconService
from service.testing import client_for, running_service


@pytest.fixture(scope="session")
def sim_service(model: Any) -> Iterator[FalconService]:
    """A service instance ``sim0`` owning a real-time simulated device."""
    with running_service("sim0", "sim", model) as service:
        yield service


@pytest.fixture
def client(sim_service: FalconService) -> Iterator[FalconClient]:
    """A client session connected to ``sim_service``."""
    with client_for(sim_service) as c:
        yield c
