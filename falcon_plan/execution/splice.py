"""Work for a running run done off its control loop, taken at a tick chosen after its measured
latency (issue 24): the minimum-time brake that takes over from the loop's quick brake, and
new plans made while the run goes (:class:`SpliceCoordinator`).

Every such job runs in a worker thread and hands a :class:`~falcon_plan.execution.schedule.SpliceOffer`
to the run's :class:`~falcon_plan.execution.schedule.SpliceSlot` for a command tick chosen
when the job starts: the loop's current tick plus the job's latency budget
(:class:`LatencyBudget`, from the latencies measured so far) plus the command delay. The loop
takes an offer only at its own tick; one that is ready after it is refused and the run keeps
its reference (the coordinator then tries again with the budget it measured), so the
reference never jumps.
"""
from __future__ import annotations

import itertools
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import InvalidParameterError
from falcon_plan.execution.schedule import SpliceOffer, SpliceSlot, held
from falcon_plan.timing import responsive_gil

if TYPE_CHECKING:
    from falcon_plan.execution.braking import Brake, StopStart
    from falcon_plan.execution.executor import Executor
    from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)

BUDGET_QUANTILE = 90.0
"""The budget covers this percentile of the latencies measured so far (the measured latency at
or below it: of a few, one slow replan is left out, as the top tenth of many is; a late plan is
retried with a budget covering it anyway, while a budget set by one slow first replan, 0.3 s
among 25-50 ms ones on the moving-target demo, scheduled the next splices 0.35-0.54 s ahead
and the device fell 30 mm behind the target)..."""
BUDGET_FACTOR = 1.5
"""...times this factor..."""
BUDGET_FLOOR_S = 0.005
"""...and never less than this [s]."""
BRAKE_BUDGET_S = 0.03
"""The minimum-time brake's first budget [s] (before any was measured)."""
STOP_BUDGET_S = 0.012
"""The first budget of the rest of the quick brake after a cancel [s] (before any was measured):
quick_brake alone takes about a millisecond, but a worker beside a paced loop on a busy machine
took 5-15 ms (bench_brake); the first commands cover twice this at 800 Hz, room for a retry."""
REPLAN_BUDGET_S = 0.15
"""A replan's first budget [s] (before any was measured)."""
PREPARE_BUDGET_S = 0.03
"""Preparing a splice of a plan made already (:meth:`Executor.prepare_splice_at`): its first budget [s]."""
MAX_POSITION_JUMP_COUNTS = 0.01
MAX_VELOCITY_JUMP_COUNTS_S = 1.0
"""A new plan whose start differs from the running reference by more than these (position
[counts], leg rate [counts/s]) is never offered: the run never jumps."""
RUN_START_WAIT_S = 5.0
"""A request made before the coordinator's run started waits this long for it [s]."""
MAX_TRIES = 3
"""A new plan that misses its tick this many times is given up (the run keeps its plan); a late
plan from rest may be offered again as many times more."""
LATE, REFUSED, REPLACED = "ready after its tick", "refused at its tick", "replaced by a newer goal"
"""Reasons of a record not taken: the first two are tried again (a later record says how the
request ended), the last ends it (a newer request is planned instead)."""


class LatencyBudget:
    """How long a kind of off-loop job takes, from its measured latencies [s]: the
    :data:`BUDGET_QUANTILE` percentile of the last ``window`` times :data:`BUDGET_FACTOR`,
    at least :data:`BUDGET_FLOOR_S`; ``first_s`` until one was measured. Thread-safe."""

    def __init__(self, first_s: float, window: int = 50) -> None:
        self.first_s = float(first_s)
        self._seen: deque[float] = deque(maxlen=window)
        self._lock = threading.Lock()

    def record(self, latency_s: float) -> None:
        """Add a measured latency ``latency_s`` [s]."""
        with self._lock:
            self._seen.append(float(latency_s))

    def budget_s(self) -> float:
        """The budget for the next job [s]."""
        with self._lock:
            if not self._seen:
                return self.first_s
            return max(BUDGET_FLOOR_S, BUDGET_FACTOR * float(np.percentile(np.array(self._seen), BUDGET_QUANTILE,
                                                                           method="lower")))

    def to_dict(self) -> dict[str, Any]:
        """The budget and the latencies behind it [ms]."""
        with self._lock:
            seen = list(self._seen)
        return {"budget_ms": 1e3 * self.budget_s(), "measured": len(seen),
                "p50_ms": 1e3 * float(np.median(seen)) if seen else None,
                "max_ms": 1e3 * max(seen) if seen else None}


