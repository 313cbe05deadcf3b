"""The one loop through which force reaches a device.

Every caller that applies force (the executor's run, the hold before it, the doctor's holds,
pulses and tours) drives the device through a :class:`ForceLoop`, and only computes its own
command per tick. The loop owns what must be the same for all of them:

- **the per-tick guards**: each command through one
  :class:`~falcon_plan.execution.safety.WatchedExchange` (checked finite, zero force when the
  loop stalls past its watchdog's bound, a device failure a
  :class:`~falcon_plan.errors.DeviceError`); each reading through one
  :class:`~falcon_plan.execution.safety.TickGuard` (a plausible encoder step, a point inside
  the workspace; :class:`~falcon_plan.errors.SafetyStop` otherwise), the first one included;
- **the pacing**: a wall-clock deadline per tick (:class:`~falcon_plan.timing.DeadlineTimer`,
  or none for a simulation stepped as fast as it goes), told to the device
  (:func:`~falcon_plan.execution.safety.follow_deadlines`), and optionally moved once onto the
  phase at which the device's readings arrive (:class:`~falcon_plan.timing.ArrivalLock`);
- **the dating of readings**: when each tick was due (:class:`~falcon_plan.timing.HandOvers`),
  so that a caller knows which tick a reading was read for (:meth:`ForceLoop.read_for`);
- **the end**: the watchdog stopped, the deadlines taken back, zero force (:meth:`ForceLoop.end`;
  never raises, says why zero force failed).

The caller's tick is ``slot = loop.wait(slot)``, its command from the last reading (checked by
``loop.guard.check``), then ``reading = loop.send(command, slot)``.
"""
from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.execution.safety import (SafetyConfig, TickGuard, WatchedExchange, follow_deadlines,
                                          zero_force_best_effort)
from falcon_plan.timing import ArrivalLock, DeadlineTimer, HandOvers

if TYPE_CHECKING:
    import threading

    from falcon_plan.devices.base import Device, DeviceReading
    from falcon_plan.model.dynamics import FalconModel


class ForceLoop:
    """Force on ``device`` one guarded tick at a time (module docstring).

    ``model``: the guards' geometry (its encoder effects included) and workspace limits, widened
    by ``safety``'s slack; ``rate_hz``: the loop's rate [Hz]; ``timer``: its deadlines (None:
    unpaced, a simulation stepped as fast as it goes); ``watchdog_s``: the watchdog's bound [s]
    (default ``safety.watchdog_timeout_s``); ``lock_arrivals``: keep an
    :class:`~falcon_plan.timing.ArrivalLock` on the timer (:attr:`arrival_lock`), which the
    caller feeds (it knows when its reference is at rest).
    """

    def __init__(self, device: Device, model: FalconModel, safety: SafetyConfig, rate_hz: float, *,
                 timer: DeadlineTimer | None, watchdog_s: float | None = None, lock_arrivals: bool = False) -> None:
        self.device = device
        self.guard = TickGuard(model.effects.encoder_params(model.params), model.limits,
                               safety.workspace_slack_rad, rate_hz, safety.max_tracking_error_counts)
        self.exchange = WatchedExchange(device, safety.watchdog_timeout_s if watchdog_s is None else watchdog_s)
        self.watchdog = self.exchange.watchdog
        self.timer = timer
        self.arrival_lock = ArrivalLock(timer) if timer is not None and lock_arrivals else None
        self.handovers = HandOvers()
        self.last_slot = -1
        """The slot of the last exchange (the first reading's: -1)."""
        self.sent_s = 0.0
        """When the last command was handed to the driver [s, monotonic]."""

    def first(self, commands: Any) -> tuple[DeviceReading, np.ndarray]:
        """The loop's first exchange, before any tick: ``commands`` (3,) [command units] (zero, or
        the command in force); its reading and the point it gives [m] (inside the workspace, else
        :class:`~falcon_plan.errors.SafetyStop`)."""
        reading = self.exchange(commands)
        return reading, self.guard.first(np.asarray(reading.counts, dtype=float))

    def begin(self, start_s: float | None = None, watch: bool = True) -> None:
        """Start the ticks: the watchdog (when ``watch``), the timer's slot 0 at ``start_s`` [s,
        the timer's clock; default now], the device told the deadlines."""
        if watch:
            self.watchdog.start()
        if self.timer is not None:
            self.timer.start(start_s)
            follow_deadlines(self.device, self.timer)

    def wait(self, slot: int, wake: threading.Event | None = None) -> int | None:
        """Wait for ``slot``'s deadline; the slot the tick runs in (later after a missed deadline;
        None when ``wake`` was set first, :meth:`~falcon_plan.timing.DeadlineTimer.wait`). Unpaced:
        ``slot`` at once."""
        return slot if self.timer is None else self.timer.wait(slot, wake=wake)

    def send(self, commands: Any, slot: int) -> DeviceReading:
        """The exchange of ``slot``: ``commands`` (3,) [command units] out (as sent:
        ``exchange.sent``), the reading back (not yet checked: the tick that uses it checks it,
        :attr:`guard`); the watchdog kicked, when the slots were due noted."""
        self.sent_s = time.monotonic()
        reading = self.exchange(commands)
        if self.timer is None:
            self.handovers.note(slot, self.sent_s)
        else:
            self.timer.io_done()
            self.handovers.note_slots(self.timer, self.last_slot, slot)
        self.watchdog.kick()
        self.last_slot = slot
        return reading

    def read_for(self, arrived_s: float | None) -> int | None:
        """The tick a reading that arrived at ``arrived_s`` [s, monotonic] was read for
        (:meth:`~falcon_plan.timing.HandOvers.reading_tick`; None when that time is unknown or
        nothing was sent yet)."""
        return None if arrived_s is None else self.handovers.reading_tick(arrived_s)

    def end(self, zero_force: bool = True) -> Exception | None:
        """Stop the watchdog, take the deadlines back and (``zero_force``) give the device zero
        force; never raises: returns why zero force failed (None: it was sent, or not asked).
        Idempotent."""
        self.watchdog.stop()
        follow_deadlines(self.device, None)
        return zero_force_best_effort(self.device) if zero_force else None


__all__ = ["ForceLoop"]
