"""Planning workers of one instance: a bounded queue of plan jobs, ``workers`` slots that run
them, and a watchdog that holds every job to its deadline and its cancel flag.

Every job carries a deadline (monotonic clock [s]) set when its request arrived: the service's
cap (``ServiceOptions.request_cap_s``) or the requester's own wait (``timeout_s``), whichever
ends first, so queue time counts. A job whose deadline passed, or whose cancel flag was set,
while it waited is dropped before it starts (its reply, if anyone still listens, says why).
A running job gets the time left as the optimiser's budget; should the rest of the planning
run past the deadline, or the job be cancelled (a goal cancelled while planning), the
watchdog answers at once (``deadline_exceeded`` / ``cancelled``) and, with process workers,
kills the worker process and starts a fresh one, so the slot is free again without waiting
for the planner.

Workers are processes by default: the CasADi/IPOPT solve holds the interpreter lock and each
compiled NLP is solved under its own lock, so threads cannot plan in parallel (two threads
gave 1.29x the plans per second of one, two processes 1.98x, on a quiet 2-core machine; see
``benchmarks/bench_load.py --pool``). Each process (``python -m service.workers``, talking over a socket
pair) builds its own planner from a factory named by its import path
(:func:`service.handlers.falcon_planner`) and sends each plan back in its one encoding, the
JSON the reply carries (:class:`~service.handlers.PlanResult`). Thread workers run a planner callable in this
process (for planners that cannot be pickled); there a cancelled or late job is answered
on time too, but the planner runs on to its own end before the slot is free.
"""
from __future__ import annotations

import collections
import importlib
import logging
import os
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

from falcon_plan.childproc import child_ignores_sigint, spawn_module
from falcon_plan.errors import InvalidParameterError
from service.codec import RequestError
from falcon_plan.planning.problem import PlanProblem
from service.handlers import PlanCache, Planner, PlannerFactory, PlanResult, plan_cache_key, run_planner

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel

log = logging.getLogger(__name__)

WATCH_PERIOD_S = 0.02
"""How often the watchdog looks at deadlines and cancel flags [s]."""

WORKER_START_TIMEOUT_S = 1800.0
"""Longest a planning process may take to start [s]: a bound for a process that hangs, not
the expected time. The first start on a machine compiles the planner's kernels (minutes on 2
cores, see :mod:`falcon_plan.compiled.build`); the pool waits for a process that is alive and
says, every :data:`WORKER_START_NOTICE_S`, that it is still starting."""

WORKER_START_NOTICE_S = 15.0
"""While a planning process starts, say that it is still starting this often [s]."""

Outcome = PlanResult | RequestError


@dataclass(eq=False)
class PlanJob:
    """One plan to make: for a plan request (``finish`` replies) or a goal (``finish`` wakes it).

    ``problem`` is planned with ``options`` (PlanOptions fields by name); ``deadline``, ``arrived`` and ``started``
    (None until a worker takes it) are on ``time.monotonic()``; ``finish(job, outcome)`` is
    called exactly once, from whichever thread ends the job first (worker, watchdog, or the
    pool closing); setting ``cancel`` ends it at once; ``use_cache``: store the fresh plan in
    the pool's cache."""

    problem: PlanProblem
    options: dict[str, Any] | None
    deadline: float
    finish: Callable[["PlanJob", Outcome], None]
    cancel: threading.Event = field(default_factory=threading.Event)
    use_cache: bool = True
    arrived: float = field(default_factory=time.monotonic)
    started: float | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, init=False)
    _ended: bool = field(default=False, init=False)

    def end(self, outcome: Outcome) -> bool:
        """Deliver ``outcome`` unless the job already ended; True if this call ended it."""
        with self._lock:
            if self._ended:
                return False
            self._ended = True
        try:
            self.finish(self, outcome)
        except Exception:  # noqa: BLE001 - a requester gone or a closed session
            log.warning("finishing a plan job failed", exc_info=True)
        return True

    def stop_reason(self, now: float, started: bool) -> RequestError | None:
        """Why the job must stop at ``now`` [s, monotonic] (cancelled or past its deadline;
        ``started``: whether a worker has it), or None."""
        if self.cancel.is_set():
            return RequestError("cancelled", "cancelled " + ("while planning" if started else "before planning began"))
        if now >= self.deadline:
            waited = now - self.arrived
            return RequestError("deadline_exceeded",
                                f"no plan within the request's deadline ({waited:.2f} s after it arrived, "
                                + ("while planning" if started else "still queued, so it was not planned")
                                + "); ask for a smaller problem, a smaller time_budget_s, or allow more time "
                                "(timeout_s, at most the service's cap)",
                                allowed="a plan that fits in min(timeout_s, the service's request_cap_s)")
        return None


