"""The hold between homing and a run: the executor's controller holding the device where it is
while the host prepares the run.

A paced run takes tens to hundreds of milliseconds to prepare (the approach, the LQR's gain
schedule along the whole plan). A Falcon given zero force meanwhile falls under gravity (after
homing, or whenever nobody holds the grip), and the run would start from a state its plan did
not know. :class:`HoldLoop` closes that window: from its first reading on, a thread of its own
runs the executor's controller (the same per-tick law the run uses,
:meth:`~falcon_plan.control.Controller.tracker`, along a reference that stays at the point
first read, with the model's gravity compensation as its feed-forward; the LQR within the
device's static limit) at the loop rate, paced to the wall clock, so the device is braked
where it was and held there. The run is planned from that point at rest
(:attr:`HoldLoop.point_m`) on the caller's thread meanwhile, and
:meth:`~falcon_plan.execution.executor.Executor.run` with ``hold=`` takes the device over at
its first tick: the hold stops after its current tick and the run's first command is the last
one the hold sent (and the run's controller starts with it in flight), so no period of zero
or stale force separates them.

While it holds, the collector is paused, the switch interval short
(:func:`~falcon_plan.timing.gc_paused`, :class:`~falcon_plan.timing.responsive_gil`), as in
a paced run, and the caller's (preparing) thread runs at real-time priority
(:func:`~falcon_plan.timing.realtime_priority`), so that it cannot be preempted by another
process while it holds the GIL and hold the loop back (with two CPU-stress processes, at
normal priority: stalls of 12-20 ms and the hold ringing at the command limit); and it gives
way to each of the hold's ticks (:func:`~falcon_plan.timing.giving_way`: the preparation's
long loops wait at :func:`~falcon_plan.timing.give_way` while a tick is under way), else each
thread of the tick waited a switch interval for the interpreter and the hold fell to 200-300
Hz, ringing at the limit, while the gain schedule was designed. A caller waits
for the hold to settle (:meth:`HoldLoop.wait_settled`, about 0.1 s after homing) before it
prepares, so that a stall cannot come while the hold still brakes at the limit. The hold applies
force through the loop every caller uses (:class:`~falcon_plan.execution.force_loop.ForceLoop`):
each reading passes the per-tick checks (a plausible encoder step, a point inside the
workspace), each command goes through the watched exchange, whose watchdog zeroes the force
when the hold's thread stalls past :data:`HOLD_WATCHDOG_S`. A device error, a guard's stop, either
watchdog (the loop's, or the device's own) ends the hold; :meth:`HoldLoop.release` then raises
it. Leaving the ``with`` block without a run taking over gives the device zero force.
"""
from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from falcon_plan.errors import DeviceError, InvalidParameterError, SafetyStop
from falcon_plan.execution.force_loop import ForceLoop
from falcon_plan.timing import DeadlineTimer, giving_way, loop_tick, realtime_section, realtime_thread

if TYPE_CHECKING:
    from falcon_plan.execution.executor import Executor

log = logging.getLogger(__name__)

SETTLED_COUNTS = 2.0
"""The hold has settled when every leg reads within this of the hold point [counts] ..."""
SETTLED_S = 0.05
"""... for this long without a break [s]."""
HOLD_WATCHDOG_S = 0.5
"""The hold's loop watchdog bound [s]: longer than a run's (``watchdog_timeout_s``, 50 ms by
default), because the hold's thread shares the interpreter with the preparation of the run,
which holds it for up to about 0.1 s at a time (starting a recording process, the first design
in a process: measured, a 105 ms stall that tripped a 90 ms bound), and because the command a
stalled hold leaves applied holds a settled device still (a caller prepares only once the hold
has settled). A hold stuck longer has its force zeroed."""
SETTLE_TIMEOUT_S = 1.5
"""Longest :meth:`HoldLoop.wait_settled` waits by default [s] (a device falling at 1 m/s is
braked and back at the point in about 0.3 s)."""


