"""The Zenoh side of the service: one session, the queryables, subscribers and publishers of
service/README.md, and the threads behind them.

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
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from falcon_plan.errors import InvalidParameterError
from service.codec import (MAX_PAYLOAD_BYTES, SCHEMA_VERSION, RequestError, encode_json, error_body,
                           schema_bytes)
from service.config import SessionSettings, open_session
from service.device import DeviceRunner
from service.goals import GoalManager
from service.handlers import (MAX_TIME_BUDGET_S, GoalRequest, PlanCache, PlannerFactory,
                              Vec3, check_plan_points, parse_goal_request, parse_plan_request, plan_cache_key,
                              plan_reply_bytes, request_id_of)
from service.keys import SCHEMA_NAMES, ServiceKeys
from service.members import Members, require_free_id
from service.workers import Outcome, PlanJob, PlanningPool, model_summary

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ServiceOptions:
    """Tunables of one instance (all have safe defaults).

    Attributes
    ----------
    state_rate_hz : device state publication rate [Hz].
    planning_workers : planner processes (or threads), each planning one request at a time.
    planning_processes : True (default): workers are processes, which plan in parallel (the
        solver holds the interpreter lock); False: threads in this process (for a planner
        that cannot be imported by name; a late or cancelled plan is answered on time but its
        thread stays busy until the planner returns).
    request_cap_s : longest any plan request or goal planning phase may take from its
        arrival, queue time included [s]; a request's ``timeout_s`` can only shorten it.
    max_pending_plans : plan requests allowed to wait for a worker before ``overloaded``.
    plan_cache_size : plans remembered by (start, goal, options); 0 disables the cache.
    queue_limit : pending goals allowed; goal_history : finished goals kept for queries.
    progress_rate_hz : most goal progress publications per second.
    max_payload_bytes : largest request accepted [bytes].
    """

    state_rate_hz: float = 50.0
    planning_workers: int = 1
    planning_processes: bool = True
    request_cap_s: float = MAX_TIME_BUDGET_S
    max_pending_plans: int = 64
    plan_cache_size: int = 64
    queue_limit: int = 16
    goal_history: int = 256
    progress_rate_hz: float = 20.0
    max_payload_bytes: int = MAX_PAYLOAD_BYTES

    def __post_init__(self) -> None:
        if not 0 < self.state_rate_hz <= 1000:
            raise InvalidParameterError(f"state_rate_hz must be in (0, 1000], got {self.state_rate_hz}")
        if not 1 <= self.planning_workers <= 64:
            raise InvalidParameterError(f"planning_workers must be in [1, 64], got {self.planning_workers}")
        if not 0 < self.request_cap_s <= 3600:
            raise InvalidParameterError(f"request_cap_s must be in (0, 3600] s, got {self.request_cap_s}")
        for name in ("max_pending_plans", "queue_limit", "goal_history", "max_payload_bytes"):
            if getattr(self, name) < 1:
                raise InvalidParameterError(f"{name} must be at least 1, got {getattr(self, name)}")


def _is_wildcard(key: str) -> bool:
    return "*" in key or "$" in key


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
        self.keys = keys
        self.runner = runner
        self.options = options
        self.cache = PlanCache(options.plan_cache_size)
        self.pool = PlanningPool(options.planning_workers, planner_factory, processes=options.planning_processes,
                                 model_path=model_path,
                                 max_pending=options.max_pending_plans, cache=self.cache,
                                 name=f"plan-{keys.instance}")
        self.members = Members(keys)
        self.goals = GoalManager(keys, runner, self._plan_goal, self._publish, queue_limit=options.queue_limit,
                                 history=options.goal_history, progress_rate_hz=options.progress_rate_hz,
                                 idle_poll_hz=options.state_rate_hz)
        self.session: Any = None
        self._declared: list[Any] = []
        self._token: Any = None
        self._state_pub: Any = None
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._close_lock = threading.Lock()
        self._closed = False
        self._encoding: Any = None

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

        self._encoding = zenoh.Encoding.APPLICATION_JSON
        try:
            self.session = open_session(self.settings)
            s = self.session
            require_free_id(s, self.keys)
            if self.runner is not None:
                self.runner.open()
            self.pool.start()
            self.members.watch(s)
            self._declared = [
                s.declare_queryable(self.keys.all, self._on_query, complete=True),
                # not complete: every instance gets each shared-key get, one answers (members.py)
                s.declare_queryable(self.keys.shared_plan, self._on_query, complete=False),
                s.declare_queryable(self.keys.shared_schema_pattern, self._on_query, complete=True),
                # one subscriber for every put on the instance's keys, so one client's submits
                # and cancels are handled in the order sent; remote only, so our own
                # publications (state, progress, results, errors) skip it
                s.declare_subscriber(self.keys.all, self._on_put, allowed_origin=zenoh.Locality.REMOTE),
            ]
            if self.runner is not None:
                self._state_pub = s.declare_publisher(self.keys.state, encoding=self._encoding)
                self._spawn(self._state_loop, f"state-{self.keys.instance}")
                self.goals.start()
            self._token = s.liveliness().declare_token(self.keys.alive)
        except BaseException:
            self.close()
            raise
        log.info("falcon-plan service %s up (%s), device %s", self.keys.base, self.settings.describe(),
                 self.runner.kind if self.runner else "none")

    def _spawn(self, target: Any, name: str) -> None:
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
        log.info("falcon-plan service %s closed", self.keys.base)

    @staticmethod
    def _undeclare(entity: Any) -> None:
        if entity is None:
            return
        try:
            entity.undeclare()
        except Exception:  # noqa: BLE001 - already gone with the session
            log.debug("undeclare failed", exc_info=True)

    # --- replies ----------------------------------------------------------------------------
    def _reply(self, query: Any, key: str, body: dict[str, Any] | bytes) -> None:
        payload = body if isinstance(body, bytes) else encode_json(body)
        query.reply(key, payload, encoding=self._encoding)

    def _reply_error(self, query: Any, error: RequestError, request_id: str | None = None) -> None:
        query.reply_err(encode_json(error_body(error, self.keys.instance, request_id)), encoding=self._encoding)

    def _publish(self, key: str, body: dict[str, Any]) -> None:
        session = self.session
        if session is None or self._closed and key == self.keys.state:
            return
        try:
            session.put(key, encode_json(body), encoding=self._encoding)
        except Exception:  # noqa: BLE001 - a closed session drops publications
            log.debug("publication on %s dropped", key, exc_info=True)

    def _publish_put_error(self, key: str, error: RequestError, request_id: str | None) -> None:
        body = error_body(error, self.keys.instance, request_id)
        body["key"] = key
        log.warning("rejected put on %s: %s", key, error)
        self._publish(self.keys.errors, body)

    # --- queries ----------------------------------------------------------------------------
    def _on_query(self, query: Any) -> None:
        """Every get reaching the instance (zenoh callback thread)."""
        t_recv = time.monotonic()
        key = str(query.key_expr)
        zbytes = query.payload
        size = len(zbytes) if zbytes is not None else 0
        payload = zbytes.to_bytes() if zbytes is not None and size <= self.options.max_payload_bytes else None
        encoding = str(query.encoding) if query.encoding is not None and payload else None
        finalise = True
        try:
            if key == self.keys.shared_plan and self.members.owner(payload or b"") != self.keys.instance:
                return  # another instance answers this one (members.py)
            if self._stop.is_set():
                raise RequestError("overloaded", "the service is shutting down; retry elsewhere")
            if _is_wildcard(key):
                for reply_key, body in self._wildcard_answers(key):
                    self._reply(query, reply_key, body)
                return
            route = self.keys.route(key)
            if route is None:
                raise RequestError("unknown_key", f"the service has no key {key!r}",
                                   field=None, allowed=self.keys.layout())
            if size > self.options.max_payload_bytes:
                raise RequestError("payload_too_large", f"payload of {size} bytes exceeds the limit of "
                                   f"{self.options.max_payload_bytes} bytes",
                                   allowed=f"at most {self.options.max_payload_bytes} bytes")
            if route.endpoint == "plan":
                finalise = not self._start_plan(query, key, payload, encoding, t_recv)
            elif route.endpoint == "goals/submit":
                self._reply(query, key, self.goals.submit(parse_goal_request(payload, encoding, require_id=False,
                                                                             cap_s=self.options.request_cap_s)))
            elif route.endpoint == "goal/result":
                self._reply(query, key, self.goals.result(route.arg or ""))
            elif route.endpoint == "goal/cancel":
                self._reply(query, key, self.goals.cancel(route.arg or ""))
            elif route.endpoint == "state":
                self._reply(query, key, self._state_body())
            elif route.endpoint == "info":
                self._reply(query, key, self._info_body())
            elif route.endpoint == "schema":
                self._reply(query, key, self._schema(route.arg or ""))
            else:  # progress, errors: publication-only keys
                raise RequestError("unknown_key", f"{key!r} is published, not queried: subscribe to it",
                                   allowed=self.keys.layout())
        except RequestError as exc:
            self._reply_error(query, exc, request_id_of(payload))
        except Exception as exc:  # noqa: BLE001 - bad input must never stop the service
            log.exception("query on %s failed", key)
            self._reply_error(query, RequestError("internal_error", f"{type(exc).__name__}: {exc}"))
        finally:
            if finalise:
                query.drop()

    def _schema(self, name: str) -> bytes:
        if name not in SCHEMA_NAMES:
            raise RequestError("unknown_key", f"no schema {name!r}", field=None, allowed=list(SCHEMA_NAMES))
        return schema_bytes(name)

    def _wildcard_answers(self, key: str) -> list[tuple[str, dict[str, Any] | bytes]]:
        """Answers to a wildcard get: every read-only key of the instance it matches
        (state, info, schemas, goal results); nothing for the rest."""
        import zenoh

        wanted = zenoh.KeyExpr(key)
        candidates: list[tuple[str, Any]] = [(self.keys.info, self._info_body)]
        if self.runner is not None:
            candidates.append((self.keys.state, self._state_body))
        candidates += [(self.keys.schema(n), lambda n=n: schema_bytes(n)) for n in SCHEMA_NAMES]
        candidates += [(self.keys.goal_result(g), lambda g=g: self.goals.result(g)) for g in self.goals.goal_ids()]
        out = []
        for candidate, make in candidates:
            if wanted.intersects(candidate):
                try:
                    out.append((candidate, make()))
                except RequestError:
                    continue  # e.g. a goal result trimmed meanwhile
        return out

    def _start_plan(self, query: Any, key: str, payload: bytes | None, encoding: str | None, t_recv: float) -> bool:
        """Answer from the cache or queue the request; True if the pool now owns the query."""
        request = parse_plan_request(payload, encoding, check_workspace=False, cap_s=self.options.request_cap_s)
        cached = self.cache.get(plan_cache_key(request.start_m, request.goal_m, request.options))
        if cached is not None:  # it passed the workspace check when it was planned
            self._reply(query, key, plan_reply_bytes(request, self.keys.instance, cached, queue_s=0.0,
                                                     service_s=time.monotonic() - t_recv))
            return False
        check_plan_points(request)
        wait_s = min(self.options.request_cap_s, request.timeout_s or math.inf)

        def answer(job: PlanJob, outcome: Outcome) -> None:
            try:
                if isinstance(outcome, RequestError):
                    self._reply_error(query, outcome, request.request_id)
                else:
                    queue_s = (job.started or t_recv) - t_recv
                    service_s = max(0.0, time.monotonic() - t_recv - queue_s - outcome.plan_s)
                    self._reply(query, key, plan_reply_bytes(request, self.keys.instance, outcome,
                                                             queue_s=queue_s, service_s=service_s))
            finally:
                query.drop()

        self.pool.submit(PlanJob(request, request.start_m, t_recv + wait_s, answer, arrived=t_recv))
        return True

    def _plan_goal(self, request: GoalRequest, start_m: Vec3, cancel: threading.Event) -> tuple[Any, dict[str, Any]]:
        """Plan a goal on the planning pool within the service's cap from now; a cancel of
        the goal ends the planning at once."""
        result = self.pool.plan_blocking(request, start_m, cancel, self.options.request_cap_s)
        return result.trajectory, result.report or {}

    # --- puts -------------------------------------------------------------------------------
    def _on_put(self, sample: Any) -> None:
        """A put on one of the instance's keys: a goal submission (id required) or a cancel;
        a put anywhere else (e.g. on ``state``) or a refused request is logged and reported on
        the errors key, as puts have no reply."""
        import zenoh

        if sample.kind != zenoh.SampleKind.PUT:
            return
        key = str(sample.key_expr)
        route = self.keys.route(key)
        zbytes = sample.payload
        size = len(zbytes)
        payload = zbytes.to_bytes() if size <= self.options.max_payload_bytes else None
        if route is not None and route.endpoint == "goals/submit":
            goal_id = self._goal_id_of(payload)
        else:
            goal_id = route.arg if route is not None and route.endpoint.startswith("goal/") else None
        try:
            if route is not None and route.endpoint == "goal/cancel":
                self.goals.cancel(route.arg or "")
            elif route is None or route.endpoint != "goals/submit":
                raise RequestError("unknown_key", f"a put on {key!r} does nothing: puts go to goals/submit or "
                                   "goals/<id>/cancel", allowed=[self.keys.goals_submit, self.keys.goal_cancel("<id>")])
            elif payload is None:
                raise RequestError("payload_too_large", f"payload of {size} bytes exceeds the limit of "
                                   f"{self.options.max_payload_bytes} bytes")
            else:
                encoding = str(sample.encoding) if payload else None
                self.goals.submit(parse_goal_request(payload, encoding, require_id=True,
                                                     cap_s=self.options.request_cap_s))
        except RequestError as exc:
            self._publish_put_error(key, exc, goal_id)
        except Exception as exc:  # noqa: BLE001 - bad input must never stop the service
            log.exception("put on %s failed", key)
            self._publish_put_error(key, RequestError("internal_error", f"{type(exc).__name__}: {exc}"), goal_id)

    @staticmethod
    def _goal_id_of(payload: bytes | None) -> str | None:
        """Best-effort ``id`` of a goal payload, to name it in an error report."""
        import json

        try:
            data = json.loads(payload or b"")
        except (ValueError, RecursionError):
            return None
        gid = data.get("id") if isinstance(data, dict) else None
        return gid if isinstance(gid, str) and len(gid) <= 64 else None

    # --- state ------------------------------------------------------------------------------
    def _state_body(self) -> dict[str, Any]:
        if self.runner is None:
            raise RequestError("no_device", f"instance {self.keys.instance!r} has no device (planning only)",
                               allowed="an instance whose info says can_execute: true")
        snap = self.runner.snapshot()
        executing, pending = self.goals.activity()
        return {"schema_version": SCHEMA_VERSION, "instance": self.keys.instance, "device": self.runner.kind,
                "t_s": snap.wall_t_s if snap else time.time(),
                "position_m": list(snap.position_m) if snap and snap.position_m else None,
                "encoders": list(snap.counts) if snap else None,
                "homed": list(snap.homed) if snap else [False, False, False],
                "buttons": snap.buttons if snap else None, "executing": executing, "queue": pending}

    def _state_loop(self) -> None:
        period = 1.0 / self.options.state_rate_hz
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                self._state_pub.put(encode_json(self._state_body()))
            except Exception:  # noqa: BLE001 - keep publishing
                log.debug("state publication failed", exc_info=True)
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t, delay = time.monotonic(), 0.0
            self._stop.wait(delay)

    def _info_body(self) -> dict[str, Any]:
        running, waiting = self.pool.busy()
        return {"schema_version": SCHEMA_VERSION, "instance": self.keys.instance,
                "device": self.runner.kind if self.runner else "none", "can_execute": self.runner is not None,
                "prefix": self.keys.prefix, "keys": self.keys.layout(), "schemas": list(SCHEMA_NAMES),
                "max_payload_bytes": self.options.max_payload_bytes, "queue_limit": self.options.queue_limit,
                "planning_workers": self.options.planning_workers,
                "planning_processes": self.options.planning_processes, "request_cap_s": self.options.request_cap_s,
                "state_rate_hz": self.options.state_rate_hz, "members": self.members.ids(),
                "planning": {"running": running, "waiting": waiting, **self.pool.stats},
                "model": self.model_info}
