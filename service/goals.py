"""Goals: a queue and one worker thread that plans and executes them, one at a time, in order.

A goal is accepted (queued, with its position) or rejected when it arrives; a goal that
arrives while another executes waits its turn. The queue holds at most ``queue_limit``
pending goals; past that, submissions are rejected with ``queue_full``. Statuses:
``pending`` (queued) -> ``running`` (planning, then executing) -> ``done`` | ``failed`` |
``cancelled`` | ``preempted``. Results of the last ``history`` goals stay queryable. No zenoh
here: results and progress go out through the ``publish(key, body)`` callable.

Preemption (issue 24): a goal with ``preempt`` that arrives while another executes does not
wait. The running execution has a :class:`~falcon_plan.execution.splice.SpliceCoordinator`;
the new goal is planned off the control loop from the running motion's state a little ahead
(position and velocity, warm-started from the running plan) and spliced in at a tick after
the replan's measured latency, continuous in position and velocity. The running goal then
ends ``preempted`` (its result names the goal that replaced it) and the new one runs on in
the same execution, its progress on its own key; a later preemption splices again. A
preemption that cannot be spliced (the run is ending, or the replan missed its tick every
time) waits at the head of the queue. A ``preempt`` goal while the running one still plans
cancels that planning; with nothing running it goes to the head of the queue. A newer
preemption replaces every earlier one not begun yet (waiting for its splice or queued: it
ends ``preempted`` without running; one whose replan is under way ends with it, spliced in or
replaced), so a stream of preempting goals (a moving target) never runs an old one after a
newer. Why a new goal
and not an update key of the running one: every goal keeps one target and one result (what
was asked, what was done, how it ended), clients follow it on the keys they already know,
and a preempted goal's result still says how far it got.
"""
from __future__ import annotations

import collections
import logging
import threading
import time
import uuid
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from falcon_plan.errors import DeviceError, FalconPlanError, SafetyStop
from service.codec import SCHEMA_VERSION, RequestError, sanitise
from service.device import DeviceRunner
from falcon_plan.planning.problem import PlanProblem
from service.handlers import GoalRequest, Vec3
from service.keys import ServiceKeys
from falcon_plan.execution.executor import ExecutionStatus
from falcon_plan.execution.splice import LATE, REFUSED

if TYPE_CHECKING:
    from falcon_plan.recording.recorder import RunRecorder

log = logging.getLogger(__name__)

class GoalStatus(StrEnum):
    """Where a goal is (equal to its string value, which the schemas carry)."""

    PENDING = "pending"
    RUNNING = "running"
    DONE = "done"
    FAILED = "failed"
    CANCELLED = "cancelled"
    PREEMPTED = "preempted"


PENDING, RUNNING, DONE, FAILED, CANCELLED, PREEMPTED = GoalStatus
FINAL_STATUSES = (DONE, FAILED, CANCELLED, PREEMPTED)

REPLANNER_WAIT_S = 30.0
"""An execution waits this long at most for the replanning process to be ready (it starts with
the service and is warm in seconds, unless it compiles kernels on a first start) [s]."""
START_TOLERANCE_M = 0.005
"""A goal's optional ``start_m`` must be within this of the device's position [m]."""

GoalPlanner = Callable[[PlanProblem, "dict[str, Any] | None", threading.Event], tuple[Any, dict[str, Any]]]
"""``plan_goal(problem, options, cancel) -> (trajectory, plan report dict)``: plan the goal's
problem (started where the device is) with its options (PlanOptions fields); raises
RequestError, at once when ``cancel`` is set (the goal's cancel flag)."""
Publish = Callable[[str, dict[str, Any]], None]
RecorderFor = Callable[[str], "RunRecorder | None"]
"""``recorder_for(goal_id) -> RunRecorder | None``: the recorder of a goal (its MCAP recording,
the live view), or None when goals are not recorded."""