class HoldLoop:
    """Holds ``executor``'s device where it is, with ``executor``'s controller, until a run of
    ``executor`` takes over (module docstring); ``executor`` must pace (a device whose time
    passes only when it is driven, a simulation stepped as fast as it goes, lives through no
    time while the host computes and needs no hold). Use as a context manager::

        with HoldLoop(executor) as hold:         # holding from here on
            plan from hold.point_m ...; executor.prepare(...)
            hold.wait_settled()
            report = executor.run(trajectory, hold=hold)
    """

    def __init__(self, executor: Executor) -> None:
        if not executor.pace:
            raise InvalidParameterError("a hold streams in real time: the executor must pace")
        self.ex = executor
        self.device = executor.device
        self.period_s = 1.0 / executor.rate_hz
        self.loop = ForceLoop(self.device, executor.model, executor.safety, executor.rate_hz,
                              timer=DeadlineTimer(executor.rate_hz, spin_s=0.0, record=False),
                              watchdog_s=HOLD_WATCHDOG_S)
        """The hold's force and guards (no busy wait: the GIL is the preparation's)."""
        self._gap = 1                          # periods between the last exchange and the one before
        self._stop = threading.Event()
        self._settled = threading.Event()
        self._thread: threading.Thread | None = None
        self._context = contextlib.ExitStack()
        self._error: BaseException | None = None
        self._handed: np.ndarray | None = None     # the command handed over to a run
        c = executor.controller
        self.law = c.tracker(np.zeros((2, 3)), executor.model)
        """The hold's law: designed now, at the home pose, before any force (the first design in
        a process takes about half a second); :meth:`start` moves it to the point read."""
        self.ticks = 0
        """Ticks held so far."""
        self._prev_t_s: float | None = None
        self._within = 0                       # consecutive fresh readings near the point
        self._settle_ticks = max(1, int(round(SETTLED_S * executor.rate_hz)))
        self.point_m = np.zeros(3)
        """The point held [m, base frame]: where the device was at the hold's first reading."""
        self.ref_counts = np.zeros(3)
        """Its counts [counts]."""

    # --- public -------------------------------------------------------------------------------
    def __enter__(self) -> "HoldLoop":
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._handed is None:
            self._halt()
            self.loop.end()   # no run took over: let go, as every exit does
        self._context.close()

    def start(self) -> None:
        """Read the device (the command in force stays: zero after homing), move the hold to
        the point read (the gains designed at the home pose, the feed-forward of the point:
        :meth:`~falcon_plan.control.Controller.quick_tail`, microseconds) and start holding."""
        from falcon_plan.lqr import model_feedforward

        ex = self.ex
        in_force = np.asarray(getattr(self.device, "last_commands", np.zeros(3)), dtype=float)
        reading, self.point_m = self.loop.first(in_force)        # SafetyStop outside the workspace
        counts = np.asarray(reading.counts, dtype=float)
        self.ref_counts = counts.copy()
        c, law, ref = ex.controller, self.law, np.repeat(counts[None], 2, axis=0)
        feedforward = model_feedforward(ref, ex.model, c.feedforward_effects, ex.rate_hz, c.feedforward_lead_samples)
        c.apply_tail(law, 0, c.quick_tail(law, 0, ref, feedforward, ex.model))
        if hasattr(law, "within_static_until"):   # a hold needs no headroom above the static limit
            law.within_static_until(2)
        law.start(counts, in_force)
        self._last = (reading, in_force)
        self._context.enter_context(realtime_section())   # the preparing thread: never preempted holding the GIL
        self._context.enter_context(giving_way())         # ... and waiting for each tick of the hold (give_way)
        self._thread = threading.Thread(target=self._loop, name="falcon-hold", daemon=True)
        self._thread.start()

    @property
    def settled(self) -> bool:
        """Every leg has read within :data:`SETTLED_COUNTS` of the point for :data:`SETTLED_S`,
        and does still."""
        return self._settled.is_set()

    def wait_settled(self, timeout_s: float = SETTLE_TIMEOUT_S) -> bool:
        """Wait until the hold has settled, at most ``timeout_s`` [s]; True if it has. Raises
        what ended the hold, if anything."""
        deadline = time.monotonic() + timeout_s
        while not self._settled.wait(0.01) and time.monotonic() < deadline and self._running():
            pass
        self._raise_error()
        return self._settled.is_set()

    def release(self) -> np.ndarray:
        """Stop holding after the current tick and hand over: the command the device applies
        now (3,) [command units] (a run calls this right before its first exchange). Raises
        what ended the hold, if anything (the device then has zero force)."""
        if self._handed is None:
            self._halt()
            self._raise_error()
            self._handed = self._last[1].copy()
        return self._handed

    # --- the loop -----------------------------------------------------------------------------
    def _running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _halt(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()

    def _raise_error(self) -> None:
        if self._error is not None:
            raise self._error

    def _tick(self, k: int, slots: int) -> None:
        """Tick k of the hold, ``slots`` periods after the previous one: command from the last
        reading, exchange, keep the new reading."""
        reading, _ = self._last
        fresh = reading.t_s != self._prev_t_s   # threaded I/O: no new status came
        self._prev_t_s = reading.t_s
        counts = np.asarray(reading.counts, dtype=float)
        if fresh:
            near = np.abs(counts - self.ref_counts).max() <= SETTLED_COUNTS
            self._within = self._within + slots if near else 0
            if self._within >= self._settle_ticks:
                self._settled.set()
            elif not near:
                self._settled.clear()
        self.loop.guard.check(counts, reading.t_s, self._gap, self.ref_counts)
        tc = self.law.update(k, counts, slots, fresh, self.loop.read_for(reading.arrived_s))
        self._last = (self.loop.send(tc, k), np.asarray(tc, dtype=float))
        self._gap = slots
        self.ticks += 1

    def _loop(self) -> None:
        """The hold's thread, at real-time priority where allowed. Its end leaves the command in
        force for the run that takes over; an error zeroes it."""
        realtime_thread()
        self.loop.begin(time.perf_counter() + self.period_s)
        k = 0
        try:
            while not self._stop.is_set():
                k = self.loop.wait(k)
                with loop_tick():        # the preparation gives way (timing.give_way) meanwhile
                    self._tick(k, k - self.loop.last_slot if self.ticks else 1)
                k += 1
        except BaseException as exc:  # noqa: BLE001 - the caller learns it at release()
            self._error = exc if isinstance(exc, (DeviceError, SafetyStop)) else DeviceError(
                f"the hold before the run failed: {type(exc).__name__}: {exc}")
            log.warning("hold ended: %s", self._error)
        finally:
            self.loop.end(zero_force=self._error is not None)


__all__ = ["HOLD_WATCHDOG_S", "HoldLoop", "SETTLED_COUNTS", "SETTLED_S", "SETTLE_TIMEOUT_S"]
