"""Pure request handling: payload bytes in, reply body out (no zenoh here).

The service plans through a :data:`Planner` callable, so the machinery can be exercised with
any planner; :func:`falcon_planner` is the real one (``falcon_plan.planning.api.plan_problem``).
Plan and goal requests carry the planner's own problem type,
:class:`~falcon_plan.planning.problem.PlanProblem` (start, goal and via points, end
velocities, payload), as flat fields of their JSON body (:data:`PROBLEM_FIELDS`).
Every refusal is a :class:`~service.codec.RequestError` with a code, a message saying what is
wrong and what is allowed, and the offending field.
"""
from __future__ import annotations

import collections
import dataclasses
import json
import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

from falcon_plan.errors import FalconPlanError, InvalidProblemError, PlanningFailed, WorkspaceError
from falcon_plan.planning.problem import PlanProblem
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


Planner = Callable[[PlanProblem, "dict[str, Any] | None", "float | None"], PlanOutcome]
"""``planner(problem, options, budget_s) -> PlanOutcome``: plan the :class:`PlanProblem`
``problem`` with ``options`` (PlanOptions fields by name, None: the planner's defaults);
``budget_s`` [s], when not None, caps the optimiser's time budget (the service passes the time
left before the request's deadline). Raises InvalidProblemError, WorkspaceError or
PlanningFailed for problems it refuses or cannot solve."""

PlannerFactory = Callable[["FalconModel | None"], Planner]
"""Builds a planner from a model (None: the nominal model); for planning processes it must be
a module-level function (such as :func:`falcon_planner`), which each process imports by name
to build its own."""


def falcon_planner(model: FalconModel | None = None, *, fast_by_default: bool = True) -> Planner:
    """The real planner for ``model`` (None: nominal): ``falcon_plan.planning.api.plan_problem``
    with options built from the request's ``options`` object on top of
    ``PlanOptions.fast(warm_start="neighbours")`` (no cross-checks, no refinement, no plant
    run, warm starts from solved neighbours: the service's latency path; a request may set
    ``warm_start: "none"``) unless ``fast_by_default`` is False. A fallback plan for a problem
    with via points is refused (``PlanningFailed``): the ruckig fallback does not pass through
    them. Imports lazily so the service machinery loads without the planner."""
    from falcon_plan.planning.api import plan_problem
    from falcon_plan.planning.problem import PlanOptions
    from falcon_plan.planning.report import PlanStatus

    base = (PlanOptions.fast(warm_start="neighbours") if fast_by_default else PlanOptions()).to_dict()

    def planner(problem: PlanProblem, options: dict[str, Any] | None, budget_s: float | None = None) -> PlanOutcome:
        opts = PlanOptions.from_dict({**base, **(options or {})})
        if budget_s is not None and budget_s < opts.solver.time_budget_s:
            opts = opts.replace(time_budget_s=max(budget_s, 1e-3))
        result = plan_problem(problem, opts, model)
        if problem.via_m and result.report.status == PlanStatus.FALLBACK:
            raise PlanningFailed(f"no plan through the via points: {result.report.fallback_reason}, and the "
                                 "fallback (ruckig) does not pass through via points; allow more time_budget_s "
                                 "or fewer via points", result.report)
        report = result.report.to_dict()
        return PlanOutcome(result.trajectory, report)

    return planner


# --- requests --------------------------------------------------------------------------------
PROBLEM_FIELDS = ("start_m", "goal_m", "via_m", "start_velocity_m_s", "goal_velocity_m_s", "payload_kg")
"""The fields of a plan or goal request that make its :class:`PlanProblem` (the wire format
is flat: they sit beside ``options``, ``request_id``, ``timeout_s`` or ``id``)."""


@dataclass(frozen=True)
class PlanRequest:
    """A validated plan request: the ``problem`` to plan with ``options`` (PlanOptions fields
    by name), tagged ``request_id``; ``timeout_s``: how long the requester waits."""

    problem: PlanProblem
    options: dict[str, Any] | None = None
    request_id: str | None = None
    timeout_s: float | None = None
    """How long the requester waits [s] from sending (None: it did not say)."""


