"""Fixtures for the executor tests: quintic reference moves, simulated devices and a device
wrapper that injects failures at a chosen tick."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.execution.safety import follow_deadlines
from falcon_plan.planning.quintic import quintic_trajectory
from falcon_plan.model.kinematics import counts_to_position
from falcon_plan.trajectory import Trajectory


@pytest.fixture(scope="session")
def home_m() -> np.ndarray:
    """The end-effector point at counts (0, 0, 0) [m] (where a reset plant starts)."""
    return counts_to_position(np.zeros(3))


@pytest.fixture(scope="session")
def make_move(model: Any, home_m: np.ndarray) -> Callable[..., Trajectory]:
    """``make_move(delta_m, rate_hz=800)``: the fastest quintic move from home by ``delta_m``
    with |feed-forward| <= 2500 (cached)."""
    cache: dict[tuple, Trajectory] = {}

    def make(delta_m: Any = (0.03, -0.02, 0.01), rate_hz: float = 800.0, **kw: Any) -> Trajectory:
        key = (tuple(delta_m), rate_hz, tuple(sorted(kw.items())))
        if key not in cache:
            cache[key] = quintic_trajectory(home_m, home_m + np.asarray(delta_m), model,
                                            rate_hz=rate_hz, **kw)
        return cache[key]

    return make


@pytest.fixture
def sim_device(model: Any) -> Callable[..., SimDevice]:
    """``sim_device(rate_hz=800, effects=None)``: an open, homed SimDevice (closed after)."""
    opened: list[SimDevice] = []

    def make(rate_hz: float = 800.0, effects: Any = None, **kw: Any) -> SimDevice:
        dev = SimDevice(model=model, rate_hz=rate_hz, effects=effects, **kw)
        dev.open()
        dev.home()
        opened.append(dev)
        return dev

    yield make
    for dev in opened:
        dev.close()


class FaultyDevice:
    """Wraps a device; at exchange number ``at`` (0 = the executor's initial read) it injects
    a fault. Records every command sent and every zero_force call (time, thread).

    fault: "raise" (raise ``exc``), "stall" (sleep ``stall_s`` inside the call, then go on),
    "jump" (report counts shifted by ``jump`` from then on).
    """

    def __init__(self, inner: Any, at: int, fault: str, exc: BaseException | None = None,
                 stall_s: float = 0.2, jump: int = 500, realtime: bool | None = None) -> None:
        self.inner, self.at, self.fault = inner, at, fault
        self.exc, self.stall_s, self.jump = exc, stall_s, jump
        self.rate_hz = inner.rate_hz
        self.realtime = inner.realtime if realtime is None else realtime
        self.exchanges = 0
        self.sent: list[list[int]] = []
        """Commands of every exchange, in order (the initial read included)."""
        self.last_sent: list[int] | None = None
        """The last command that went out, by exchange or zero_force."""
        self.zero_calls: list[tuple[float, str]] = []
        self.fault_time: float | None = None
        self.exchange_times: list[float] = []
        """When each exchange call started (time.perf_counter) [s]."""

    @property
    def homed(self) -> bool:
        return self.inner.homed

    @property
    def plant(self) -> Any:
        """The simulated plant behind the wrapped device (makes it count as simulated)."""
        return self.inner.plant

    @property
    def device_clock(self) -> str:
        """How the wrapped device keeps time (a simulated one: "slots")."""
        return self.inner.device_clock

    def follow_deadlines(self, timer: Any) -> None:
        """Tell the wrapped device the loop's deadlines (a simulated one lives the skipped slots)."""
        follow_deadlines(self.inner, timer)

    def exchange(self, commands: Any, leds: int = 0) -> Any:
        k = self.exchanges
        self.exchanges += 1
        self.exchange_times.append(time.perf_counter())
        if k == self.at:
            self.fault_time = time.perf_counter()
            if self.fault == "raise":
                assert self.exc is not None
                raise self.exc
            if self.fault == "stall":
                time.sleep(self.stall_s)
        reading = self.inner.exchange(commands, leds)
        self.sent.append([int(c) for c in np.asarray(commands)])
        self.last_sent = self.sent[-1]
        if self.fault == "jump" and k >= self.at:
            shifted = np.asarray(reading.counts) + self.jump
            reading = type(reading)(shifted, reading.buttons, reading.homed, reading.t_s)
        return reading

    def zero_force(self) -> None:
        self.zero_calls.append((time.perf_counter(), threading.current_thread().name))
        self.inner.zero_force()
        self.last_sent = [0, 0, 0]
