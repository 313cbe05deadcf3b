"""Pure request handling: payload bytes in, reply body out (no zenoh here).

The service plans through a :data:`Planner` callable, so the machinery can be exercised with
any planner; :func:`falcon_planner` is the real one (``falcon_plan.planning.api.plan``).
Every refusal is a :class:`~service.codec.RequestError` with a code, a message saying what is
wrong and what is allowed, and the offending field.
"""
from __future__ import annotations

import collections
import json
import logging
import re
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from falcon_plan.errors import FalconPlanError, InvalidProblemError, PlanningFailed, WorkspaceError
from falcon_plan.model.workspace import require_in_workspace
from service.codec import SCHEMA_VERSION, RequestError, decode_request, encode_json

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class PlanOutcome:
    """What a planner returns: the trajectory (anything with ``to_dict()``, normally a
    :class:`~falcon_plan.trajectory.Trajectory`) and the plan report as a dict."""

    trajectory: Trajectory
    report: dict[str, Any]


Planner = Callable[..., PlanOutcome]
"""``planner(start_m, goal_m, options, budget_s=None) -> PlanOutcome``; raises
InvalidProblemError, WorkspaceError or PlanningFailed for problems it refuses or cannot solve.
``budget_s`` [s], when given, caps the optimiser's time budget (the service passes the time
left before the request's deadline)."""

PlannerFactory = Callable[[Any], Planner]
"""Builds a planner from a model (None: the nominal model)."""
"""Builds a planner; for planning processes it must be a module-level function (such as
:func:`falcon_planner`), which each process imports by name to build its own."""


def falcon_planner(model: FalconModel | None = None, *, fast_by_default: bool = True) -> Planner:
    """The real planner for ``model`` (None: nominal): ``falcon_plan.planning.api.plan`` with options built from the
    request's ``options`` object on top of ``PlanOptions.fast(warm_start="neighbours")`` (no
    cross-checks, no refinement, no plant run, warm starts from solved neighbours: the
    service's latency path; a request may set ``warm_start: "none"``) unless
    ``fast_by_default`` is False. Imports lazily so the service machinery loads without the
    planner."""
    from falcon_plan.planning.api import plan
    from falcon_plan.planning.problem import PlanOptions

    base = (PlanOptions.fast(warm_start="neighbours") if fast_by_default else PlanOptions()).to_dict()

    def planner(start_m: Vec3, goal_m: Vec3, options: dict[str, Any] | None,
                budget_s: float | None = None) -> PlanOutcome:
        opts = PlanOptions.from_dict({**base, **(options or {})})
        if budget_s is not None and budget_s < opts.solver.time_budget_s:
            opts = opts.replace(time_budget_s=max(budget_s, 1e-3))
        result = plan(start_m, goal_m, opts, model)
        report = result.report.to_dict() if hasattr(result.report, "to_dict") else dict(result.report)
        return PlanOutcome(result.trajectory, report)

    return planner


# --- requests --------------------------------------------------------------------------------
@dataclass(frozen=True)
class PlanRequest:
    """A validated plan request: from ``start_m`` to ``goal_m`` [m, base frame] with
    ``options`` (PlanOptions fields), tagged ``request_id``; ``timeout_s``: how long the
    requester waits."""

    start_m: Vec3
    goal_m: Vec3
    options: dict[str, Any] | None = None
    request_id: str | None = None
    timeout_s: float | None = None
    """How long the requester waits [s] from sending (None: it did not say)."""


@dataclass(frozen=True)
class GoalRequest:
    """A validated goal to ``goal_m`` [m] with ``options`` (PlanOptions fields), named
    ``goal_id`` (None: the service names it); ``start_m`` None means "from where the device
    is"."""

    goal_m: Vec3
    start_m: Vec3 | None = None
    options: dict[str, Any] | None = None
    goal_id: str | None = None


MAX_TIME_BUDGET_S = 30.0
"""Default cap of the service on one request [s] (``ServiceOptions.request_cap_s``): no plan
request or goal planning phase holds a worker longer, queue time included, and a planner
``time_budget_s`` above it is refused."""

_MUST_BE = re.compile(r" must be (.*?)(?:, got .*)?$")


