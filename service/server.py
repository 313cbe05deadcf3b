"""The Zenoh side of the service: one session, the queryables, subscribers and publishers of
service/README.md, and the threads behind them. This module owns the instance's lifetime
(start, stop, close) and wires its parts: the routing of requests (:mod:`service.dispatch`),
the planning pool (:mod:`service.workers`), the goal queue (:mod:`service.goals`) and the
state publication (:mod:`service.status`).

Threads: zenoh's own callback threads decode requests and answer the quick ones (state,
info, schemas, goal submission, results, cancels, plans found in the cache); plans that need
the planner go to the :class:`~service.workers.PlanningPool` (``planning_workers`` processes,
each request held to its deadline; past ``max_pending_plans`` waiting, a request gets
``overloaded`` at once); goals run on the :class:`~service.goals.GoalManager`'s worker and
plan on the same pool; a publisher thread sends the device state at ``state_rate_hz``.
Requests on the shared plan key reach every instance and are answered by one
(:mod:`service.members`). Every query is dropped (finalised) as soon as it is answered, so no client
waits for its timeout (a query's final message goes out only when the Query object is
finalised; zenoh-python issue #459). :meth:`FalconService.close` stops all of it in order and closes the
session; it is idempotent and safe from a signal handler's thread.
"""
from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from falcon_plan.model.dynamics import FalconModel
from service.codec import encode_json
from service.config import SessionSettings, open_session
from service.device import DeviceRunner
from service.dispatch import Dispatcher, json_encoding
from service.goals import GoalManager
from falcon_plan.planning.problem import PlanProblem
from service.handlers import PlanCache, PlannerFactory
from service.keys import ServiceKeys
from service.members import Members, require_free_id
from service.options import ServiceOptions
from service.status import StatePublisher, info_body, state_body
from service.workers import PlanningPool, load_model, model_summary

if TYPE_CHECKING:
    from falcon_plan.recording.live import LiveView
    from falcon_plan.recording.recorder import RunRecorder

log = logging.getLogger(__name__)