@dataclass
class Goal:
    """One goal and what became of it (mutated by the worker under the manager's lock):
    ``goal_id``, the ``request``, when it was ``submitted_at``, ``started_at`` and
    ``finished_at`` [s, monotonic], its ``status``, the ``start_m`` [m] it was planned from,
    its ``plan_report`` and ``tracking_report`` (JSON bodies), its ``run`` (the executed
    run's falcon log in short, :func:`service.device.run_record`), the ``error`` body if it
    failed, the ``cancel`` event that stops its planning and execution, the goal that
    ``preempted_by`` replaced it, and the ``splices`` of its execution."""

    goal_id: str
    request: GoalRequest
    submitted_at: float
    status: GoalStatus = PENDING
    started_at: float | None = None
    finished_at: float | None = None
    start_m: Vec3 | None = None
    plan_report: dict[str, Any] | None = None
    tracking_report: dict[str, Any] | None = None
    run: dict[str, Any] | None = None
    error: dict[str, Any] | None = None
    cancel: threading.Event = field(default_factory=threading.Event)
    preempted_by: str | None = None
    splices: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class _Execution:
    """The execution going now: its ``coordinator`` (splices new goals in), the goal it serves
    now (``current``), the ``waiting`` preempting goals not spliced yet, the ``splices``
    taken so far (the replanner's records) and its ``recorder`` (the first goal's; the goals
    spliced in are recorded there too: one run, one recording), or None."""

    coordinator: Any            # None until the run starts
    current: Goal
    waiting: dict[str, Goal] = field(default_factory=dict)
    splices: list[dict[str, Any]] = field(default_factory=list)
    recorder: Any = None