def _guarded(name: str, job: Callable[[], None]) -> None:
    """Run ``job`` (called ``name``), its exceptions logged, never raised into the loop, the GIL
    handed back to the loop often while it runs (:class:`responsive_gil`)."""
    try:
        with responsive_gil():
            job()
    except Exception:  # a worker's failure leaves the run on its reference
        log.exception("%s failed; the run keeps its reference", name)


def start_worker(name: str, job: Callable[[], None]) -> threading.Thread:
    """Run ``job`` in a new daemon thread called ``name`` (as :func:`_guarded`)."""
    thread = threading.Thread(target=_guarded, args=(name, job), name=name, daemon=True)
    thread.start()
    return thread


class JobThread:
    """A thread started before its jobs are needed (a run's, for the stop after a cancel), so
    that handing one over costs the loop a few microseconds (starting a thread costs it a
    hundred or more), called ``name``: :meth:`submit` queues a job (run in order, as
    :func:`_guarded`), :meth:`close` ends the thread after the queued ones."""

    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue[tuple[str, Callable[[], None]] | None] = queue.SimpleQueue()
        threading.Thread(target=self._serve, name=name, daemon=True).start()

    def submit(self, name: str, job: Callable[[], None]) -> None:
        """Queue ``job`` (called ``name`` in the log)."""
        self._jobs.put((name, job))

    def close(self) -> None:
        self._jobs.put(None)

    def _serve(self) -> None:
        while (item := self._jobs.get()) is not None:
            _guarded(*item)


def _submit(run: Any, name: str, job: Callable[[], None]) -> None:
    """``job`` on the run's :class:`JobThread` (``run.jobs``), else in a thread of its own."""
    if run.jobs is not None:
        run.jobs.submit(name, job)
    else:
        start_worker(name, job)


def refine_brake(executor: Executor, brake: Brake, slot: SpliceSlot, budget: LatencyBudget) -> None:
    """Off the loop of ``executor``'s running run: the minimum-time brake
    (:func:`~falcon_plan.execution.braking.plan_brake`) from the quick ``brake``'s state at a tick after ``budget``, with the stop's designed
    gains (:meth:`~falcon_plan.control.Controller.splice_tail`), offered to ``slot``. The two
    brakes lie on one line, so the hand-over is continuous in position and velocity."""
    from falcon_plan.execution.braking import plan_brake

    run = executor.running_run()
    c, rate = executor.controller, executor.rate_hz
    law = run.law
    start = time.perf_counter()
    tick = max(brake.tick, run.k_now) + int(math.ceil(budget.budget_s() * rate)) + 1
    hold = brake.ref_counts.shape[0] - (tick - brake.tick)

    def job() -> None:
        try:
            make()
        finally:
            slot.expect(None)

    def make() -> None:
        j = tick - brake.tick
        if j >= brake.ref_counts.shape[0] - 1:
            return
        refined = plan_brake(brake.ref_counts, brake.position_m, brake.velocity_m_s, j, executor.model,
                             c.feedforward_effects, rate, c.feedforward_lead_samples, max(hold, 1))
        if refined is None:
            return
        tail = c.splice_tail(law, tick, refined.ref_counts, refined.feedforward, executor.model)
        spent = time.perf_counter() - start
        budget.record(spent)
        slot.offer(SpliceOffer(tick, refined.ref_counts, refined.position_m, refined.velocity_m_s, tail,
                               (refined.position_jump_counts, refined.velocity_jump_counts_s, refined.command_jump),
                               f"min-time brake ({refined.deceleration_m_s2:.1f} m/s^2)", spent))

    slot.expect(tick)
    _submit(run, "the min-time brake", job)


