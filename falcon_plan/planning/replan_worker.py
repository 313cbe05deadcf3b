"""Replans made in a process of their own (issue 24): :class:`ReplanWorker`.

A replan made in a thread of the process that runs the control loop is slow and slows the
loop: the loop hands the interpreter lock back every 0.2 ms (``timing.responsive_gil``), so a
15 ms plan takes about 100 ms there, and a CasADi solve holds the lock for its whole length
(a stall the loop's watchdog stops the run for). The worker process runs
:func:`~falcon_plan.planning.replan.moving_planner` instead: the parent sends the
:class:`~falcon_plan.execution.splice.MovingStart` (the running plan in it), the goal, the
options and the model; it gets the trajectory and the :class:`~falcon_plan.planning.replan.Replan`
back (without its pipeline report). One replan at a time; the process is started again
after it died.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import pickle
import sys
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

from falcon_plan.childproc import child_ignores_sigint, spawn_module
from falcon_plan.errors import FalconPlanError

log = logging.getLogger(__name__)

START_TIMEOUT_S = 1800.0
"""Longest the process may take to start and warm up [s]: a bound for a process that hangs,
not the expected time (a first start on a machine compiles the planner's kernels: minutes,
see :mod:`falcon_plan.compiled.build`; else a few seconds). :meth:`ReplanWorker.wait_ready`
tells a caller that cannot wait so long."""
START_NOTICE_S = 15.0
"""While the process starts, say that it is still starting this often [s]."""
REPLAN_TIMEOUT_S = 30.0
"""Longest one replan may take before the process is killed and the replan fails [s]."""
NICE = -5
"""The process's niceness where it may raise its priority (root, CAP_SYS_NICE; else it keeps
its parent's): a stream of goals waits for its replans (the device rests at its last goal
meanwhile), so on a busy machine they come before other work at normal priority (the
control loop runs at real-time priority above both)."""


class ReplanError(FalconPlanError):
    """A replan in the worker process failed (its error's type and message), or the process did."""


class ReplanWorker:
    """A replanning process (module docstring). :meth:`start` it (it warms its planner up: the
    first replan is as fast as the next), call :meth:`planner` for a coordinator's planner,
    :meth:`close` it at the end. Thread-safe (replans queue on a lock)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._process: Any = None
        self._conn: Connection | None = None
        self._closed = False
        self._ready = threading.Event()

    def start(self) -> None:
        """Start the process and wait until it is warm (no-op while it runs)."""
        with self._lock:
            self._start_locked()

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait at most ``timeout_s`` [s] until the process is started and warm; whether it is."""
        return self._ready.wait(timeout_s)

    def _start_locked(self) -> None:
        if self._closed:
            raise ReplanError("the replanning process was closed")
        if self._process is not None and self._process.poll() is None:
            return
        self._process, self._conn = spawn_module(__name__)
        started = time.monotonic()
        ready = False
        try:
            while not self._conn.poll(START_NOTICE_S):
                waited = time.monotonic() - started
                if self._process.poll() is not None or waited > START_TIMEOUT_S:
                    break
                log.warning("the replanning process is still starting after %.0f s (its first start on this "
                            "machine compiles the planner's kernels, once)", waited)
            else:
                ready = self._conn.recv() == "ready"
        except (EOFError, OSError):   # it died, or was killed while it started (close)
            pass
        if not ready:
            self._kill_locked()
            raise ReplanError("the replanning process did not start")
        self._ready.set()

    def close(self) -> None:
        """Stop the process at once, also while it starts or replans (idempotent)."""
        self._closed = True
        process = self._process
        if process is not None:
            process.kill()   # (a start or a replan waiting on it ends now and lets the lock go)
        with self._lock:
            self._kill_locked()

    def _kill_locked(self) -> None:
        self._ready.clear()
        if self._process is not None:
            self._process.kill()
            self._process.wait()
            assert self._conn is not None
            self._conn.close()
        self._process = self._conn = None

    def planner(self, model: Any) -> Any:
        """``planner(start, goal, options=None) -> (trajectory, Replan)`` (a
        :class:`~falcon_plan.execution.splice.SpliceCoordinator`'s planner):
        :func:`moving_planner` with ``PlanOptions.fast(**options)`` and ``model`` (a FalconModel),
        run in the process, which readies ``model`` now (its first replan is as fast as the next)."""
        blob = pickle.dumps(model)
        self._ask(("model", blob))

        def plan(start: Any, goal: Any, options: dict[str, Any] | None = None) -> Any:
            running = start.plan
            if getattr(running, "plan", None) is not None:   # (its pipeline report stays here)
                start = dataclasses.replace(start, plan=dataclasses.replace(running, plan=None))
            return self._ask(("replan", blob, options, start, goal))

        return plan

    def _ask(self, request: tuple[Any, ...]) -> Any:
        with self._lock:
            self._start_locked()
            assert self._conn is not None
            try:
                self._conn.send(request)
                if not self._conn.poll(REPLAN_TIMEOUT_S):
                    self._kill_locked()
                    raise ReplanError(f"the replanning process gave no answer within {REPLAN_TIMEOUT_S:g} s")
                kind, value = self._conn.recv()
            except (EOFError, OSError) as exc:
                self._kill_locked()
                raise ReplanError(f"the replanning process ended during a replan ({type(exc).__name__})") from exc
        if kind != "ok":
            raise ReplanError(value)
        return value


def _child_main(conn: Connection) -> None:
    """The process: warm the planner up, then make the replans the socket brings."""
    child_ignores_sigint()
    with contextlib.suppress(OSError):
        os.setpriority(os.PRIO_PROCESS, 0, NICE)
    from falcon_plan.planning.problem import PlanOptions
    from falcon_plan.planning.replan import moving_planner

    _warm_up()
    conn.send("ready")
    models: dict[bytes, Any] = {}
    while True:
        try:
            kind, blob, *request = conn.recv()   # ("model", model) or ("replan", model, options, start, goal)
        except (EOFError, OSError):  # the parent has gone
            return
        try:
            if blob not in models:  # its CasADi Functions are built on first use: now
                models[blob] = pickle.loads(blob)
                models[blob].functions
            if kind == "model":
                conn.send(("ok", None))
                continue
            options, start, goal = request
            made = moving_planner(PlanOptions.fast(**(options or {})), models[blob])(start, goal)
            conn.send(("ok", (made[0], dataclasses.replace(made[1], plan=None))))
        except Exception as exc:  # noqa: BLE001 - the process must survive any replan
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


def _warm_up() -> None:
    """Plan once from rest and replan once from the motion (the planner's compiled pieces and
    both NLPs load on first use: seconds), so that the first real replan is as fast as the next,
    both with the default time budget and with one shorter than the coarse solve's own wall-time
    limit (:data:`~falcon_plan.planning.pattern.COARSE_WALL_TIME_S`: its NLP then stops by a
    deadline callback, another NLP, built on first use in ~0.25 s: a moving target's first replan,
    :data:`~falcon_plan.moving_target.FOLLOW_OPTIONS`, took 0.3 s, and the splice budget measured
    from it kept the next splices 0.5 s ahead); and import what a replan's four-arc guesses import
    on first use (scipy.linalg, ~0.2 s: it would eat their share of the time,
    :data:`~falcon_plan.planning.replan.FOUR_ARC_SHARE`), and what a request carries
    (:class:`~falcon_plan.execution.splice.MovingStart`)."""
    try:
        import numpy as np
        import scipy.linalg  # noqa: F401

        import falcon_plan.execution.splice  # noqa: F401  (what a request carries: ~40 ms to import)

        from falcon_plan.model.kinematics import counts_to_position
        from falcon_plan.planning.api import plan_problem
        from falcon_plan.planning.pattern import COARSE_WALL_TIME_S
        from falcon_plan.planning.problem import PlanOptions, PlanProblem
        from falcon_plan.planning.replan import Replan, replan

        home = counts_to_position(np.zeros(3))
        for options in (PlanOptions.fast(), PlanOptions.fast(time_budget_s=0.5 * COARSE_WALL_TIME_S)):
            first = Replan.of_plan(plan_problem(PlanProblem(tuple(home), tuple(home + [0.02, 0.0, 0.0])), options))
            replan(first, 0.5 * first.duration_s, home + [-0.01, 0.01, 0.0], options=options)   # a reversal: the pipeline
    except Exception:  # noqa: BLE001 - a warm-up that fails only leaves the first replan slow
        log.warning("warming the replanner up failed", exc_info=True)


__all__ = ["ReplanWorker", "ReplanError", "START_TIMEOUT_S", "START_NOTICE_S", "REPLAN_TIMEOUT_S", "NICE"]

if __name__ == "__main__":  # the process: python -m falcon_plan.planning.replan_worker FD
    logging.basicConfig(level=os.environ.get("FALCON_PLAN_LOG", "WARNING").upper(),
                        format="%(asctime)s %(levelname)s replan-worker %(name)s: %(message)s")
    _child_main(Connection(int(sys.argv[1])))
