"""The doctor's paced loop: :class:`~falcon_plan.execution.force_loop.ForceLoop` as a context
manager, for a caller whose command each tick is its own (the doctor's holds, pulses and tours).

The executor follows a planned trajectory under its controller; a diagnostic needs other
commands (an open-loop pulse, a PD hold with an excitation added). It sends them through
:class:`PacedLoop`, which is the executor's loop (the same guards, the same watched exchange, a
wall-clock deadline per tick, zero force on leaving it) with the collector paused and the
thread at real-time priority while it runs, and its deadline grid moved once onto the device's
reading arrivals while the caller holds at its start.
"""
from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.execution.force_loop import ForceLoop
from falcon_plan.execution.safety import SafetyConfig
from falcon_plan.timing import DeadlineTimer, realtime_section

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device
    from falcon_plan.model.dynamics import FalconModel


ALIGN_WITHIN_S = 0.25
"""A paced loop moves its deadline grid onto the device's reading arrivals
(:class:`~falcon_plan.timing.ArrivalLock`) only within this long of its start [s], which every
caller spends holding (the doctor holds 0.5 s first): so it measures and drives the device
with the delay an executor's run, aligned in its own hold, has."""


class PacedLoop:
    """Force on ``device`` (at its ``rate_hz``) one paced, guarded tick at a time; the guards
    use ``model``'s geometry (its encoder effects included) and limits, widened by ``safety``'s
    slack (default :class:`~falcon_plan.execution.safety.SafetyConfig`); ``capacity``: the
    expected number of ticks (the timer's buffer). A context manager: entering it starts the
    clock and reads the device at zero force (:attr:`counts`, checked inside the workspace);
    leaving it gives the device zero force. Each tick: ``slot = loop.wait(slot)``, then
    ``loop.send(commands, slot)``. Within :data:`ALIGN_WITHIN_S` of the start, the grid moves
    once onto the phase at which the readings arrive, as an executor's run does in its hold.
    Between the first reading and leaving, a caller that does not send for ``safety``'s
    ``watchdog_timeout_s`` has its force zeroed, and its next send raises
    :class:`~falcon_plan.errors.SafetyStop`.
    """

    def __init__(self, device: Device, model: FalconModel, safety: SafetyConfig | None = None,
                 capacity: int = 20000) -> None:
        self.rate_hz = float(device.rate_hz)
        self.loop = ForceLoop(device, model, safety or SafetyConfig(), self.rate_hz,
                              timer=DeadlineTimer(self.rate_hz, capacity=capacity), lock_arrivals=True)
        """The force loop every caller drives a device through."""
        self.timer, self.guard, self.exchange = self.loop.timer, self.loop.guard, self.loop.exchange
        self._align_slots = int(ALIGN_WITHIN_S * self.rate_hz)
        self.counts = np.zeros(3)
        """The latest reading [counts] (3,)."""
        self.slot = 0
        """The next slot a caller's tick waits for (kept by the caller)."""
        self._context = contextlib.ExitStack()

    def __enter__(self) -> "PacedLoop":
        reading, _ = self.loop.first(np.zeros(3))
        self.counts = np.asarray(reading.counts, dtype=float)
        # as in the executor's run: a collection in a big process stops every thread for tens
        # of ms (the device's watchdog trips at 100 ms), and no other process preempts this one
        self._context.enter_context(realtime_section())
        self.loop.begin()     # (were __exit__ never to run, the watchdog would zero the force)
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.loop.end()
        finally:
            self._context.close()

    def wait(self, slot: int) -> int:
        """Wait for ``slot``'s deadline; the slot the tick runs in (later than ``slot`` after a
        missed deadline)."""
        return self.loop.wait(slot)

    def send(self, commands: Any, slot: int, ref_counts: Any = None) -> np.ndarray:
        """Send ``commands`` (3,) [command units] in ``slot``; the counts read back (3,), also
        :attr:`counts`, after the guards passed them, the tracking bound against ``ref_counts``
        (3,) [counts], the reference the caller's law follows, included (None: a command law
        with no reference, e.g. an open-loop pulse or a zero-force step)."""
        gap = max(1, slot - self.loop.last_slot)
        reading = self.loop.send(commands, slot)
        counts = np.asarray(reading.counts, dtype=float)
        fresh = self.loop.guard.fresh(reading.t_s)     # before check makes it the previous reading
        self.loop.guard.check(counts, reading.t_s, gap,
                              None if ref_counts is None else np.asarray(ref_counts, dtype=float))
        if fresh and reading.arrived_s is not None:
            self.loop.arrival_lock.note(reading.arrived_s, may_move=slot < self._align_slots)
        self.counts = counts
        return counts


__all__ = ["PacedLoop"]