def stop_offer(executor: Executor, plan: Any, tick: int, start: StopStart | None, at: int) -> SpliceOffer | None:
    """The rest of the stop of ``executor``'s running run cancelled at command ``tick`` of the
    schedule ``plan`` (what it followed then: its ``ref_counts``, ``position_m``, ``velocity_m_s``), from
    command ``at`` on (:func:`~falcon_plan.execution.braking.continue_brake`, about a millisecond):
    continuing ``start`` (the table's first commands from ``tick``, which the loop follows), or
    the running plan when None (then None when no brake within the bound keeps to the
    workspace: the plan ends the motion). The offer carries the whole stop
    (:attr:`SpliceOffer.brake`) and the controller's :meth:`~falcon_plan.control.Controller.quick_tail`."""
    from falcon_plan.execution.braking import STOP_HOLD_S, continue_brake, joined_stop

    t0 = time.perf_counter()
    run = executor.running_run()
    c, rate, model = executor.controller, executor.rate_hz, executor.model
    s, effects, lead_samples = plan, c.feedforward_effects, c.feedforward_lead_samples
    hold = int(round(max(executor.settle_s, STOP_HOLD_S) * rate))
    if start is None:
        rest = whole = continue_brake(s.ref_counts, s.position_m, s.velocity_m_s, at, model, effects, rate,
                                      lead_samples, hold)
    else:
        rest = continue_brake(start.ref_counts, start.position_m, start.velocity_m_s, at - tick, model, effects,
                              rate, lead_samples, hold, must_stop=True)
        whole = None if rest is None else joined_stop(s.ref_counts, s.position_m, s.velocity_m_s, tick, start, rest,
                                                      model, effects, rate, lead_samples)
    if rest is None:
        log.warning("cancel at tick %d: no brake within the bound stays in the workspace; %s", tick,
                    "the plan ends the motion" if start is None else "the first commands go on")
        return None
    tail = c.quick_tail(run.law, at, rest.ref_counts, rest.feedforward, model)
    return SpliceOffer(at, rest.ref_counts, rest.position_m, rest.velocity_m_s, tail,
                       (rest.position_jump_counts, rest.velocity_jump_counts_s, rest.command_jump),
                       f"quick brake ({rest.deceleration_m_s2:.1f} m/s^2)", time.perf_counter() - t0, brake=whole)


def warm_stop(executor: Executor, schedule: Any) -> None:
    """The rest of a stop computed once for ``executor``, as :func:`stop_offer` would, from the
    middle of ``schedule``'s stop table (nothing offered): the first one in a process took 5-10 ms more
    (first calls), enough for the worker to miss all the first commands; the run's
    :class:`JobThread` does it when the run starts."""
    from falcon_plan.execution.braking import STOP_HOLD_S, continue_brake, joined_stop

    table = schedule.first_brake
    if table is None or not len(table.ticks):
        return
    tick = table.ticks.start + len(table.ticks) // 2
    start = table.row(tick)
    c, rate, model = executor.controller, executor.rate_hz, executor.model
    hold = int(round(max(executor.settle_s, STOP_HOLD_S) * rate))
    if start is not None:
        rest = continue_brake(start.ref_counts, start.position_m, start.velocity_m_s, start.exact // 2, model,
                              c.feedforward_effects, rate, c.feedforward_lead_samples, hold, must_stop=True)
        if rest is not None:
            joined_stop(schedule.ref_counts, schedule.position_m, schedule.velocity_m_s, tick, start, rest, model,
                        c.feedforward_effects, rate, c.feedforward_lead_samples)


