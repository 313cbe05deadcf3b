"""Helpers to run service instances in-process and talk to them: for tests, examples and
benchmarks. Real Zenoh sessions on loopback only (a fresh free port each), multicast
scouting off, every session closed on exit whatever happened.
"""
from __future__ import annotations

import contextlib
import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator

from service.client import FalconClient, wait_for_instance
from service.codec import load_schema, validate
from service.config import SessionSettings, free_loopback_port
from service.device import make_runner
from service.handlers import falcon_planner
from service.keys import ServiceKeys
from service.options import ServiceOptions
from service.server import FalconService

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel

PREFIX = "falcontest"
"""Key prefix of test instances (not the default, so a running demo is never disturbed)."""

HOME_M = (0.0, 0.0, 0.1448)
"""The simulated device's home position [m] (all encoder counts 0)."""
GOAL_A_M = (0.02, 0.01, 0.13)
GOAL_B_M = (0.0, 0.0, 0.14)
"""Two goals near home, inside the workspace, reachable from each other and from home."""

REPLY_TIMEOUT_S = 30.0
"""Longest wait for a reply (a cold plan compiles the planner's functions)."""


def endpoint() -> str:
    """A fresh loopback endpoint."""
    return f"tcp/127.0.0.1:{free_loopback_port()}"


@contextlib.contextmanager
def running_service(instance: str, device: str = "none", model: FalconModel | None = None, listen: str | None = None,
                    connect: tuple[str, ...] = (), options: ServiceOptions = ServiceOptions(),
                    prefix: str = PREFIX, settings: SessionSettings | None = None,
                    model_path: Path | None = None) -> Iterator[FalconService]:
    """A started service ``instance`` under ``prefix`` with a ``device`` of that kind and the
    tunables ``options``, listening on ``listen`` (default: a fresh loopback endpoint) and
    joining ``connect``, or with ``settings``; closed on exit whatever happened. ``model`` is the device's; the
    planning processes build the nominal model, or the one in ``model_path``."""
    service = FalconService(settings or SessionSettings.server([listen or endpoint()], connect),
                            ServiceKeys(prefix, instance), falcon_planner, make_runner(device, model), options,
                            model_path=model_path)
    try:
        service.start()
        yield service
    finally:
        service.close()


@contextlib.contextmanager
def client_for(service_or_endpoint: Any, instance: str = "sim0", timeout_s: float = REPLY_TIMEOUT_S,
               prefix: str = PREFIX, mode: str = "peer") -> Iterator[FalconClient]:
    """A client session (``mode`` peer or client) connected to ``service_or_endpoint`` (a
    running service, or an endpoint, e.g. a router's), under ``prefix``, once ``instance``
    is alive, with replies awaited at most ``timeout_s`` [s]; closed on exit."""
    ep = service_or_endpoint if isinstance(service_or_endpoint, str) else service_or_endpoint.settings.listen[0]
    client = FalconClient(SessionSettings.client([ep], mode=mode), prefix=prefix, instance=instance,
                          timeout_s=timeout_s)
    try:
        wait_for_instance(client, instance)
        yield client
    finally:
        client.close()


def check_schema(body: dict[str, Any], name: str) -> dict[str, Any]:
    """Assert ``body`` follows the published schema ``name``; returns it."""
    validate(json.loads(json.dumps(body)), load_schema(name))
    return body


def wait_until(condition: Callable[[], Any], what: str, timeout_s: float = 20.0) -> Any:
    """Poll ``condition`` until it returns a true value (returned), at most ``timeout_s`` [s]
    (generous: a loaded machine is slow, a broken subject still fails), then AssertionError
    naming ``what`` was awaited."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"waited {timeout_s} s for {what}")
        time.sleep(0.02)


def left_at_tolerance_mm(tracking_report: dict[str, Any]) -> float:
    """How far [mm] the device's next reading may be from where a run's ``tracking_report``
    (the executor's report as a dict) says it left the device (its final tracking error): the state is the reading one sample after the last
    logged one, so 0.5 mm for a run that kept its deadlines (the arm is settled), 2 mm for one
    that skipped slots on a loaded machine (the arm still moving at its end)."""
    return 0.5 if tracking_report["skipped_slots"] == 0 else 2.0


START_GATE_ENV = "FALCON_PLAN_TEST_START_GATE"
"""Names the file :func:`gated_planner_factory` waits for."""


def gated_planner_factory(model: FalconModel | None = None) -> Callable[..., Any]:
    """A planner factory (for a planning process) that stands for a slow first start (the
    kernels compiling): it returns only once the file named by ``$FALCON_PLAN_TEST_START_GATE``
    exists, and exits with status 3 if that file says ``exit``. Its planner (``model`` is not
    used) plans nothing."""
    import os

    gate = Path(os.environ[START_GATE_ENV])
    while not gate.exists():
        time.sleep(0.01)
    if gate.read_text().strip() == "exit":
        raise SystemExit(3)

    def planner(*args: Any) -> Any:
        raise RuntimeError("the gated test planner plans nothing")

    return planner
