"""What an instance says about itself: the ``state`` body (device position, encoders, homing,
goal activity), published at ``state_rate_hz`` by :class:`StatePublisher` and answered on a
get, and the ``info`` body (keys, limits, planning load, model). Keys and payloads:
service/README.md."""
from __future__ import annotations

import logging
import threading
import time
from typing import TYPE_CHECKING, Any, Callable

from service.codec import SCHEMA_VERSION, RequestError, encode_json
from service.keys import SCHEMA_NAMES, ServiceKeys

if TYPE_CHECKING:
    from service.device import DeviceRunner
    from service.goals import GoalManager
    from service.members import Members
    from service.options import ServiceOptions
    from service.workers import PlanningPool

log = logging.getLogger(__name__)


def state_body(keys: ServiceKeys, runner: DeviceRunner | None, goals: GoalManager) -> dict[str, Any]:
    """The ``state`` body of the instance ``keys`` names: its device ``runner``'s latest
    snapshot and the goal activity of ``goals``; ``no_device`` (a RequestError) for a
    planning-only instance (``runner`` None)."""
    if runner is None:
        raise RequestError("no_device", f"instance {keys.instance!r} has no device (planning only)",
                           allowed="an instance whose info says can_execute: true")
    snap = runner.snapshot()
    executing, pending = goals.activity()
    return {"schema_version": SCHEMA_VERSION, "instance": keys.instance, "device": runner.kind,
            "t_s": snap.wall_t_s if snap else time.time(),
            "position_m": list(snap.position_m) if snap and snap.position_m else None,
            "encoders": list(snap.counts) if snap else None,
            "homed": list(snap.homed) if snap else [False, False, False],
            "buttons": snap.buttons if snap else None, "executing": executing, "queue": pending}


def info_body(keys: ServiceKeys, runner: DeviceRunner | None, options: ServiceOptions, pool: PlanningPool,
              members: Members, model_info: dict[str, Any]) -> dict[str, Any]:
    """The ``info`` body of the instance ``keys`` names: its device ``runner`` (None:
    planning only), its tunables ``options``, the planning ``pool``'s load and counters, the
    instance ids ``members`` sees under the prefix, and ``model_info`` (the model it plans
    with, a ModelFile summary)."""
    running, waiting = pool.busy()
    return {"schema_version": SCHEMA_VERSION, "instance": keys.instance,
            "device": runner.kind if runner else "none", "can_execute": runner is not None,
            "prefix": keys.prefix, "keys": keys.layout(), "schemas": list(SCHEMA_NAMES),
            "max_payload_bytes": options.max_payload_bytes, "queue_limit": options.queue_limit,
            "planning_workers": options.planning_workers,
            "planning_processes": options.planning_processes, "request_cap_s": options.request_cap_s,
            "state_rate_hz": options.state_rate_hz, "members": members.ids(),
            "planning": {"running": running, "waiting": waiting, **pool.stats},
            "model": model_info}


class StatePublisher:
    """Publishes the device state at a fixed rate on its own thread until ``stop`` is set.

    ``publisher``: the declared zenoh publisher of the state key; ``body``: makes the state
    body (:func:`state_body`); ``rate_hz``: publications per second; ``stop``: the instance's
    stop event. A late publication is skipped, not made up (the schedule restarts from now)."""

    def __init__(self, publisher: Any, body: Callable[[], dict[str, Any]], rate_hz: float,
                 stop: threading.Event) -> None:
        self.publisher, self.body, self.period_s, self.stop = publisher, body, 1.0 / rate_hz, stop

    def run(self) -> None:
        """The publishing loop (the thread's target)."""
        next_t = time.monotonic()
        while not self.stop.is_set():
            try:
                self.publisher.put(encode_json(self.body()))
            except Exception:  # noqa: BLE001 - keep publishing
                log.debug("state publication failed", exc_info=True)
            next_t += self.period_s
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t, delay = time.monotonic(), 0.0
            self.stop.wait(delay)