def finish_stop(executor: Executor, plan: Any, tick: int, start: StopStart | None, slot: SpliceSlot,
                budget: LatencyBudget) -> None:
    """Off the loop of ``executor``'s running run, cancelled at command ``tick`` of the schedule
    ``plan`` (as :func:`stop_offer`): the rest of the stop (:func:`stop_offer`), offered to ``slot`` for a tick after ``budget`` (its measured
    latency, from this call to the offer). The loop meanwhile follows ``start``, the table's first
    commands from ``tick`` (:meth:`~falcon_plan.execution.braking.FirstCommands.row`; None: the
    running plan, no row was within), and the offer continues them (same line, continuous in
    position and velocity) before its exact commands run out; an offer ready after its tick is
    refused and made again for a later one while they last (a paced run). The loop takes the
    offer and then starts :func:`refine_brake`."""
    run = executor.running_run()
    rate = executor.rate_hz
    last = None if start is None else tick + start.exact - 1     # the last exact command followed
    begun = time.perf_counter()

    def choose(now: int) -> int | None:
        at = now + int(math.ceil(budget.budget_s() * rate)) + 1
        if last is not None:
            at = min(at, last)
        return at if at > now or now == tick else None

    def job() -> None:
        try:
            make(first, begun)
        finally:
            slot.expect(None)

    def make(at: int | None, since: float) -> None:
        while at is not None and executor.running_run() is run:
            offer = stop_offer(executor, plan, tick, start, at)
            if offer is None:
                return
            budget.record(time.perf_counter() - since)
            if executor.offer_and_wait(slot, offer) or not executor.pace:
                return
            since = time.perf_counter()
            at = choose(run.k_now)                        # late: again for a later tick while they last
            if at is not None:
                slot.expect(at)
        if executor.running_run() is run:
            log.warning("cancel at tick %d: the rest of the stop was not ready within its first commands", tick)

    first = choose(tick)
    slot.expect(first)
    _submit(run, "the rest of the stop", job)


@dataclass(frozen=True)
class MovingStart:
    """Where a new plan must start: the running reference's state at the splice.

    Attributes
    ----------
    tick : the splice's command tick in the run (the commands change there; the new plan's
        motion starts one command delay later).
    position_m, velocity_m_s : (3,) the running reference's point [m] and velocity [m/s] where
        the new plan starts.
    plan_s : that instant in the running plan's time [s] (its t = 0 the plan's start; beyond
        its length: the plan ended and holds its goal).
    plan : the running plan as the coordinator was given it (for a warm start).
    """

    tick: int
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    plan_s: float
    plan: Any


Planner = Callable[[MovingStart, Any], tuple["Trajectory", Any]]
"""``planner(start, goal) -> (trajectory, plan)``: a plan from ``start`` (its t = 0 at the
splice) to ``goal`` (whatever the caller's goals are), and what the next splice's
:attr:`MovingStart.plan` is (e.g. a :class:`falcon_plan.planning.replan.Replan`)."""