def factory_path(factory: PlannerFactory) -> str:
    """``module:name`` of a module-level factory (what a planning process imports)."""
    path = f"{factory.__module__}:{factory.__qualname__}"
    if "<" in path or "." in factory.__qualname__:
        raise InvalidParameterError(f"planning processes need a module-level planner factory, got {path}")
    return path


def _load_factory(path: str) -> PlannerFactory:
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def load_model(model_path: Path | None) -> FalconModel | None:
    """The model a planner is built with: the model file ``model_path``'s, or None (the
    nominal model)."""
    if model_path is None:
        return None
    from falcon_plan.model.modelfile import read_model_file

    return read_model_file(model_path).model


def model_summary(model_path: Path | None) -> dict[str, Any]:
    """What ``info`` reports as a service's model: the summary of the model file
    ``model_path``, or the nominal one."""
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.modelfile import ModelFile, read_model_file

    if model_path is None:
        return ModelFile(FalconModel(), {"source": "nominal"}).summary()
    return read_model_file(model_path).summary()


def _child_main(conn: Connection, factory: PlannerFactory, model_path: Path | None = None) -> None:
    """A planning process: build the planner (with the model file's model, if any), warm it
    up, then plan what the socket brings."""
    child_ignores_sigint()
    planner = factory(load_model(model_path))
    try:  # build the NLPs now so the first request is as fast as the next
        planner(PlanProblem((0.0, 0.0, 0.12), (0.01, 0.005, 0.125)), None, None)
    except Exception:  # noqa: BLE001 - warming up is best effort
        log.debug("planner warm-up failed", exc_info=True)
    conn.send("ready")
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):  # the service has gone
            return
        problem, options, budget_s = message  # as sent by PlanningPool._run_in_process
        try:
            result = run_planner(planner, PlanProblem.from_dict(problem), options, None, budget_s)
            # the plan in its one encoding, JSON (the service decodes the objects if it needs them)
            conn.send(("ok", (result.trajectory_json, result.report_json, result.plan_s)))
        except RequestError as exc:
            conn.send(("error", (exc.code, str(exc), exc.field, exc.allowed, exc.detail)))
        except Exception as exc:  # noqa: BLE001 - the process must survive any request
            log.exception("planning failed unexpectedly")
            conn.send(("error", ("internal_error", f"{type(exc).__name__}: {exc}", None, None, None)))


