"""A paced loop that applies force with the executor's per-tick guards, for a caller whose
command each tick is its own (the doctor's holds, pulses and tours).

The executor follows a planned trajectory under its controller; a diagnostic needs other
commands (an open-loop pulse, a PD hold with an excitation added). It sends them through
:class:`PacedLoop`, which applies force as the executor's run does: each tick paced to a
wall-clock deadline (:class:`~falcon_plan.timing.DeadlineTimer`), each command sent by the
same :class:`~falcon_plan.execution.safety.WatchedExchange` (checked finite, zero force when the
loop stalls longer than the watchdog's bound), each reading checked by the
same :class:`~falcon_plan.execution.safety.TickGuard` (a plausible encoder step, a point
inside the workspace: :class:`~falcon_plan.errors.SafetyStop` otherwise), any failure of the
device's exchange a :class:`~falcon_plan.errors.DeviceError`, the collector paused and the
thread at real-time priority while it runs, and zero force on leaving it.
"""
from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.execution.safety import (SafetyConfig, TickGuard, WatchedExchange, follow_deadlines,
                                          zero_force_best_effort)
from falcon_plan.timing import ArrivalLock, DeadlineTimer, realtime_section

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
        safety = safety or SafetyConfig()
        self.device = device
        self.rate_hz = float(device.rate_hz)
        self.guard = TickGuard(model.effects.encoder_params(model.params), model.limits,
                               safety.workspace_slack_rad, self.rate_hz)
        self.exchange = WatchedExchange(device, safety.watchdog_timeout_s)
        self.timer = DeadlineTimer(self.rate_hz, capacity=capacity)
        self.arrival_lock = ArrivalLock(self.timer)
        self._align_slots = int(ALIGN_WITHIN_S * self.rate_hz)
        self.counts = np.zeros(3)
        """The latest reading [counts] (3,)."""
        self.slot = 0
        """The next slot a caller's tick waits for (kept by the caller)."""
        self._last_slot = -1          # the slot of the last exchange (the first reading: -1)
        self._context = contextlib.ExitStack()

    def __enter__(self) -> "PacedLoop":
        self.timer.start()
        reading = self.exchange(np.zeros(3))
        self.counts = np.asarray(reading.counts, dtype=float)
        self.guard.first(self.counts)
        # as in the executor's run: a collection in a big process stops every thread for tens
        # of ms (the device's watchdog trips at 100 ms), and no other process preempts this one
        self._context.enter_context(realtime_section())
        self.exchange.watchdog.start()   # (were __exit__ never to run, it would zero the force)
        follow_deadlines(self.device, self.timer)    # last: __exit__ (which takes them back) follows
        return self

    def __exit__(self, *exc: object) -> None:
        self.exchange.watchdog.stop()
        follow_deadlines(self.device, None)
        try:
            zero_force_best_effort(self.device)
        finally:
            self._context.close()

    def wait(self, slot: int) -> int:
        """Wait for ``slot``'s deadline; the slot the tick runs in (later than ``slot`` after a
        missed deadline)."""
        return self.timer.wait(slot)

    def send(self, commands: Any, slot: int) -> np.ndarray:
        """Send ``commands`` (3,) [command units] in ``slot``; the counts read back (3,), also
        :attr:`counts`, after the guards passed them."""
        reading = self.exchange(commands)
        self.exchange.watchdog.kick()
        counts = np.asarray(reading.counts, dtype=float)
        fresh = self.guard.fresh(reading.t_s)             # before check makes it the previous reading
        self.guard.check(counts, reading.t_s, max(1, slot - self._last_slot))
        if fresh and reading.arrived_s is not None:
            self.arrival_lock.note(reading.arrived_s, may_move=slot < self._align_slots)
        self._last_slot = slot
        self.counts = counts
        return counts


__all__ = ["PacedLoop"]
