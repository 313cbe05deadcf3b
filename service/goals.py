"""Goals: a queue and one worker thread that plans and executes them, one at a time, in order.

A goal is accepted (queued, with its position) or rejected when it arrives; a goal that
arrives while another executes waits its turn. The queue holds at most ``queue_limit``
pending goals; past that, submissions are rejected with ``queue_full``. Statuses:
``pending`` (queued) -> ``running`` (planning, then executing) -> ``done`` | ``failed`` |
``cancelled``. Results of the last ``history`` goals stay queryable. No zenoh here: results
and progress go out through the ``publish(key, body)`` callable.
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
from service.codec import SCHEMA_VERSION, RequestError
from service.device import DeviceRunner
from falcon_plan.planning.problem import PlanProblem
from service.handlers import GoalRequest, Vec3
from service.keys import ServiceKeys

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


PENDING, RUNNING, DONE, FAILED, CANCELLED = GoalStatus
FINAL_STATUSES = (DONE, FAILED, CANCELLED)

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
    failed, and the ``cancel`` event that stops its planning and execution."""

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
    """

    def __init__(self, keys: ServiceKeys, runner: DeviceRunner | None, plan_goal: GoalPlanner, publish: Publish,
                 *, queue_limit: int = 16, history: int = 256, progress_rate_hz: float = 20.0,
                 idle_poll_hz: float = 50.0, recorder_for: RecorderFor | None = None) -> None:
        self.keys = keys
        self.runner = runner
        self.queue_limit = queue_limit
        self._plan_goal = plan_goal
        self._publish = publish
        self._history = history
        self._progress_period_s = 1.0 / progress_rate_hz
        self._idle_period_s = 1.0 / idle_poll_hz
        self._recorder_for = recorder_for
        self._cond = threading.Condition()
        self._queue: collections.deque[Goal] = collections.deque()
        self._goals: collections.OrderedDict[str, Goal] = collections.OrderedDict()
        self._running: Goal | None = None
        self._stopping = False
        self._thread: threading.Thread | None = None

    # --- lifetime ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the worker thread (only with a device)."""
        if self.runner is not None and self._thread is None:
            self._thread = threading.Thread(target=self._work, name=f"goals-{self.keys.instance}", daemon=True)
            self._thread.start()

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
            if len(self._queue) >= self.queue_limit:
                raise RequestError("queue_full", f"{len(self._queue)} goals are already waiting (the limit is "
                                   f"{self.queue_limit}); retry when one has finished",
                                   allowed=f"at most {self.queue_limit} pending goals")
            goal = Goal(goal_id, request, time.time())
            self._goals[goal_id] = goal
            self._queue.append(goal)
            position = self._position_locked(goal)
            self._trim_locked()
            self._cond.notify_all()
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
            if goal.status == PENDING:
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
                "error": goal.error}

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
                if recorder is not None:
                    recorder.goal_event(goal.goal_id, "finished", status, None if error is None else {"error": error})
                    recorder.close()
            with self._cond:
                self._finish_locked(goal, status, error)
                self._running = None
                self._trim_locked()
            log.info("goal %s %s", goal.goal_id, status)
            self._publish_result(goal)

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
            wanted = goal.request.start_m
            offset_m = float(np.linalg.norm(np.subtract(wanted, start))) if wanted is not None else 0.0
            if offset_m > START_TOLERANCE_M:
                raise RequestError(
                    "start_mismatch", f"start_m {list(wanted)} is {1e3 * offset_m:.1f} mm from the device's "
                    f"position {[round(v, 5) for v in start]}; omit start_m to start where the device is",
                    field="start_m",
                    allowed=f"within {1e3 * START_TOLERANCE_M:.0f} mm of the device's position, or absent")
            trajectory, report = self._plan_goal(goal.request.problem_from(start), goal.request.options,
                                                 goal.cancel)
            goal.plan_report = report
            if recorder is not None:
                recorder.goal_event(goal.goal_id, "planned", RUNNING, {"start_m": list(start)})
                recorder.plan(trajectory, report)
            if goal.cancel.is_set():
                return CANCELLED, None
            self._publish_progress(goal, "planning", 1.0)
            duration = float(getattr(trajectory, "duration_s", 0.0)) or 1.0
            t_exec = time.time()
            last = [0.0]

            def on_progress(detail: dict[str, Any]) -> None:
                now = time.time()
                if now - last[0] >= self._progress_period_s:
                    last[0] = now
                    total = detail.get("samples_total")
                    fraction = detail["samples_done"] / total if total else (now - t_exec) / duration
                    self._publish_progress(goal, "executing", fraction, detail)

            self._publish_progress(goal, "executing", 0.0)
            report, goal.run = self.runner.execute(trajectory, goal.cancel, on_progress, sink=recorder,
                                                   release=goal.request.release)
            goal.tracking_report = report
            outcome = report.get("status", "completed")
            if outcome == "cancelled" or goal.cancel.is_set():
                return CANCELLED, None
            if outcome != "completed":
                return FAILED, RequestError("device_error", f"execution ended with {outcome}: "
                                            f"{report.get('reason', '')}").to_dict()
            self._publish_progress(goal, "executing", 1.0)
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