@dataclass(frozen=True)
class GoalRequest:
    """A validated goal: the motion ``problem`` with ``options`` (PlanOptions fields), named
    ``goal_id`` (None: the service names it). The goal is planned from where the device is
    when its turn comes (:meth:`problem_from`); ``start_given`` says whether the request
    named a start (then ``problem.start_m``, which must be within a few mm of the device),
    else ``problem.start_m`` is only a stand-in (the goal point) and the start is at rest;
    ``release`` says what a cancel in motion does: brake and hold (False) or zero force at
    once (True); ``preempt`` that it replaces the running goal in motion (spliced in) instead
    of waiting its turn."""

    problem: PlanProblem
    start_given: bool = True
    options: dict[str, Any] | None = None
    goal_id: str | None = None
    release: bool = False
    preempt: bool = False

    @property
    def goal_m(self) -> Vec3:
        """The goal point [m]."""
        return self.problem.goal_m

    @property
    def start_m(self) -> Vec3 | None:
        """The start point the request named [m], or None ("from where the device is")."""
        return self.problem.start_m if self.start_given else None

    def problem_from(self, position_m: Vec3) -> PlanProblem:
        """The problem to plan when the device is at ``position_m`` [m]: this one, starting there."""
        return dataclasses.replace(self.problem, start_m=position_m)


MAX_TIME_BUDGET_S = 30.0
"""Default cap of the service on one request [s] (``ServiceOptions.request_cap_s``): no plan
request or goal planning phase holds a worker longer, queue time included, and a planner
``time_budget_s`` above it is refused."""

def _allowed(exc: Exception) -> Any:
    """What ``exc`` says is allowed (an :class:`~falcon_plan.errors.InputError`'s ``allowed``),
    else its message."""
    allowed = getattr(exc, "allowed", None)
    return allowed if allowed is not None else str(exc)


def _check_options(data: dict[str, Any], cap_s: float = MAX_TIME_BUDGET_S) -> None:
    """Check ``options`` (planner options by name, :data:`~falcon_plan.planning.problem.OPTION_FIELDS`)
    field by field against ``PlanOptions`` (unknown names, types and ranges), naming the exact field (``options.<name>``) and what it allows, and refuse a
    ``time_budget_s`` over the service's cap."""
    options = data.get("options")
    if not options:
        return
    from falcon_plan.planning.problem import OPTION_FIELDS, PlanOptions

    known = sorted(OPTION_FIELDS)
    for name in options:
        if name not in known:
            raise RequestError("invalid_request", f"options.{name} is not a planner option", field=f"options.{name}",
                               allowed=known)
    try:  # one construction checks them all; the refusal names its field
        PlanOptions.fast(**options)
    except (FalconPlanError, TypeError, ValueError) as exc:
        name = getattr(exc, "field", None) or next(iter(options))
        raise RequestError("invalid_problem", f"options.{name}: {exc}", field=f"options.{name}",
                           allowed=_allowed(exc)) from None
    budget = options.get("time_budget_s")
    if budget is not None and budget > cap_s:
        raise RequestError("invalid_problem", f"options.time_budget_s {budget} s is more than this service allows "
                           f"({cap_s:g} s)", field="options.time_budget_s", allowed=f"at most {cap_s:g} s")


def _problem(data: dict[str, Any], start_m: Any) -> PlanProblem:
    """The :class:`PlanProblem` of the request fields ``data`` starting at ``start_m`` [m]; its
    refusals (beyond the schema's, e.g. an end speed above what is plannable) become
    ``invalid_problem`` naming the field."""
    fields = {name: data[name] for name in PROBLEM_FIELDS if name in data}
    try:
        return PlanProblem(**{**fields, "start_m": start_m})
    except InvalidProblemError as exc:
        name = exc.field if exc.field is not None and exc.field.split("[")[0] in PROBLEM_FIELDS else None
        raise RequestError("invalid_problem", str(exc), field=name, allowed=_allowed(exc)) from None


def require_in_workspace(problem: PlanProblem, model: FalconModel, *, skip_start: bool = False) -> None:
    """Raise ``outside_workspace`` naming the request field (``start_m``, ``via_m[i]``,
    ``goal_m``) of the first point of ``problem`` outside ``model``'s workspace (the model
    the service plans with); ``skip_start``: the start is the device's position, not asked for.
    The service's one workspace check of a request, made when it arrives."""
    from falcon_plan.model.workspace import require_in_workspace as require_point_in_workspace

    names = ["start_m", *[f"via_m[{i}]" for i in range(len(problem.via_m))], "goal_m"]
    for name, point in list(zip(names, problem.waypoints_m))[1 if skip_start else 0:]:
        try:
            require_point_in_workspace(point, model.params, model.limits, what=name)
        except WorkspaceError as exc:
            raise RequestError("outside_workspace", str(exc), field=name,
                               allowed="a point inside the workspace (see the workspace limits in info)") from None


