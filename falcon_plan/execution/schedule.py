"""What a run follows and what is handed to it while it runs: its per-tick reference
(:class:`RunSchedule`, :func:`held`), and a new reference prepared off the loop
(:class:`SpliceOffer`) passed through a :class:`SpliceSlot` to the loop, which takes it at its
tick or refuses it (the executor's run, :mod:`~falcon_plan.execution.executor`; the jobs that
make offers, :mod:`~falcon_plan.execution.splice`)."""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from falcon_plan.control import Tracker
    from falcon_plan.execution.braking import Brake, FirstCommands


@dataclass(frozen=True)
class RunSchedule:
    """A run's per-tick arrays on the uniform grid t_k = k / rate (pre-roll, trajectory, settle).

    t_s : (n,) tick times [s]; position_m, velocity_m_s : (n, 3) the planned point [m] and
    velocity [m/s] (where a brake starts); ref_counts : (n, 3) the reference [counts];
    tracker : the controller's per-tick law along ``ref_counts``; preroll_samples : rows before
    the motion starts (not in the tracking error); first_brake : the safe stop's first command at
    every tick, made with the plan (None: none made).
    """

    t_s: np.ndarray
    position_m: np.ndarray
    ref_counts: np.ndarray
    tracker: Tracker
    preroll_samples: int
    velocity_m_s: np.ndarray
    first_brake: FirstCommands | None = None

    @property
    def motion_start_s(self) -> float:
        """Time of the motion's start from the first row [s]."""
        return float(self.t_s[min(self.preroll_samples, len(self.t_s) - 1)])


@dataclass(frozen=True)
class SpliceOffer:
    """A new plan for a running run, prepared off the loop (:meth:`~falcon_plan.execution.executor.Executor.prepare_splice`):
    from command tick ``tick`` on the run follows ``ref_counts`` (m, 3) [counts] (the running
    reference for the command delay, then the new plan from its start), ``position_m`` (m, 3)
    [m], ``velocity_m_s`` (m, 3) [m/s], with the controller's ``tail`` (gains or offsets); ``jumps`` the splice's
    discontinuities (position [counts], rate [counts/s], feed-forward [command units]);
    ``source`` the new plan's; ``prepare_s`` the time preparing took [s]; ``brake``: set when the offer is the
    rest of a stop after a cancel (:func:`~falcon_plan.execution.splice.finish_stop`): the whole
    stop, which the run's report gives (not a splice)."""

    tick: int
    ref_counts: np.ndarray
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    tail: Any
    jumps: tuple[float, float, float]
    source: str
    prepare_s: float
    brake: Brake | None = None


class SpliceSlot:
    """Where a replanning thread hands a :class:`SpliceOffer` to a running executor (thread-safe;
    the loop looks once per tick). An offer whose tick has passed is refused (kept as missed):
    the run keeps its plan, it never jumps. :meth:`offer_and_wait` tells the offering thread
    which it was. ``pending_after_take``: see :attr:`pending_after_take`."""

    def __init__(self, *, pending_after_take: bool = False) -> None:
        self._lock = threading.Lock()
        self.pending_after_take = pending_after_take
        """Whether an offer taken leaves the slot :attr:`PENDING` until the offering job says
        what comes next (:meth:`expect`): a run that is not paced then waits for it rather than
        running on while the job finishes (a job that always ends with :meth:`expect`)."""
        self._offer: SpliceOffer | None = None
        self._decided = threading.Event()
        self._taken = False
        self._expected: int | None = None
        self._last_expected = -math.inf
        self.latest_tick = 0
        """The latest command tick an offer was announced for (:meth:`expect`)."""
        self._arrived = threading.Condition(self._lock)

    PENDING = -1
    """:meth:`expect`'s tick for a job that has not chosen its tick yet."""

    def expect(self, tick: int | None) -> None:
        """Announce that an offer for command ``tick`` is being prepared (:attr:`PENDING`: a
        job began and will choose its tick; None: no longer): a run that is not paced (a
        simulation stepped as fast as it goes, whose time does not pass while it waits) waits
        for it at that tick, and at any tick while it is pending (:meth:`wait_for`), so that
        its splices fall where a paced run's would with the same latencies in ticks."""
        with self._lock:
            self._expected = tick
            self._last_expected = time.monotonic()
            self.latest_tick = max(self.latest_tick, tick or 0)
            self._arrived.notify_all()

    def expecting(self, grace_s: float = 0.0) -> bool:
        """Whether an offer is announced (:meth:`expect`) and not decided yet, or was within
        the last ``grace_s`` [s] (a stream of new goals: the next one is likely on its way)."""
        with self._lock:
            return self._expected is not None or time.monotonic() - self._last_expected < grace_s

    def wait_for(self, k: int, timeout_s: float = 10.0) -> None:
        """Wait (up to ``timeout_s`` [s]) while an offer for tick k is expected but not here."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._expected == self.PENDING or (
                    self._expected == k and (self._offer is None or self._offer.tick != k)):
                left = deadline - time.monotonic()
                if left <= 0 or not self._arrived.wait(left):
                    return

    def offer(self, splice: SpliceOffer) -> None:
        """Hand ``splice`` over (replacing an earlier one not yet taken)."""
        with self._lock:
            self._offer, self._taken = splice, False
            self._decided = threading.Event()
            self._arrived.notify_all()

    def offer_and_wait(self, splice: SpliceOffer, timeout_s: float) -> bool:
        """:meth:`offer` ``splice``, then wait up to ``timeout_s`` [s] for the loop: True when it took the
        offer at its tick, False when it refused it (or did not look: the run ended)."""
        self.offer(splice)
        with self._lock:
            decided = self._decided
        if not decided.wait(timeout_s):
            with self._lock:
                if self._offer is splice:
                    self._offer = None
            return False
        with self._lock:
            return self._taken

    def take(self, k: int) -> tuple[SpliceOffer | None, SpliceOffer | None]:
        """(the offer due at tick k, or None; an offer that missed its tick, or None). The
        loop calls :meth:`applied` once it follows an offer it took."""
        with self._lock:
            o = self._offer
            if o is None or o.tick > k:
                return None, None
            self._offer, self._taken = None, o.tick == k
            if o.tick != k:
                self._decided.set()
            elif self.pending_after_take:
                self._expected = self.PENDING
        return (o, None) if o.tick == k else (None, o)

    def applied(self) -> None:
        """The loop follows the offer it took (the run's reference is the new one): the
        offering thread may go on (and read the run's new reference)."""
        with self._lock:
            self._decided.set()


def held(s: RunSchedule, n: int) -> RunSchedule:
    """``s`` with its last point held (at rest) to at least ``n`` ticks."""
    more = n - s.t_s.shape[0]
    if more <= 0:
        return s
    n_new = s.t_s.shape[0] + more
    hold = lambda a: np.concatenate([a, np.repeat(a[-1:], more, axis=0)])  # noqa: E731
    return RunSchedule(s.t_s[0] + np.arange(n_new) * (s.t_s[1] - s.t_s[0]) if n_new > 1 else s.t_s, hold(s.position_m),
                     hold(s.ref_counts), s.tracker, s.preroll_samples,
                     np.concatenate([s.velocity_m_s, np.zeros((more, 3))]))


__all__ = ["RunSchedule", "SpliceOffer", "SpliceSlot", "held"]