class _Slot:
    """One worker: a thread here, plus (process mode) its planning process and pipe."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.job: PlanJob | None = None
        self.process: Any = None
        self.conn: Any = None
        self.killed = False
        """Set when :meth:`kill` ended the process: the kill may land after the process answered
        its job (the watchdog and the slot's thread race at a deadline or a cancel), so the next
        job must not be sent to it even if ``poll()`` does not see it dead yet."""
        self.lock = threading.Lock()

    def alive(self) -> bool:
        """True while the planning process runs."""
        return self.process is not None and self.process.poll() is None

    def needs_restart(self) -> bool:
        """True when the planning process was killed or has ended: a new one must start before
        the next job is sent."""
        with self.lock:
            return self.killed or not self.alive()

    def set_job(self, job: PlanJob | None) -> None:
        """Mark the job this slot runs (None: idle)."""
        with self.lock:
            self.job = job

    def kill(self, job: PlanJob | None = None) -> None:
        """End the planning process now (the slot's thread starts a new one); with ``job``,
        only while the slot still runs that job."""
        with self.lock:
            if job is not None and self.job is not job:
                return
            if self.alive():
                self.process.kill()
                self.killed = True


class PlanningPool:
    """Plan jobs on ``workers`` processes (or threads), each job within its deadline.

    Parameters
    ----------
    workers : number of slots.
    factory : builds the planner (in each process, or once here for threads).
    processes : True for worker processes, False for threads in this process.
    max_pending : jobs allowed to wait; past that :meth:`submit` raises ``overloaded``.
    cache : where fresh plans of jobs with ``use_cache`` are stored (the service looks
        there when a request arrives).
    name : for thread and log names.
    model_path : a model file every planner is built with (None: nominal).
    """

    def __init__(self, workers: int, factory: PlannerFactory, *, processes: bool = True, max_pending: int = 64,
                 cache: PlanCache | None = None, name: str = "plan", model_path: Path | None = None) -> None:
        self.workers = workers
        self.processes = processes
        self.max_pending = max_pending
        self.cache = cache
        self.name = name
        self._factory = factory
        self._model_path = model_path
        self._planner: Planner | None = None
        self._cond = threading.Condition()
        self._queue: collections.deque[PlanJob] = collections.deque()
        self._slots = [_Slot(f"{name}-{i}") for i in range(workers)]
        self._threads: list[threading.Thread] = []
        self._closing = False
        self.stats = collections.Counter({"planned": 0, "dropped": 0, "cancelled": 0, "deadline_exceeded": 0,
                                          "restarts": 0})

    def _count(self, name: str) -> None:
        with self._cond:
            self.stats[name] += 1

    # --- lifetime ---------------------------------------------------------------------------
    def start(self) -> None:
        """Start the workers (process mode: start all processes and wait until they are ready)."""
        if self.processes:
            for slot in self._slots:
                self._launch(slot)
            for slot in self._slots:
                self._await_ready(slot)
        else:
            self._planner = self._factory(load_model(self._model_path))
        for slot in self._slots:
            self._spawn_thread(self._work, slot)
        self._spawn_thread(self._watch, None)

    def _spawn_thread(self, target: Any, slot: _Slot | None) -> None:
        thread = threading.Thread(target=target, args=(slot,) if slot else (), daemon=True,
                                  name=slot.name if slot else f"{self.name}-watchdog")
        thread.start()
        self._threads.append(thread)

    def _launch(self, slot: _Slot) -> None:
        process, conn = spawn_module("service.workers", factory_path(self._factory),
                                     *([] if self._model_path is None else [str(self._model_path)]))
        with slot.lock:
            slot.process, slot.conn, slot.killed = process, conn, False
            if self._closing:   # close() ran while this one started: it may not have seen it
                process.kill()

    def _await_ready(self, slot: _Slot) -> None:
        """Wait until ``slot``'s process says it is ready: as long as it lives (a first start
        compiles kernels), at most :data:`WORKER_START_TIMEOUT_S`."""
        started = time.monotonic()
        while not slot.conn.poll(WORKER_START_NOTICE_S):
            waited = time.monotonic() - started
            if not slot.alive() or waited > WORKER_START_TIMEOUT_S:
                break
            log.warning("planning process %s is still starting after %.0f s (its first start on this machine "
                        "compiles the planner's kernels, once; `python3 dev.py setup` builds them ahead)",
                        slot.name, waited)
        else:
            try:
                if slot.conn.recv() == "ready":
                    return
            except (EOFError, OSError):  # it died before it was ready
                pass
        try:  # (its socket closes a moment before it can be reaped)
            code = slot.process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            code = None
        raise RuntimeError(f"planning process {slot.name} did not start"
                           + (f" (it exited with status {code})" if code is not None else ""))

    def close(self) -> None:
        """End every waiting and running job with an ``overloaded`` reply (shutting down),
        stop the processes and threads; idempotent."""
        with self._cond:
            if self._closing:
                return
            self._closing = True
            waiting = list(self._queue)
            self._queue.clear()
            self._cond.notify_all()
        shutting = RequestError("overloaded", "the service is shutting down; retry on another instance")
        for job in waiting:
            job.end(shutting)
        for slot in self._slots:
            job = slot.job
            if job is not None:
                job.end(shutting)
            slot.kill()
        for thread in self._threads:  # a planning thread (thread mode) runs on to its end
            thread.join(timeout=0.5)
        for slot in self._slots:
            with slot.lock:
                process = slot.process
            if process is not None:
                try:
                    process.wait(timeout=5.0)
                except subprocess.TimeoutExpired:   # never expected after kill(): kill it again
                    process.kill()
                    process.wait()
                slot.conn.close()

    # --- jobs -------------------------------------------------------------------------------
    def submit(self, job: PlanJob) -> int:
        """Queue ``job``; returns the number of jobs ahead of it. Raises ``overloaded`` when
        ``max_pending`` jobs already wait or the pool is closing."""
        with self._cond:
            if self._closing:
                raise RequestError("overloaded", "the service is shutting down; retry on another instance")
            if len(self._queue) >= self.max_pending:
                raise RequestError("overloaded", f"{self.max_pending} plan requests are already waiting on this "
                                   "instance; retry later or add instances (see service/README.md)")
            self._queue.append(job)
            ahead = len(self._queue) - 1
            self._cond.notify()
        return ahead

    def plan_blocking(self, problem: PlanProblem, options: dict[str, Any] | None, cancel: threading.Event,
                      within_s: float) -> PlanResult:
        """Plan ``problem`` with ``options`` (PlanOptions fields) in this thread's turn and wait:
        the plan, or RequestError (``cancelled`` at once when ``cancel`` is set,
        ``deadline_exceeded`` after ``within_s`` [s])."""
        done = threading.Event()
        box: list[Outcome] = []

        def wake(_job: PlanJob, outcome: Outcome) -> None:
            box.append(outcome)
            done.set()

        self.submit(PlanJob(problem, options, time.monotonic() + within_s, wake, cancel, use_cache=False))
        done.wait()
        if isinstance(box[0], RequestError):
            raise box[0]
        return box[0]

    def busy(self) -> tuple[int, int]:
        """(jobs running, jobs waiting) now."""
        with self._cond:
            return sum(s.job is not None for s in self._slots), len(self._queue)

    def _take(self) -> PlanJob | None:
        """The next job in arrival order; None when closing."""
        with self._cond:
            while not self._queue and not self._closing:
                self._cond.wait()
            return None if self._closing else self._queue.popleft()

    def _work(self, slot: _Slot) -> None:
        while (job := self._take()) is not None:
            reason = job.stop_reason(time.monotonic(), started=False)
            if reason is not None:  # its requester has gone or it was cancelled: never start it
                self._count("dropped")
                job.end(reason)
                continue
            job.started = time.monotonic()
            slot.set_job(job)
            budget_s = max(job.deadline - job.started, 1e-3)
            try:
                outcome = self._run_in_process(slot, job, budget_s) if self.processes else self._run_here(job, budget_s)
            finally:
                slot.set_job(None)
            if isinstance(outcome, PlanResult):
                self._count("planned")
                if job.use_cache and self.cache is not None:
                    self.cache.put(plan_cache_key(job.problem, job.options), outcome)
            job.end(outcome)

    def _run_here(self, job: PlanJob, budget_s: float) -> Outcome:
        assert self._planner is not None
        try:
            return run_planner(self._planner, job.problem, job.options, None, budget_s)
        except RequestError as exc:
            return exc
        except Exception as exc:  # noqa: BLE001 - the worker must survive any request
            log.exception("planning failed unexpectedly")
            return RequestError("internal_error", f"{type(exc).__name__}: {exc}")

    def _run_in_process(self, slot: _Slot, job: PlanJob, budget_s: float) -> Outcome:
        if slot.needs_restart() and not self._closing:  # killed just after it answered its last job, or died idle
            self._restart(slot)
        try:
            slot.conn.send((job.problem.to_dict(), job.options, budget_s))  # plain JSON-like data
            kind, value = slot.conn.recv()
        except (EOFError, OSError):  # killed by the watchdog (the job has its answer) or died
            if not self._closing:
                self._restart(slot)
            return RequestError("internal_error", "the planning process ended during the request")
        if kind == "ok":
            return PlanResult(*value)
        code, message, field_, allowed, detail = value
        return RequestError(code, message, field_, allowed, detail)

    def _restart(self, slot: _Slot) -> None:
        with slot.lock:
            old = slot.process
        if old is not None:
            if old.poll() is None:  # its socket closed first: make sure it is gone
                old.kill()
            old.wait(timeout=5.0)
            slot.conn.close()
        self._count("restarts")
        log.info("restarting planning process %s", slot.name)
        try:
            self._launch(slot)
            self._await_ready(slot)
        except Exception:  # noqa: BLE001 - try again with the next job
            if not self._closing:
                log.exception("restarting planning process %s failed", slot.name)

    def _watch(self) -> None:
        """Every WATCH_PERIOD_S: end queued and running jobs that are cancelled or late."""
        while not self._closing:
            now = time.monotonic()
            with self._cond:
                late = [(j, r) for j in self._queue if (r := j.stop_reason(now, started=False)) is not None]
                for job, _ in late:
                    self._queue.remove(job)
                    self.stats["dropped"] += 1  # under the lock already
            for job, reason in late:
                job.end(reason)
            for slot in self._slots:
                job = slot.job
                reason = job.stop_reason(now, started=True) if job is not None else None
                if reason is not None and job is not None and job.end(reason):
                    self._count(reason.code)
                    if self.processes:
                        slot.kill(job)
            time.sleep(WATCH_PERIOD_S)


if __name__ == "__main__":  # a planning process: python -m service.workers FD module:factory [MODEL_FILE]
    logging.basicConfig(level=os.environ.get("FALCON_PLAN_LOG", "WARNING").upper(),
                        format="%(asctime)s %(levelname)s plan-worker %(name)s: %(message)s")
    _child_main(Connection(int(sys.argv[1])), _load_factory(sys.argv[2]),
                Path(sys.argv[3]) if len(sys.argv) > 3 else None)