def parse_plan_request(payload: bytes | None, encoding: str | None = None, *,
                       cap_s: float = MAX_TIME_BUDGET_S) -> PlanRequest:
    """Decode and check the plan request ``payload`` (its ``encoding`` must be JSON; schema
    ``plan_request``; a ``timeout_s`` or time budget above ``cap_s`` [s] is refused). The
    workspace is not checked here: a caller looks in its plan cache first (only requests that
    passed the check can be there) and calls :func:`require_in_workspace` on a miss."""
    data = decode_request(payload, "plan_request", encoding=encoding)
    assert data is not None
    _check_options(data, cap_s)
    timeout = data.get("timeout_s")
    return PlanRequest(_problem(data, data["start_m"]), data.get("options"), data.get("request_id"),
                       float(timeout) if timeout is not None else None)


def parse_goal_request(payload: bytes | None, encoding: str | None = None, *,
                       require_id: bool, cap_s: float = MAX_TIME_BUDGET_S) -> GoalRequest:
    """Decode and check the goal ``payload`` (its ``encoding`` must be JSON; schema
    ``goal_request``; a time budget above ``cap_s`` [s] is refused); ``require_id`` for puts,
    which have no reply to carry a generated id. Without ``start_m`` the goal starts at rest
    where the device is, so a ``start_velocity_m_s`` then is refused."""
    data = decode_request(payload, "goal_request", encoding=encoding)
    assert data is not None
    if require_id and "id" not in data:
        raise RequestError("invalid_request",
                           "a goal sent by put needs a client-chosen 'id' (there is no reply to carry one); "
                           "allowed: 1-64 letters, digits, '_', '.', '-'", field="id",
                           allowed="^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
    start_given = "start_m" in data
    if not start_given and "start_velocity_m_s" in data:
        raise RequestError("invalid_request", "start_velocity_m_s needs start_m: a goal without start_m starts "
                           "at rest where the device is; give start_m or leave out start_velocity_m_s",
                           field="start_velocity_m_s", allowed="absent when start_m is absent")
    _check_options(data, cap_s)
    problem = _problem(data, data["start_m"] if start_given else data["goal_m"])
    return GoalRequest(problem, start_given, data.get("options"), data.get("id"), bool(data.get("release", False)),
                       bool(data.get("preempt", False)))


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
    """A plan ready to send, in its one encoding: ``trajectory_json`` and ``report_json``
    (JSON: what a planning process sends back over its socket, what the cache keeps and what
    the reply carries), the planning time ``plan_s`` [s], whether it came ``cached``.
    :attr:`trajectory` and :attr:`report` are the objects (a goal executes the trajectory):
    the planner's own when it ran in this process (``made``), else decoded from the JSON on
    first use."""

    trajectory_json: bytes
    report_json: bytes
    plan_s: float = 0.0
    cached: bool = False
    made: PlanOutcome | None = dataclasses.field(default=None, repr=False, compare=False)

    @property
    def trajectory(self) -> Trajectory:
        """The plan's trajectory."""
        return self._objects().trajectory

    @property
    def report(self) -> dict[str, Any]:
        """The plan report's body."""
        return self._objects().report

    def _objects(self) -> PlanOutcome:
        if self.made is None:
            from falcon_plan.trajectory import Trajectory

            decoded = PlanOutcome(Trajectory.from_dict(json.loads(self.trajectory_json)), json.loads(self.report_json))
            object.__setattr__(self, "made", decoded)   # a cache of what the fields say
        assert self.made is not None
        return self.made


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


def plan_cache_key(problem: PlanProblem, options: dict[str, Any] | None) -> str:
    """Canonical text of what determines a plan: the whole ``problem`` and ``options`` (the
    request id does not)."""
    return json.dumps([problem.to_dict(), options or {}], sort_keys=True)


def run_planner(planner: Planner, problem: PlanProblem, options: dict[str, Any] | None,
                cache: PlanCache | None = None, budget_s: float | None = None) -> PlanResult:
    """Plan ``problem`` with ``options`` with ``planner`` (or take the plan from ``cache``)
    with at most ``budget_s`` [s] for the optimiser. Planner errors become RequestError."""
    key = plan_cache_key(problem, options)
    hit = cache.get(key) if cache is not None else None
    if hit is not None:
        return hit
    t0 = time.perf_counter()
    try:
        outcome = planner(problem, options, budget_s)
    except Exception as exc:  # noqa: BLE001 - every planner failure must become a reply
        raise planning_error(exc) from exc
    plan_s = time.perf_counter() - t0
    result = PlanResult(encode_json(outcome.trajectory.to_dict()), encode_json(outcome.report), plan_s, False,
                        outcome)
    if cache is not None:
        cache.put(key, result)
    return result