class GoalManager:
    """The goal queue of one instance and its worker thread.

    Parameters
    ----------
    keys : the instance's keys (for the acknowledgement and the publications).
    runner : the device; None for a planning-only instance (every goal is rejected).
    plan_goal : plans a goal from a start point.
    publish : sends a body on a key (progress and results).
    queue_limit : most pending goals; history : finished goals kept for queries.
    progress_rate_hz : most progress publications per second while executing.
    idle_poll_hz : how often an idle device is read (when its runner polls while idle).
    recorder_for : the recorder of each goal (its events, plan and rows; closed when the goal
        ends), or None.
    recorded_before : ``recorded_before(goal_id)``, where an earlier run of the service
        recorded a goal of that id (a path; the id is then refused), None if none; or None.
    """

    def __init__(self, keys: ServiceKeys, runner: DeviceRunner | None, plan_goal: GoalPlanner, publish: Publish,
                 *, queue_limit: int = 16, history: int = 256, progress_rate_hz: float = 50.0,
                 idle_poll_hz: float = 50.0, recorder_for: RecorderFor | None = None,
                 recorded_before: Callable[[str], str | None] | None = None) -> None:
        self.keys = keys
        self.runner = runner
        self.queue_limit = queue_limit
        self._plan_goal = plan_goal
        self._publish = publish
        self._history = history
        self._progress_period_s = 1.0 / progress_rate_hz
        self._idle_period_s = 1.0 / idle_poll_hz
        self._recorder_for = recorder_for
        self._recorded_before = recorded_before
        self._cond = threading.Condition()
        self._queue: collections.deque[Goal] = collections.deque()
        self._goals: collections.OrderedDict[str, Goal] = collections.OrderedDict()
        self._running: Goal | None = None
        self._execution: _Execution | None = None
        from falcon_plan.execution.splice import REPLAN_BUDGET_S, LatencyBudget

        self._replan_budget = LatencyBudget(REPLAN_BUDGET_S)  # measured over every execution's replans
        from falcon_plan.planning.replan_worker import ReplanWorker

        self._replanner: ReplanWorker | None = ReplanWorker()   # started with the worker thread
        self._replanner_starter: threading.Thread | None = None
        self._stopping = False
        self._thread: threading.Thread | None = None

    # --- lifetime ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the worker thread (only with a device)."""
        if self.runner is not None and self._thread is None:
            self._thread = threading.Thread(target=self._work, name=f"goals-{self.keys.instance}", daemon=True)
            self._thread.start()
            self._start_replanner_in_background()  # (now, not during an execution, where it would compete with the loop)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Cancel the running goal and every pending one, then join the worker (at most
        ``timeout_s`` [s])."""
        with self._cond:
            self._stopping = True
            pending = list(self._queue)
            self._queue.clear()
            for goal in pending:
                self._finish_locked(goal, CANCELLED, error=None)
            if self._running is not None:
                self._running.cancel.set()
            self._cond.notify_all()
        for goal in pending:
            self._publish_result(goal)
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("goal worker did not stop within %.1f s", timeout_s)
        if self._replanner is not None:
            self._replanner.close()

    # --- requests ---------------------------------------------------------------------------
    def submit(self, request: GoalRequest) -> dict[str, Any]:
        """Queue the goal ``request``; returns the acknowledgement body (schema ``goal_ack``)."""
        if self.runner is None:
            raise RequestError("no_device", f"instance {self.keys.instance!r} has no device (planning only); "
                               "send goals to an instance started with --device sim|emulated|usb",
                               allowed="an instance whose info says can_execute: true")
        with self._cond:
            if self._stopping:
                raise RequestError("overloaded", "the service is shutting down")
            goal_id = request.goal_id or f"g-{uuid.uuid4().hex[:12]}"
            if goal_id in self._goals:
                raise RequestError("duplicate_goal_id", f"goal id {goal_id!r} was already used on this instance; "
                                   "choose a new id", field="id", allowed="an id not used before")
            earlier = self._recorded_before(goal_id) if self._recorded_before is not None else None
            if earlier is not None:   # (a restarted service forgot the id; its recording would be replaced)
                raise RequestError("duplicate_goal_id", f"goal id {goal_id!r} was used before: its recording {earlier} "
                                   "exists; choose a new id", field="id", allowed="an id not recorded before")
            if len(self._queue) >= self.queue_limit and not request.preempt:   # (a preemption does not wait in it)
                raise RequestError("queue_full", f"{len(self._queue)} goals are already waiting (the limit is "
                                   f"{self.queue_limit}); retry when one has finished",
                                   allowed=f"at most {self.queue_limit} pending goals")
            goal = Goal(goal_id, request, time.time())
            self._goals[goal_id] = goal
            execution = self._execution
            splice = request.preempt and execution is not None and not execution.current.cancel.is_set()
            superseded: list[Goal] = []
            in_flight = None   # the preemption being planned: it ends when its replan does (_on_splice)
            if splice and execution.coordinator is not None:  # (else the coordinator asks for it when it starts)
                in_flight = execution.coordinator.request(goal)
            if request.preempt:
                # an earlier preemption not begun yet (waiting for its splice, or queued: given up by
                # the execution, or stranded when it ended) is replaced by this one: it never runs
                superseded = [g for g in self._queue if g.request.preempt]
                superseded += [g for g in execution.waiting.values() if g is not in_flight] if execution is not None else []
                for older in superseded:
                    if older in self._queue:
                        self._queue.remove(older)
                    older.preempted_by = goal_id
                    self._finish_locked(older, PREEMPTED, error=None)
            if splice:
                execution.waiting = {g.goal_id: g for g in (in_flight, goal) if g is goal or g in execution.waiting.values()}
            elif request.preempt:
                self._queue.appendleft(goal)
                if self._running is not None:  # still planning: stop that, this goal comes first
                    self._running.preempted_by = goal_id
                    self._running.cancel.set()
            else:
                self._queue.append(goal)
            position = 0 if splice else self._position_locked(goal)
            self._trim_locked()
            self._cond.notify_all()
        for older in superseded:
            self._publish_result(older)
        if splice and execution.coordinator is not None:
            log.info("goal %s preempts goal %s: replanning from its motion", goal_id, execution.current.goal_id)
        else:
            log.info("goal %s queued at position %d", goal_id, position)
        return {"schema_version": SCHEMA_VERSION, "id": goal_id, "instance": self.keys.instance,
                "status": PENDING, "position": position,
                "keys": {"progress": self.keys.goal_progress(goal_id), "result": self.keys.goal_result(goal_id),
                         "cancel": self.keys.goal_cancel(goal_id)}}

    def cancel(self, goal_id: str) -> dict[str, Any]:
        """Cancel the goal ``goal_id``: a pending one is dequeued at once; a running one is stopped where
        it is, its planning at once (``plan_goal`` watches the flag), its execution by the
        executor within one control period (its result follows on the result key). Body:
        schema ``cancel_reply``."""
        publish = False
        with self._cond:
            goal = self._require_locked(goal_id)
            cancelled = False
            waiting = self._execution.waiting if self._execution is not None else {}
            if goal.status == PENDING and goal_id in waiting:  # a preemption not spliced yet
                del waiting[goal_id]
                goal.cancel.set()
                self._finish_locked(goal, CANCELLED, error=None)
                cancelled = publish = True
            elif goal.status == PENDING:
                self._queue.remove(goal)
                self._finish_locked(goal, CANCELLED, error=None)
                cancelled = publish = True
            elif goal.status == RUNNING and not goal.cancel.is_set():
                goal.cancel.set()
                cancelled = True
            status = goal.status
        if publish:
            self._publish_result(goal)
        log.info("cancel of goal %s: cancelled=%s status=%s", goal_id, cancelled, status)
        return {"schema_version": SCHEMA_VERSION, "id": goal_id, "instance": self.keys.instance,
                "cancelled": cancelled, "status": status}

    def result(self, goal_id: str) -> dict[str, Any]:
        """The status of goal ``goal_id`` now (schema ``goal_result``)."""
        with self._cond:
            return self._result_locked(self._require_locked(goal_id))

    def known(self, goal_id: str) -> bool:
        """True if the goal ``goal_id`` is queued, running or among the kept results."""
        with self._cond:
            return goal_id in self._goals

    def goal_ids(self) -> list[str]:
        """Ids of the goals whose results are kept (oldest first)."""
        with self._cond:
            return list(self._goals)

    def activity(self) -> tuple[str | None, list[str]]:
        """(id of the running goal or None, ids of the pending goals in order)."""
        with self._cond:
            return (self._running.goal_id if self._running else None), [g.goal_id for g in self._queue]

    # --- helpers (call with the lock held) --------------------------------------------------
    def _require_locked(self, goal_id: str) -> Goal:
        goal = self._goals.get(goal_id)
        if goal is None:
            raise RequestError("unknown_goal", f"no goal {goal_id!r} on instance {self.keys.instance!r} "
                               f"(the last {self._history} goals are kept)", field="id")
        return goal

    def _position_locked(self, goal: Goal) -> int:
        if goal not in self._queue:  # a preemption waiting for its splice
            return 0
        return self._queue.index(goal) + (1 if self._running is not None else 0)

    def _trim_locked(self) -> None:
        finished = [gid for gid, g in self._goals.items() if g.status in FINAL_STATUSES]
        for gid in finished[:max(0, len(self._goals) - self._history)]:
            del self._goals[gid]

    def _finish_locked(self, goal: Goal, status: GoalStatus, error: dict[str, Any] | None) -> None:
        goal.status = status
        goal.error = error
        goal.finished_at = time.time()

    def _result_locked(self, goal: Goal) -> dict[str, Any]:
        return {"schema_version": SCHEMA_VERSION, "id": goal.goal_id, "instance": self.keys.instance,
                "status": goal.status,
                "position": self._position_locked(goal) if goal.status == PENDING else None,
                "submitted_at": goal.submitted_at, "started_at": goal.started_at,
                "finished_at": goal.finished_at, "goal_m": list(goal.request.goal_m),
                "start_m": list(goal.start_m) if goal.start_m is not None else None,
                "plan_report": goal.plan_report, "tracking_report": goal.tracking_report, "run": goal.run,
                "error": goal.error, "preempted_by": goal.preempted_by, "splices": list(goal.splices)}

    def _publish_result(self, goal: Goal) -> None:
        with self._cond:
            body = self._result_locked(goal)
        self._publish(self.keys.goal_result(goal.goal_id), body)

    def _publish_progress(self, goal: Goal, phase: str, fraction: float, detail: dict[str, Any] | None = None) -> None:
        body: dict[str, Any] = {"schema_version": SCHEMA_VERSION, "id": goal.goal_id, "instance": self.keys.instance,
                                "phase": phase, "fraction": min(1.0, max(0.0, fraction)),
                                "elapsed_s": time.time() - (goal.started_at or time.time())}
        if detail is not None:
            body["detail"] = detail
        self._publish(self.keys.goal_progress(goal.goal_id), body)

    # --- the worker ---------------------------------------------------------------------------
    def _next(self) -> Goal | None:
        """Wait for the next goal (reading an idle device meanwhile); None when stopping."""
        assert self.runner is not None
        while True:
            with self._cond:
                if self._stopping:
                    return None
                if self._queue:
                    goal = self._queue.popleft()
                    goal.status, goal.started_at = RUNNING, time.time()
                    self._running = goal
                    return goal
                self._cond.wait(self._idle_period_s if self.runner.poll_when_idle else None)
                if self._stopping or self._queue or not self.runner.poll_when_idle:
                    continue
            try:
                self.runner.poll()
            except (DeviceError, SafetyStop) as exc:
                log.warning("reading the idle device failed: %s", exc)
                time.sleep(self._idle_period_s)

    def _work(self) -> None:
        while (goal := self._next()) is not None:
            log.info("goal %s running", goal.goal_id)
            recorder = self._open_recorder(goal)
            status, error = FAILED, None
            try:
                status, error = self._run(goal, recorder)
            finally:
                with self._cond:  # the execution may have moved on to a goal that preempted this one
                    execution, self._execution = self._execution, None
                    last = execution.current if execution is not None else goal
                    stranded = list(execution.waiting.values()) if execution is not None else []
                    for waiting in reversed(stranded):  # never spliced in: first in the queue
                        self._queue.appendleft(waiting)
                if recorder is not None:
                    recorder.goal_event(last.goal_id, "finished", status, None if error is None else {"error": error})
                    recorder.close()
            with self._cond:
                if status == CANCELLED and last.preempted_by is not None:
                    status = PREEMPTED
                if last.status not in FINAL_STATUSES or status != DONE:
                    self._finish_locked(last, status, error)
                self._running = None
                self._trim_locked()
                self._cond.notify_all()
            log.info("goal %s %s", last.goal_id, status)
            self._publish_result(last)

    # --- preemption (the coordinator's thread) -------------------------------------------------
    def _coordinator(self, goal: Goal, trajectory: Any, report: dict[str, Any]) -> Callable[[Any], Any]:
        """``splices(executor)`` for the runner: the coordinator of ``goal``'s execution (its
        first plan ``trajectory`` with its plan ``report``), kept as :attr:`_execution`."""

        def make(executor: Any) -> Any:
            from falcon_plan.execution.splice import SpliceCoordinator
            from falcon_plan.planning.replan import Replan, moving_planner

            first = Replan.of_report(trajectory, goal.request.problem_from(goal.start_m or goal.request.goal_m), report)

            remote = self._remote_planner(executor.model)   # warm before the run starts (else the first replan is late)

            def plan(start: Any, new: Goal) -> Any:
                if new.cancel.is_set():
                    raise RequestError("cancelled", f"goal {new.goal_id} was cancelled before its splice")
                problem = new.request.problem
                goal = {"position_m": problem.goal_m, "velocity_m_s": problem.goal_velocity_m_s}
                if remote is not None:
                    return remote(start, goal, new.request.options)
                from falcon_plan.planning.problem import PlanOptions

                return moving_planner(PlanOptions.fast(**(new.request.options or {})), executor.model)(start, goal)

            coordinator = SpliceCoordinator(executor, plan, first, on_splice=self._on_splice, budget=self._replan_budget)
            with self._cond:
                execution = self._execution
                execution.coordinator = coordinator
                early = list(execution.waiting.values())
            for waiting in early:  # preemptions that came while the run was being set up
                coordinator.request(waiting)
            return coordinator.slot

        return make

    def _on_splice(self, outcome: dict[str, Any]) -> None:
        """A splice of the running execution was taken (the goal it serves changes) or given up."""
        log.info("splice towards goal %s: %s", outcome.get("goal"),
                 "taken" if outcome.get("taken") else f"not taken ({outcome.get('reason')})")
        with self._cond:
            execution = self._execution
            if execution is None:
                return
            recorder, coordinator = execution.recorder, execution.coordinator
            new = self._goals.get(outcome.get("goal"))
            if new is None or new is execution.current:
                return
            if outcome.get("taken"):
                execution.waiting.pop(new.goal_id, None)
                old = execution.current
                execution.splices.append(outcome)
                old.splices = list(execution.splices)
                if old.status not in FINAL_STATUSES:
                    old.preempted_by = new.goal_id
                    self._finish_locked(old, PREEMPTED, error=None)
                if new.status not in FINAL_STATUSES:
                    new.status = RUNNING
                new.started_at, new.start_m = time.time(), old.start_m
                new.cancel = old.cancel            # the execution's cancel: a cancel of the new goal stops it
                new.splices = list(execution.splices)
                execution.current = self._running = new
            elif outcome.get("reason") in (LATE, REFUSED) or new.goal_id not in execution.waiting:
                return   # tried again (or no longer waiting)
            else:
                del execution.waiting[new.goal_id]
                newer = [g for g in execution.waiting.values() if g.status == PENDING]
                if newer:   # replaced by a newer preemption (its replan follows), or given up with one waiting
                    new.preempted_by = newer[-1].goal_id
                    self._finish_locked(new, PREEMPTED, error=None)
                else:       # given up: wait at the head of the queue
                    self._queue.appendleft(new)
                old = None
        if new.status == PREEMPTED:
            self._publish_result(new)
        if outcome.get("taken"):
            log.info("goal %s preempted by goal %s at tick %s", old.goal_id, new.goal_id, outcome.get("tick"))
            self._publish_result(old)
            self._publish_progress(new, "executing", 0.0, {"plan": {"goal_id": new.goal_id, "splices": len(new.splices)}})
            if recorder is not None and coordinator is not None:
                _record_splice(recorder, old, new, outcome, coordinator.plan)

    def _remote_planner(self, model: Any) -> Any:
        """The replanning process's planner with ``model`` (:meth:`ReplanWorker.planner`), once
        the process is ready (at most :data:`REPLANNER_WAIT_S`); None when it cannot be had:
        this execution's replans are made here."""
        replanner = self._replanner
        if replanner is None:
            return None
        if not replanner.wait_ready(0.0):   # (it died since: started again)
            self._start_replanner_in_background()
        deadline = time.monotonic() + REPLANNER_WAIT_S
        while not replanner.wait_ready(0.05):
            if self._replanner is not replanner:   # its start failed (said so)
                return None
            if time.monotonic() > deadline:
                log.warning("the replanning process is not ready after %.0f s (a first start compiles kernels): "
                            "this execution replans in the service's process", REPLANNER_WAIT_S)
                return None
        try:
            return replanner.planner(model)
        except FalconPlanError:
            log.warning("the replanning process failed; replanning in the service's process", exc_info=True)
            return None

    def _start_replanner_in_background(self) -> None:
        """:meth:`_start_replanner` in a thread of its own, unless one runs."""
        if self._replanner_starter is None or not self._replanner_starter.is_alive():
            self._replanner_starter = threading.Thread(target=self._start_replanner, daemon=True,
                                                       name=f"replanner-start-{self.keys.instance}")
            self._replanner_starter.start()

    def _start_replanner(self) -> None:
        """Start the replanning process (it warms up: seconds); should it fail, preemptions
        are replanned in this process (more slowly: the control loop holds the interpreter)."""
        try:
            assert self._replanner is not None
            self._replanner.start()
        except Exception:  # noqa: BLE001 - preemptions still work, slower
            if not self._stopping:   # (stop() ends a start under way)
                log.warning("the replanning process did not start; replanning in the service's process",
                            exc_info=True)
            self._replanner = None

    def _open_recorder(self, goal: Goal) -> RunRecorder | None:
        """The goal's recorder (None when goals are not recorded, or when it cannot be opened:
        the goal runs unrecorded, with a warning)."""
        if self._recorder_for is None:
            return None
        try:
            recorder = self._recorder_for(goal.goal_id)
        except FalconPlanError as exc:
            log.warning("goal %s is not recorded: %s", goal.goal_id, exc)
            return None
        if recorder is not None:
            recorder.goal_event(goal.goal_id, "started", RUNNING,
                                {"goal_m": list(goal.request.goal_m), "submitted_at": goal.submitted_at,
                                 "started_at": goal.started_at})
        return recorder

    def _run(self, goal: Goal, recorder: RunRecorder | None = None) -> tuple[GoalStatus, dict[str, Any] | None]:
        """Plan and execute one goal, its events, plan and rows going to ``recorder`` (a
        RunRecorder or None); returns (final status, error dict or None)."""
        assert self.runner is not None
        try:
            self._publish_progress(goal, "planning", 0.0)
            self.runner.ensure_homed()
            start = self.runner.position_m()
            goal.start_m = start
            self.runner.require_start(start)
            wanted = goal.request.start_m
            offset_m = float(np.linalg.norm(np.subtract(wanted, start))) if wanted is not None else 0.0
            if offset_m > START_TOLERANCE_M:
                raise RequestError(
                    "start_mismatch", f"start_m {list(wanted)} is {1e3 * offset_m:.1f} mm from the device's "
                    f"position {[round(v, 5) for v in start]}; omit start_m to start where the device is",
                    field="start_m",
                    allowed=f"within {1e3 * START_TOLERANCE_M:.0f} mm of the device's position, or absent")
            trajectory, plan_report = self._plan_goal(goal.request.problem_from(start), goal.request.options,
                                                      goal.cancel)
            goal.plan_report = plan_report
            if recorder is not None:
                recorder.goal_event(goal.goal_id, "planned", RUNNING, {"start_m": list(start)})
                recorder.plan(trajectory, plan_report)
            if goal.cancel.is_set():
                return CANCELLED, None
            self._publish_progress(goal, "planning", 1.0)
            duration = float(getattr(trajectory, "duration_s", 0.0)) or 1.0
            t_exec = time.time()
            last = [0.0]

            def on_progress(detail: dict[str, Any]) -> None:
                now = time.time()
                if now - last[0] >= 0.75 * self._progress_period_s:  # the executor calls at the period: allow its jitter
                    last[0] = now
                    total = detail.get("samples_total")
                    fraction = detail["samples_done"] / total if total else (now - t_exec) / duration
                    current = self._execution.current if self._execution is not None else goal
                    detail["plan"] = {"goal_id": current.goal_id, "splices": len(current.splices)}
                    self._publish_progress(current, "executing", fraction, detail)

            with self._cond:  # from now on a preemption is spliced in (its coordinator starts with the run)
                self._execution = _Execution(None, goal, recorder=recorder)
            self._publish_progress(goal, "executing", 0.0)
            report, run = self.runner.execute(trajectory, goal.cancel, on_progress, sink=recorder,
                                              release=goal.request.release, progress_period_s=self._progress_period_s,
                                              splices=self._coordinator(goal, trajectory, plan_report))
            with self._cond:
                execution = self._execution
                last = execution.current if execution is not None else goal
            if execution is not None and execution.coordinator is not None:
                execution.coordinator.close()
                with self._cond:
                    last.splices = _splice_records(report.get("splices", []), execution.splices)
            last.run, last.tracking_report = run, report
            outcome = ExecutionStatus(report.get("status", ExecutionStatus.COMPLETED))
            if outcome == ExecutionStatus.CANCELLED or last.cancel.is_set():
                return CANCELLED, None
            if outcome != ExecutionStatus.COMPLETED:
                return FAILED, RequestError("device_error", f"execution ended with {outcome}: "
                                            f"{report.get('reason', '')}").to_dict()
            self._publish_progress(last, "executing", 1.0)
            return DONE, None
        except RequestError as exc:
            return (CANCELLED, None) if goal.cancel.is_set() else (FAILED, exc.to_dict())
        except FalconPlanError as exc:
            code = "device_error" if isinstance(exc, (DeviceError, SafetyStop)) else "internal_error"
            log.warning("goal %s failed: %s", goal.goal_id, exc)
            return FAILED, RequestError(code, f"{type(exc).__name__}: {exc}").to_dict()
        except Exception as exc:  # noqa: BLE001 - the worker must survive any goal
            log.exception("goal %s failed unexpectedly", goal.goal_id)
            return FAILED, RequestError("internal_error", f"{type(exc).__name__}: {exc}").to_dict()