class FalconService:
    """One running instance: ``with FalconService(...) as svc: svc.wait()``.

    Parameters
    ----------
    settings : how to open the zenoh session.
    keys : prefix and instance id.
    planner_factory : builds the planner (:func:`service.handlers.falcon_planner` in
        production); a module-level function when ``options.planning_processes``, as each
        process imports it by name and builds its own planner.
    runner : the device runner, or None for a planning-only instance.
    options : tunables.
    model_path : a model file (``discrepancy``'s output); the planners are built with its
        model (each planning process loads it) and ``info`` reports it. None: nominal.
    """

    def __init__(self, settings: SessionSettings, keys: ServiceKeys, planner_factory: PlannerFactory,
                 runner: DeviceRunner | None = None, options: ServiceOptions = ServiceOptions(),
                 model_path: Path | None = None) -> None:
        self.settings = settings
        self.model_info = model_summary(model_path)
        """What ``info`` reports as the service's model (a ModelFile summary)."""
        self.model = load_model(model_path) or FalconModel()
        """The model the planners plan with (requests are checked against its workspace)."""
        self.keys = keys
        self.runner = runner
        self.options = options
        self.cache = PlanCache(options.plan_cache_size)
        self.pool = PlanningPool(options.planning_workers, planner_factory, processes=options.planning_processes,
                                 model_path=model_path,
                                 max_pending=options.max_pending_plans, cache=self.cache,
                                 name=f"plan-{keys.instance}")
        self.members = Members(keys)
        self.live: LiveView | None = None
        """The Foxglove live view (``options.foxglove_port``), started with the service."""
        recorded = options.record_dir is not None or options.foxglove_port is not None
        self.goals = GoalManager(keys, runner, self._plan_goal, self._publish, queue_limit=options.queue_limit,
                                 history=options.goal_history, progress_rate_hz=options.progress_rate_hz,
                                 idle_poll_hz=options.state_rate_hz,
                                 recorder_for=self._goal_recorder if recorded else None,
                                 recorded_before=self._recorded_before if options.record_dir is not None else None)
        self._stop = threading.Event()
        self.dispatch = Dispatcher(
            keys, options, self.cache, self.pool, self.goals, self.members, self._stop, self._publish,
            state_body=lambda: state_body(keys, runner, self.goals),
            info_body=lambda: info_body(keys, runner, options, self.pool, self.members, self.model_info),
            has_device=runner is not None, model=self.model)
        self.session: Any = None
        self._declared: list[Any] = []
        self._token: Any = None
        self._threads: list[threading.Thread] = []
        self._close_lock = threading.Lock()
        self._closed = False

    # --- lifetime ---------------------------------------------------------------------------
    def __enter__(self) -> "FalconService":
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def start(self) -> None:
        """Open the session, refuse a taken instance id, open the device, start the planning
        workers, declare everything, and last the liveliness token."""
        import zenoh

        try:
            self.session = open_session(self.settings)
            s = self.session
            require_free_id(s, self.keys)
            if self.runner is not None:
                self.runner.open()
            if self.options.foxglove_port is not None:
                from falcon_plan.recording.live import LiveView

                self.live = LiveView(self.options.foxglove_port, name=f"falcon-plan {self.keys.base}")
            self.pool.start()
            self.members.watch(s)
            self._declared = [
                s.declare_queryable(self.keys.all, self.dispatch.on_query, complete=True),
                # not complete: every instance gets each shared-key get, one answers (members.py)
                s.declare_queryable(self.keys.shared_plan, self.dispatch.on_query, complete=False),
                s.declare_queryable(self.keys.shared_schema_pattern, self.dispatch.on_query, complete=True),
                # one subscriber for every put on the instance's keys, so one client's submits
                # and cancels are handled in the order sent; remote only, so our own
                # publications (state, progress, results, errors) skip it
                s.declare_subscriber(self.keys.all, self.dispatch.on_put, allowed_origin=zenoh.Locality.REMOTE),
            ]
            if self.runner is not None:
                publisher = s.declare_publisher(self.keys.state, encoding=json_encoding())
                states = StatePublisher(publisher, self.dispatch.state_body, self.options.state_rate_hz, self._stop)
                self._spawn(states.run, f"state-{self.keys.instance}")
                self.goals.start()
            self._token = s.liveliness().declare_token(self.keys.alive)
        except BaseException:
            self.close()
            raise
        log.info("falcon-plan service %s up (%s), device %s", self.keys.base, self.settings.describe(),
                 self.runner.kind if self.runner else "none")

    def _goal_recorder(self, goal_id: str) -> RunRecorder | None:
        """The recorder of goal ``goal_id``: ``<record_dir>/<goal_id>.mcap`` and/or the live view."""
        from falcon_plan.recording.recorder import open_recorder

        path = None if self.options.record_dir is None else Path(self.options.record_dir) / f"{goal_id}.mcap"
        return open_recorder(path, self.live, metadata={"service": {"instance": self.keys.base, "goal_id": goal_id}})

    def _recorded_before(self, goal_id: str) -> str | None:
        """The recording of goal ``goal_id`` in ``<record_dir>`` if one exists (a path), else None."""
        path = Path(self.options.record_dir) / f"{goal_id}.mcap"
        return str(path) if path.exists() else None

    def _spawn(self, target: Callable[[], None], name: str) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until :meth:`request_stop` (or ``timeout_s``); True if stopping."""
        return self._stop.wait(timeout_s)

    def request_stop(self) -> None:
        """Ask :meth:`wait` to return (safe from a signal handler)."""
        self._stop.set()

    def close(self) -> None:
        """Stop everything in order and close the session and the device; idempotent."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        self._stop.set()
        # leave the members first: the others take over this one's share of the shared key
        self._undeclare(self._token)
        self.goals.stop()  # the running goal is cancelled (also while planning)
        self.pool.close()  # plans waiting or in flight get an error reply now
        for thread in self._threads:
            thread.join(timeout=2.0)
        # The queryables and subscribers go with the session. (Undeclaring a queryable that is
        # not complete just before closing a client-mode session left the router routing gets
        # to it, each waiting for its timeout: eclipse-zenoh 1.10, tests/service/test_instances.py.)
        if self.session is not None:
            try:
                self.session.close()
            except Exception:  # noqa: BLE001 - closing must finish
                log.exception("closing the zenoh session failed")
        if self.runner is not None and self.runner.is_open:
            self.runner.close()
        if self.live is not None:
            self.live.close()
        log.info("falcon-plan service %s closed", self.keys.base)

    @staticmethod
    def _undeclare(entity: Any) -> None:
        if entity is None:
            return
        try:
            entity.undeclare()
        except Exception:  # noqa: BLE001 - already gone with the session
            log.debug("undeclare failed", exc_info=True)

    # --- publications ----------------------------------------------------------------------
    def _publish(self, key: str, body: dict[str, Any]) -> None:
        session = self.session
        if session is None or self._closed and key == self.keys.state:
            return
        try:
            session.put(key, encode_json(body), encoding=json_encoding())
        except Exception:  # noqa: BLE001 - a closed session drops publications
            log.debug("publication on %s dropped", key, exc_info=True)

    def _plan_goal(self, problem: PlanProblem, options: dict[str, Any] | None,
                   cancel: threading.Event) -> tuple[Any, dict[str, Any]]:
        """Plan a goal's ``problem`` with ``options`` on the planning pool within the
        service's cap from now; a cancel of the goal ends the planning at once."""
        result = self.pool.plan_blocking(problem, options, cancel, self.options.request_cap_s)
        return result.trajectory, result.report or {}