def _check_options(data: dict[str, Any], cap_s: float = MAX_TIME_BUDGET_S) -> None:
    """Check ``options`` (planner options by name, :data:`~falcon_plan.planning.problem.OPTION_FIELDS`)
    field by field against ``PlanOptions`` (unknown names, types and ranges), naming the exact field (``options.<name>``) and what it allows, and refuse a
    ``time_budget_s`` over the service's cap."""
    options = data.get("options")
    if not options:
        return
    from falcon_plan.planning.problem import OPTION_FIELDS, PlanOptions

    known = sorted(OPTION_FIELDS)
    for name, value in options.items():
        if name not in known:
            raise RequestError("invalid_request", f"options.{name} is not a planner option", field=f"options.{name}",
                               allowed=known)
        try:
            PlanOptions.fast(**{name: value})
        except (FalconPlanError, TypeError, ValueError) as exc:
            match = _MUST_BE.search(str(exc))
            raise RequestError("invalid_problem", f"options.{name}: {exc}", field=f"options.{name}",
                               allowed=match.group(1) if match else str(exc)) from None
    budget = options.get("time_budget_s")
    if budget is not None and budget > cap_s:
        raise RequestError("invalid_problem", f"options.time_budget_s {budget} s is more than this service allows "
                           f"({cap_s:g} s)", field="options.time_budget_s", allowed=f"at most {cap_s:g} s")


def _check_points(data: dict[str, Any], names: tuple[str, ...]) -> None:
    """Raise ``outside_workspace`` naming the first point outside the workspace."""
    for name in names:
        if data.get(name) is None:
            continue
        try:
            require_in_workspace(np.asarray(data[name], dtype=float), what=name)
        except WorkspaceError as exc:
            raise RequestError("outside_workspace", str(exc), field=name,
                               allowed="a point inside the workspace (see the workspace limits in info)") from None


def parse_plan_request(payload: bytes | None, encoding: str | None = None, *,
                       check_workspace: bool = True, cap_s: float = MAX_TIME_BUDGET_S) -> PlanRequest:
    """Decode and check the plan request ``payload`` (its ``encoding`` must be JSON;
    schema ``plan_request``; a ``timeout_s`` or time budget above ``cap_s`` [s] is refused;
    points in the workspace
    unless ``check_workspace`` is False, for a caller that first looks in its plan cache,
    where only requests that passed the check can be, and calls :func:`check_plan_points`
    on a miss)."""
    data = decode_request(payload, "plan_request", encoding=encoding)
    assert data is not None
    _check_options(data, cap_s)
    if check_workspace:
        _check_points(data, ("start_m", "goal_m"))
    timeout = data.get("timeout_s")
    return PlanRequest(tuple(map(float, data["start_m"])), tuple(map(float, data["goal_m"])),
                       data.get("options"), data.get("request_id"), float(timeout) if timeout is not None else None)


def check_plan_points(request: PlanRequest) -> None:
    """Raise ``outside_workspace`` if the request's start or goal is outside the workspace."""
    _check_points({"start_m": request.start_m, "goal_m": request.goal_m}, ("start_m", "goal_m"))


