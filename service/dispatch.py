"""Routing of one instance's requests: every get (:meth:`Dispatcher.on_query`) and put
(:meth:`Dispatcher.on_put`) reaching the instance's keys goes to its handler (plans to the
cache or the planning pool, goals to the goal manager, state, info and schemas answered at
once), and every refusal becomes a coded error (a reply for a get, a publication on the
errors key for a put). Runs on zenoh's callback threads; bad input never stops the service.
Keys and payloads: service/README.md.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from functools import lru_cache
from typing import TYPE_CHECKING, Any, Callable

from service.codec import RequestError, encode_json, error_body, schema_bytes
from service.handlers import (GoalRequest, PlanCache, parse_goal_request, parse_plan_request, payload_string,
                              plan_cache_key, plan_reply_bytes, request_id_of, require_in_workspace)
from service.keys import SCHEMA_NAMES, ServiceKeys
from service.workers import Outcome, PlanJob, PlanningPool

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from service.goals import GoalManager
    from service.members import Members
    from service.options import ServiceOptions

log = logging.getLogger(__name__)


@lru_cache(maxsize=1)
def json_encoding() -> Any:
    """zenoh's JSON encoding of every reply and publication (zenoh imported on first use)."""
    import zenoh

    return zenoh.Encoding.APPLICATION_JSON


def _is_wildcard(key: str) -> bool:
    return "*" in key or "$" in key


class Dispatcher:
    """Answers the gets and puts of one instance.

    Parameters
    ----------
    keys : the instance's key layout; options : its tunables (payload limit, request cap).
    cache : the plan cache; pool : the planning pool; goals : the goal manager; members : the
        instances under the prefix (which one answers a get on the shared plan key).
    stop : set when the instance is stopping (new requests then get ``overloaded``).
    publish : ``publish(key, body)`` puts a JSON body (refusals of puts go to the errors key).
    state_body, info_body : make the ``state`` and ``info`` bodies (:mod:`service.status`).
    has_device : whether the instance owns a device (a wildcard get then includes state).
    model : the model the instance plans with; each request's points are checked against its
        workspace once, when the request arrives.
    """

    def __init__(self, keys: ServiceKeys, options: ServiceOptions, cache: PlanCache, pool: PlanningPool,
                 goals: GoalManager, members: Members, stop: threading.Event,
                 publish: Callable[[str, dict[str, Any]], None], state_body: Callable[[], dict[str, Any]],
                 info_body: Callable[[], dict[str, Any]], has_device: bool, model: FalconModel) -> None:
        self.keys, self.options, self.cache, self.pool = keys, options, cache, pool
        self.goals, self.members, self.stop, self.publish = goals, members, stop, publish
        self.state_body, self.info_body, self.has_device = state_body, info_body, has_device
        self.model = model

    # --- replies ----------------------------------------------------------------------------
    def reply(self, query: Any, key: str, body: dict[str, Any] | bytes) -> None:
        """Answer ``query`` on ``key`` with ``body`` (a JSON object, or bytes already encoded)."""
        payload = body if isinstance(body, bytes) else encode_json(body)
        query.reply(key, payload, encoding=json_encoding())

    def reply_error(self, query: Any, error: RequestError, request_id: str | None = None) -> None:
        """Answer ``query`` with the coded ``error`` (naming the request's ``request_id``)."""
        query.reply_err(encode_json(error_body(error, self.keys.instance, request_id)), encoding=json_encoding())

    def _publish_put_error(self, key: str, error: RequestError, request_id: str | None) -> None:
        body = error_body(error, self.keys.instance, request_id)
        body["key"] = key
        log.warning("rejected put on %s: %s", key, error)
        self.publish(self.keys.errors, body)

    # --- queries ----------------------------------------------------------------------------
    def on_query(self, query: Any) -> None:
        """Answer ``query``, a get reaching the instance (zenoh callback thread)."""
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
            if self.stop.is_set():
                raise RequestError("overloaded", "the service is shutting down; retry elsewhere")
            if _is_wildcard(key):
                for reply_key, body in self._wildcard_answers(key):
                    self.reply(query, reply_key, body)
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
                self.reply(query, key, self.goals.submit(self._goal_request(payload, encoding, require_id=False)))
            elif route.endpoint == "goal/result":
                self.reply(query, key, self.goals.result(route.arg or ""))
            elif route.endpoint == "goal/cancel":
                self.reply(query, key, self.goals.cancel(route.arg or ""))
            elif route.endpoint == "state":
                self.reply(query, key, self.state_body())
            elif route.endpoint == "info":
                self.reply(query, key, self.info_body())
            elif route.endpoint == "schema":
                self.reply(query, key, self._schema(route.arg or ""))
            else:  # progress, errors: publication-only keys
                raise RequestError("unknown_key", f"{key!r} is published, not queried: subscribe to it",
                                   allowed=self.keys.layout())
        except RequestError as exc:
            self.reply_error(query, exc, request_id_of(payload))
        except Exception as exc:  # noqa: BLE001 - bad input must never stop the service
            log.exception("query on %s failed", key)
            self.reply_error(query, RequestError("internal_error", f"{type(exc).__name__}: {exc}"))
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
        candidates: list[tuple[str, Any]] = [(self.keys.info, self.info_body)]
        if self.has_device:
            candidates.append((self.keys.state, self.state_body))
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
        request = parse_plan_request(payload, encoding, cap_s=self.options.request_cap_s)
        cached = self.cache.get(plan_cache_key(request.problem, request.options))
        if cached is not None:  # it passed the workspace check when it was planned
            self.reply(query, key, plan_reply_bytes(request, self.keys.instance, cached, queue_s=0.0,
                                                     service_s=time.monotonic() - t_recv))
            return False
        require_in_workspace(request.problem, self.model)
        wait_s = min(self.options.request_cap_s, request.timeout_s or math.inf)

        def answer(job: PlanJob, outcome: Outcome) -> None:
            try:
                if isinstance(outcome, RequestError):
                    self.reply_error(query, outcome, request.request_id)
                else:
                    queue_s = (job.started or t_recv) - t_recv
                    service_s = max(0.0, time.monotonic() - t_recv - queue_s - outcome.plan_s)
                    self.reply(query, key, plan_reply_bytes(request, self.keys.instance, outcome,
                                                             queue_s=queue_s, service_s=service_s))
            finally:
                query.drop()

        self.pool.submit(PlanJob(request.problem, request.options, t_recv + wait_s, answer, arrived=t_recv))
        return True

    def _goal_request(self, payload: bytes | None, encoding: str | None, *, require_id: bool) -> GoalRequest:
        """The goal request ``payload``, checked (its asked-for points in the workspace of the
        model the instance plans with)."""
        request = parse_goal_request(payload, encoding, require_id=require_id, cap_s=self.options.request_cap_s)
        require_in_workspace(request.problem, self.model, skip_start=not request.start_given)
        return request

    # --- puts -------------------------------------------------------------------------------
    def on_put(self, sample: Any) -> None:
        """Handle ``sample``, a put on one of the instance's keys: a goal submission (id
        required) or a cancel;
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
            goal_id = payload_string(payload, "id", 64)  # best effort, to name it in an error
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
                self.goals.submit(self._goal_request(payload, encoding, require_id=True))
        except RequestError as exc:
            self._publish_put_error(key, exc, goal_id)
        except Exception as exc:  # noqa: BLE001 - bad input must never stop the service
            log.exception("put on %s failed", key)
            self._publish_put_error(key, RequestError("internal_error", f"{type(exc).__name__}: {exc}"), goal_id)
