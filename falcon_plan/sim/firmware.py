"""The firmware of the simulated Falcon: command delay line and command hold (step 1 of the
period described in :mod:`falcon_plan.sim.plant`)."""
from __future__ import annotations

from collections import deque

import numpy as np

class Firmware:
    """The device firmware's command path: a delay line of ``delay`` periods and the command
    hold, which turns the commands issued each period (or None: nothing issued) into the
    command acting in that period; after ``hold_periods`` periods without a new command the
    force drops to zero (see :mod:`falcon_plan.sim.plant`, step 1)."""

    def __init__(self, delay: int, hold_periods: int) -> None:
        self.delay, self.hold = delay, hold_periods
        self.queue: deque[np.ndarray | None] = deque([None] * delay)
        self.latched = np.zeros(3)
        self.since = hold_periods  # nothing received yet: no force

    def push(self, issued: np.ndarray | None) -> np.ndarray:
        """Issue the command ``issued`` (3 command units) now (None: nothing); return the
        command acting in this period."""
        self.queue.append(issued)
        arrived = self.queue.popleft()
        if arrived is not None:
            self.latched, self.since = arrived, 0
        else:
            self.since += 1
        return self.latched if self.since < self.hold else _ZERO3

    def peek(self, i: int) -> np.ndarray:
        """The command that will act ``i`` periods from now if only None is issued meanwhile
        (i < delay: already decided by the queue)."""
        latched, since = self.latched, self.since
        for item in list(self.queue)[:i + 1]:
            latched, since = (item, 0) if item is not None else (latched, since + 1)
        return latched if since < self.hold else _ZERO3

    def preload(self, issued: np.ndarray) -> None:
        """As if the command ``issued`` (3 command units) had been issued every period until
        now: it acts from the next period on (e.g. the commands that hold a PD's equilibrium)."""
        self.queue = deque(issued.copy() for _ in range(self.delay))
        self.latched, self.since = issued, 0

    def after_commands(self, issued: np.ndarray, actives: np.ndarray) -> None:
        """State after a batch that issued a command every period (rows of ``issued``), whose
        acting commands were ``actives`` (same shape)."""
        k = issued.shape[0]
        if k == 0:
            return
        if k <= self.delay:
            for row in issued:
                self.push(row.copy())
            return
        self.queue = deque(row.copy() for row in issued[k - self.delay:])
        self.latched, self.since = actives[-1].copy(), 0


_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)