def parse_goal_request(payload: bytes | None, encoding: str | None = None, *,
                       require_id: bool, cap_s: float = MAX_TIME_BUDGET_S) -> GoalRequest:
    """Decode and check the goal ``payload`` (its ``encoding`` must be JSON; schema
    ``goal_request``; a time budget above ``cap_s`` [s] is refused); ``require_id`` for puts,
    which have no reply to carry a generated id."""
    data = decode_request(payload, "goal_request", encoding=encoding)
    assert data is not None
    if require_id and "id" not in data:
        raise RequestError("invalid_request",
                           "a goal sent by put needs a client-chosen 'id' (there is no reply to carry one); "
                           "allowed: 1-64 letters, digits, '_', '.', '-'", field="id",
                           allowed="^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    _check_options(data, cap_s)
    _check_points(data, ("start_m", "goal_m"))
    start = data.get("start_m")
    return GoalRequest(tuple(map(float, data["goal_m"])), tuple(map(float, start)) if start else None,
                       data.get("options"), data.get("id"))


def payload_string(payload: bytes | None, name: str, max_chars: int) -> str | None:
    """Best-effort string field ``name`` of a JSON ``payload`` (None if the payload is not a
    JSON object, or the field is absent, not a string or longer than ``max_chars``), to name
    a refused request in its error report."""
    try:
        data = json.loads(payload or b"")
    except (ValueError, RecursionError):
        return None
    value = data.get(name) if isinstance(data, dict) else None
    return value if isinstance(value, str) and len(value) <= max_chars else None


def request_id_of(payload: bytes | None) -> str | None:
    """Best-effort ``request_id`` of a payload, to echo in an error reply (None if absent)."""
    return payload_string(payload, "request_id", 128)


def planning_error(exc: Exception) -> RequestError:
    """Translate the planner exception ``exc`` into the error reply the client gets."""
    if isinstance(exc, RequestError):
        return exc
    if isinstance(exc, WorkspaceError):
        return RequestError("outside_workspace", str(exc), allowed="points inside the workspace")
    if isinstance(exc, InvalidProblemError):
        return RequestError("invalid_problem", str(exc))
    if isinstance(exc, PlanningFailed):
        report = getattr(exc, "report", None)
        if report is not None and hasattr(report, "to_dict"):
            report = report.to_dict()
        return RequestError("planning_failed", str(exc), detail=report if isinstance(report, dict) else None)
    if isinstance(exc, FalconPlanError):
        return RequestError("invalid_problem", str(exc))
    log.exception("planner raised an unexpected error")
    return RequestError("internal_error", f"the planner failed unexpectedly: {type(exc).__name__}: {exc}")


@dataclass(frozen=True)
class PlanResult:
    """A plan ready to send: ``trajectory_json`` and ``report_json`` (encoded JSON, what the
    cache keeps), the planning time ``plan_s`` [s], whether it came ``cached``, plus the
    objects when freshly planned (a goal executes ``trajectory``; ``report`` is the plan
    report's body)."""

    trajectory_json: bytes
    report_json: bytes
    plan_s: float = 0.0
    cached: bool = False
    trajectory: Trajectory | None = None
    report: dict[str, Any] | None = None


class PlanCache:
    """A small thread-safe LRU cache of encoded plans keyed by :func:`plan_cache_key`.
    ``size`` 0 disables it. The planner is deterministic for a given request, so a repeat
    gets the same trajectory without planning again (and without encoding it again)."""

    def __init__(self, size: int = 64) -> None:
        if size < 0:
            raise ValueError(f"cache size must be >= 0, got {size}")
        self.size = size
        self._items: collections.OrderedDict[str, PlanResult] = collections.OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: str) -> PlanResult | None:
        """The cached plan for ``key`` (marked ``cached``), or None."""
        with self._lock:
            item = self._items.get(key)
            if item is not None:
                self._items.move_to_end(key)
            return item

    def put(self, key: str, result: PlanResult) -> None:
        """Remember the encoded plan ``result`` under ``key`` (:func:`plan_cache_key`),
        evicting the least recently used beyond ``size``."""
        if self.size == 0:
            return
        with self._lock:
            self._items[key] = PlanResult(result.trajectory_json, result.report_json, cached=True)
            self._items.move_to_end(key)
            while len(self._items) > self.size:
                self._items.popitem(last=False)


def plan_reply_bytes(request: PlanRequest, instance: str, result: PlanResult, *, queue_s: float,
                     service_s: float) -> bytes:
    """The encoded plan reply (schema ``plan_reply``) to ``request`` from ``instance``,
    assembled around the already encoded trajectory and report of ``result`` so a cached
    plan is never encoded twice; ``queue_s`` and ``service_s`` [s] are the timings it reports."""
    head: dict[str, Any] = {"schema_version": SCHEMA_VERSION, "instance": instance}
    if request.request_id is not None:
        head["request_id"] = request.request_id
    head["timing"] = {"plan_s": result.plan_s, "service_s": service_s, "queue_s": queue_s, "cached": result.cached}
    return b"".join((encode_json(head)[:-1], b',"trajectory":', result.trajectory_json,
                     b',"report":', result.report_json, b"}"))


def plan_cache_key(start_m: Vec3, goal_m: Vec3, options: dict[str, Any] | None) -> str:
    """Canonical text of what determines a plan: ``start_m``, ``goal_m`` [m] and ``options``
    (the request id does not)."""
    return json.dumps([list(start_m), list(goal_m), options or {}], sort_keys=True)


def run_planner(planner: Planner, request: PlanRequest | GoalRequest, start_m: Vec3,
                cache: PlanCache | None = None, budget_s: float | None = None) -> PlanResult:
    """Plan ``request`` from ``start_m`` [m] with ``planner`` (or take the plan from
    ``cache``) with at most ``budget_s`` [s] for the optimiser.
    Planner errors become RequestError."""
    key = plan_cache_key(start_m, request.goal_m, request.options)
    hit = cache.get(key) if cache is not None else None
    if hit is not None:
        return hit
    t0 = time.perf_counter()
    try:
        outcome = planner(start_m, request.goal_m, request.options, budget_s)
    except Exception as exc:  # noqa: BLE001 - every planner failure must become a reply
        raise planning_error(exc) from exc
    plan_s = time.perf_counter() - t0
    result = PlanResult(encode_json(outcome.trajectory.to_dict()), encode_json(outcome.report), plan_s, False,
                        outcome.trajectory, outcome.report)
    if cache is not None:
        cache.put(key, result)
    return result