def _record_splice(recorder: RunRecorder, old: Goal, new: Goal, outcome: dict[str, Any], replan: Any) -> None:
    """Goal ``new`` spliced into the running execution in place of goal ``old``, recorded in
    the execution's ``recorder``: ``old`` finished (preempted), ``new`` started and planned, and
    its plan (``replan``, the coordinator's Replan: the trajectory from the splice on) with the
    splice's record ``outcome`` (tick, budget and latency [ms]) as its report."""
    tick = outcome.get("tick")
    recorder.goal_event(old.goal_id, "finished", PREEMPTED, {"preempted_by": new.goal_id, "spliced_at_tick": tick})
    recorder.goal_event(new.goal_id, "started", RUNNING,
                        {"goal_m": list(new.request.goal_m), "submitted_at": new.submitted_at,
                         "started_at": new.started_at, "spliced_into": old.goal_id, "spliced_at_tick": tick})
    recorder.goal_event(new.goal_id, "planned", RUNNING, {"start_m": [float(x) for x in replan.problem.start_m],
                                                          "start_velocity_m_s": [float(x) for x in
                                                                                 replan.problem.start_velocity_m_s]})
    report = {"goal_id": new.goal_id, "method": replan.method, "splice_s": replan.splice_s,
              "duration_s": replan.duration_s, "worst_command_ratio": replan.worst_command_ratio,
              "solve_time_s": replan.solve_time_s, "notes": list(replan.notes),
              **{k: outcome.get(k) for k in ("tick", "attempt", "budget_ms", "latency_ms", "position_jump_counts",
                                             "velocity_jump_counts_s", "command_jump")}}
    recorder.plan(replan.trajectory, sanitise(report))


def _splice_records(loop: list[dict[str, Any]], replanner: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every splice of an execution: the loop's records (``loop``, the report's: tick, source,
    taken, the jumps) with the replanner's (``replanner``: goal id, attempt, budget and latency)
    of the same tick merged in."""
    made = {r["tick"]: r for r in replanner if r.get("taken")}
    return [{**made.get(r["tick"], {}), **r} for r in loop]