class SpliceCoordinator:
    """Replans a running run towards new goals, off its control loop.

    :meth:`request` (any thread) asks for a new goal; a worker thread (one at a time; a newer
    request replaces a pending one) takes the loop's current tick, chooses the splice tick
    after the replan's measured :class:`LatencyBudget` (``budget``; default: first
    :data:`REPLAN_BUDGET_S`), plans from the running reference's
    state there with ``planner`` and prepares the splice
    (:meth:`~falcon_plan.execution.executor.Executor.prepare_splice_at`: the reference, the
    feed-forward and the LQR's gains from that tick). A replan that is ready after its tick
    is refused by the loop: the run keeps its plan and the coordinator tries again, its budget
    at once covering the latency it just measured, up to :data:`MAX_TRIES` times; a newer
    request then takes its place, except when the late plan starts where the running reference
    rests (its plan ended and holds its goal): that plan fits any later tick as well, so it is
    offered again after the time preparing a splice takes (``prepare_budget``) instead of being
    thrown away. For the same reason a plan from where the reference rests is offered, in a
    paced run, at the first tick after its preparation rather than at the tick its budget chose.
    ``on_splice(record)`` is called
    for every splice taken or given up (the run's report lists them all).

    A run that is not paced (a simulation stepped as fast as it goes) waits for the worker, so
    that its time does not run on while a replan is made; whether a replan was in time is then
    judged by its measured latency in ticks (or by ``simulated_latency_s`` [s] when given: a
    simulation of a machine where every replan takes that long).

    Use: ``coordinator = SpliceCoordinator(executor, planner, first_plan)``, then
    ``executor.run(trajectory, splices=coordinator.slot)`` in one thread and
    ``coordinator.request(goal)`` from others; :meth:`close` after the run.
    """

    def __init__(self, executor: Executor, planner: Planner, plan: Any, *,
                 budget: LatencyBudget | None = None,
                 on_splice: Callable[[dict[str, Any]], None] | None = None,
                 simulated_latency_s: float | None = None) -> None:
        self.executor = executor
        self.planner = planner
        self.slot = SpliceSlot(pending_after_take=True)   # _serve ends every job with expect()
        self.budget = budget or LatencyBudget(REPLAN_BUDGET_S)
        self.prepare_budget = LatencyBudget(PREPARE_BUDGET_S)
        """How long preparing a splice of a plan made already takes (a late plan offered again)."""
        self._missed_s = 0.0    # a budget covering the last replan that came late [s] (0 after a splice)
        self._missed_prepare_s = 0.0    # the same for a late plan offered again [s]
        self._lock = threading.Condition()
        self._pending: Any = None
        self._has_pending = False
        self._closed = False
        self._plan = plan                       # the plan the run follows (or will, once taken)
        self._plan_tick: int | None = None      # its t = 0's tick (None: the run's own start)
        self.outcomes: list[dict[str, Any]] = []
        """What became of every request: taken (its tick, budget and latency [ms]) or not, and why."""
        self.on_splice = on_splice
        self.simulated_latency_s = simulated_latency_s
        self._worker = threading.Thread(target=self._serve, name="falcon-plan replanner", daemon=True)
        self._worker.start()

    # --- any thread ----------------------------------------------------------------------------
    def request(self, goal: Any) -> Any:
        """Plan towards ``goal`` as soon as the worker is free (replacing a request not yet
        begun); returns the goal being planned now (None when idle): it ends with a record
        taken, given up, or :data:`REPLACED` (by this one)."""
        with self._lock:
            self._pending, self._has_pending = goal, True
            if not self._busy:
                self.slot.expect(self.slot.PENDING)
            self._lock.notify()
            return self._planning if self._busy else None

    def idle(self) -> bool:
        """No request pending or being planned."""
        with self._lock:
            return not self._has_pending and not self._busy

    def close(self) -> None:
        """Stop the worker (after its current job)."""
        with self._lock:
            self._closed = True
            self._lock.notify()
        self._worker.join(timeout=10.0)

    @property
    def plan(self) -> Any:
        """The plan the run follows now (the first one, or the last splice's)."""
        with self._lock:
            return self._plan

    # --- the worker ------------------------------------------------------------------------------
    _busy = False
    _planning: Any = None   # the goal being planned (while _busy)
    _now = 0            # the worker's idea of the loop's tick (see _replan)

    def _serve(self) -> None:
        while True:
            with self._lock:
                while not self._has_pending and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                goal, self._has_pending, self._busy = self._pending, False, True
                self._planning = goal
            try:
                with responsive_gil():
                    self._replan(goal)
            except Exception as exc:  # the run keeps its plan
                log.exception("replan towards %r failed", goal)
                self._record({"goal": _jsonable(goal), "taken": False, "reason": f"{type(exc).__name__}: {exc}"})
            finally:
                with self._lock:
                    self._busy = False
                    self.slot.expect(self.slot.PENDING if self._has_pending else None)

    def _replan(self, goal: Any) -> None:
        ex = self.executor
        started = time.monotonic()
        while ex.running_run() is None and not self._closed and time.monotonic() - started < RUN_START_WAIT_S:
            time.sleep(1e-3)  # a request made while the run is being set up: wait for its first tick
        made: tuple[MovingStart, Any, Any] | None = None   # a plan that came late: (its start, trajectory, plan)
        tries = {False: 0, True: 0}     # replans made, and late plans offered again
        for attempt in itertools.count(1):
            # a late plan from where the running reference rests can be offered again, later
            reuse = made is not None and not made[0].velocity_m_s.any()
            with self._lock:  # a newer goal: plan towards that one instead (unless this one's plan can be used)
                replaced = self._has_pending and not reuse
                if self._closed:
                    return
            if replaced:
                self._record({"goal": _jsonable(goal), "taken": False, "reason": REPLACED})
                return
            t0 = time.perf_counter()
            budget = self._prepare_budget_s() if reuse else self._replan_budget_s()
            try:
                start = self._start_after(budget)
                if reuse and not _same_rest(made[0], start):
                    reuse = False
                    with self._lock:
                        replaced = self._has_pending
                    if replaced:
                        self._record({"goal": _jsonable(goal), "taken": False, "reason": REPLACED})
                        return
                    budget = self._replan_budget_s()
                    start = self._start_after(budget)
            except InvalidParameterError as exc:   # the run is ending: nothing to splice into
                self._record({"goal": _jsonable(goal), "taken": False, "reason": str(exc)})
                return
            tries[reuse] += 1
            if tries[reuse] > MAX_TRIES:
                break
            self.slot.expect(start.tick)
            trajectory, plan = (made[1], made[2]) if reuse else self.planner(start, goal)
            if ex.pace and not reuse and not start.velocity_m_s.any():
                # from where the reference rests: the earliest tick after the preparation that finds it there
                try:
                    sooner = self._start_after(self._prepare_budget_s())
                except InvalidParameterError:
                    sooner = start
                if sooner.tick < start.tick and _same_rest(start, sooner):
                    start, budget = sooner, time.perf_counter() - t0 + self._prepare_budget_s()
                    self.slot.expect(start.tick)
            t_prepare = time.perf_counter()
            offer = ex.prepare_splice_at(trajectory, start.tick + ex.command_lead())
            self.prepare_budget.record(time.perf_counter() - t_prepare)
            latency = time.perf_counter() - t0
            charged = latency if ex.pace or self.simulated_latency_s is None or reuse else self.simulated_latency_s
            if not reuse:
                self.budget.record(charged)
            run = ex.running_run()
            if run is None:
                return
            about = {"goal": _jsonable(goal), "attempt": attempt, "tick": offer.tick, "budget_ms": 1e3 * budget,
                     "latency_ms": 1e3 * latency, "method": getattr(plan, "method", None), "reused": reuse,
                     "plan_ms": 1e3 * float(getattr(plan, "solve_time_s", math.nan)),
                     "position_jump_counts": offer.jumps[0], "velocity_jump_counts_s": offer.jumps[1],
                     "command_jump": offer.jumps[2]}
            # the tick the offer arrived at: the loop's, or in a run that is not paced (which
            # waited for it) the tick its latency would have reached
            arrived = run.k_now if ex.pace else self._now + int(math.ceil(charged * ex.rate_hz))
            about["arrived_tick"] = arrived
            if offer.jumps[0] > MAX_POSITION_JUMP_COUNTS or offer.jumps[1] > MAX_VELOCITY_JUMP_COUNTS_S:
                self.slot.expect(None)              # a plan that does not continue the run: never offered
                self._record({**about, "taken": False, "reason": "not continuous with the running reference"})
                return
            if arrived > offer.tick:              # too late: keep the running plan, try again
                self._now = arrived
                if reuse:   # the next budget covers this one's latency at once
                    self._missed_prepare_s = max(self._missed_prepare_s, BUDGET_FACTOR * latency)
                else:
                    self._missed_s = max(self._missed_s, BUDGET_FACTOR * charged)
                made = (start, trajectory, plan)
                self.slot.expect(self.slot.PENDING)
                self._record({**about, "taken": False, "reason": LATE})
                continue
            if ex.offer_and_wait(self.slot, offer):
                with self._lock:
                    self._plan, self._plan_tick = plan, offer.tick + ex.command_lead()
                self._missed_s = self._missed_prepare_s = 0.0
                self._record({**about, "taken": True})
                return
            made = (start, trajectory, plan)
            self._record({**about, "taken": False, "reason": REFUSED})
        log.warning("replan towards %r missed its tick %d times; the run keeps its plan", goal, attempt - 1)
        self._record({"goal": _jsonable(goal), "taken": False, "reason": f"missed its tick {attempt - 1} times"})

    def _record(self, outcome: dict[str, Any]) -> None:
        self.outcomes.append(outcome)
        if self.on_splice is not None:
            self.on_splice(outcome)

    def _prepare_budget_s(self) -> float:
        """Preparing a splice of a plan made already: its budget [s], at least what covers the
        last one that came late."""
        return max(self.prepare_budget.budget_s(), self._missed_prepare_s)

    def _replan_budget_s(self) -> float:
        """A replan's budget [s]: the measured one, at least what covers the last late replan."""
        return max(self.budget.budget_s(), self._missed_s)

    def _start_after(self, budget_s: float) -> MovingStart:
        """The running reference's state at the first splice after ``budget_s`` [s]."""
        ex = self.executor
        run = ex.running_run()
        if run is None:
            raise InvalidParameterError("no run is going")
        lead = ex.command_lead()
        self._now = max(run.k_now, self._now) if not ex.pace else run.k_now
        tick = self._now + int(math.ceil(max(budget_s, 0.0) * ex.rate_hz)) + 1
        k_s = tick + lead

        last = run.hold_end() - 2
        if k_s > last and ex.pace and last > run.n_planned:
            k_s = last    # the run rests there: a plan from that rest is offered once made (_replan), whenever it is
        elif k_s > last:
            raise InvalidParameterError(f"a splice {budget_s * 1e3:.1f} ms from now is past the running run")
        s = held(run.s, k_s + 1)          # past its end the run holds its last point, at rest
        plan_tick = ex.plan_start_tick() if self._plan_tick is None else self._plan_tick
        k_s = max(k_s, plan_tick)
        with self._lock:
            plan = self._plan
        return MovingStart(k_s - lead, s.position_m[k_s].copy(), s.velocity_m_s[k_s].copy(),
                           (k_s - plan_tick) / ex.rate_hz, plan)


def _same_rest(a: MovingStart, b: MovingStart) -> bool:
    """Both starts are the running reference at rest at one point (it ended and holds its
    goal): a plan made from one starts from the other as well."""
    return (not a.velocity_m_s.any() and not b.velocity_m_s.any()
            and bool(np.array_equal(a.position_m, b.position_m)))


def _jsonable(goal: Any) -> Any:
    if hasattr(goal, "goal_id"):
        return goal.goal_id
    try:
        return [float(x) for x in np.asarray(goal, dtype=float).reshape(-1)]
    except (TypeError, ValueError):
        return repr(goal)


__all__ = ["LatencyBudget", "MovingStart", "Planner", "SpliceCoordinator", "JobThread", "finish_stop", "refine_brake",
           "stop_offer", "start_worker", "warm_stop", "LATE", "REFUSED", "REPLACED",
           "BRAKE_BUDGET_S", "STOP_BUDGET_S", "REPLAN_BUDGET_S", "MAX_TRIES"]
