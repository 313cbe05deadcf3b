"""Deadline-based loop timing: absolute deadlines, sleep then spin, missed-deadline counting.

Tick k of a loop at ``rate_hz`` is due at ``t0 + k / rate_hz`` on :func:`time.perf_counter`'s
clock. Deadlines are absolute, so a late tick never pushes the later ones back (no drift).
:meth:`DeadlineTimer.wait` sleeps until ``spin_s`` before the deadline (the OS sleep
overshoots by tens to hundreds of microseconds) and busy-waits the rest. A tick that starts
more than one period late is a *missed deadline*: the loop then resynchronises to the
current slot, skipping the slots it missed, so the loop's time keeps following the wall
clock (a falcon log shows the skipped slots as a gap in ``t``). A loop whose device answers
in fixed frames (USB) can move its grid once onto the phase at which readings arrive
(:func:`arrival_phase`, :meth:`DeadlineTimer.align`), so that every run has the same delay.

:func:`gc_paused` keeps the garbage collector's full collections out of a run;
:func:`realtime_priority` runs it, and :func:`realtime_thread` the USB I/O threads, at
real-time priority where the system allows it.

The executor, the real-time devices (:class:`~falcon_plan.devices.base.BaseDevice`) and the
timer benchmark (``benchmarks/bench_executor.py``) share this class, so the benchmark's bare
reference loop measures exactly the scheme the executor uses.
"""
from __future__ import annotations

import collections
import contextlib
import gc
import math
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidParameterError

DEFAULT_SPIN_S = 3e-4
"""Busy-wait window before each deadline [s]."""
REALTIME_PRIORITY = 10
"""SCHED_FIFO priority of the real-time threads (a paced loop, the USB driver's I/O threads)
where the system allows it (Linux, with CAP_SYS_NICE or an ``rtprio`` limit): above every
normal process, so that a busy neighbour on the other core can no longer hold a tick or a
USB transfer back (measured with 1 CPU-stress process and a loaded machine: missed deadlines
from ~17 % to 0.06 %); low among real-time threads (the kernel's own run above it). The
kernel still keeps 5 % of each core for normal processes (``sched_rt_runtime_us``)."""
REALTIME_ENV = "FALCON_PLAN_REALTIME"
"""Set to 0 to keep every thread at its normal priority."""
RESET_ON_FORK = getattr(os, "SCHED_RESET_ON_FORK", 0)
"""Added to the real-time policy: a process started from a real-time thread (the recording
process, a replan worker, the C compiler that builds a kernel) starts at normal priority
instead of inheriting SCHED_FIFO. Without it, the recording process started while a hold ran
imported its modules at real-time priority for 100-140 ms and the hold, sharing 2 cores
with it, missed 74-114 ticks in a row (the simulated Falcon, which lives the skipped ticks
under the held command, lost its grip in 3 of 6 runs)."""


_gc_pauses = 0
_gc_was_enabled = False
_gc_lock = threading.Lock()


@contextlib.contextmanager
def gc_paused() -> Iterator[None]:
    """Python's cyclic garbage collector off for the duration of a real-time loop, as it
    was afterwards. Reference counting still frees almost everything; what the collector
    would do waits for the end of the run. Why: a full collection stops every thread, for
    ~80 ms in a process holding 140 000 objects (measured in the test suite's process), and
    the device's watchdog trips at 100 ms. Pauses may overlap (threads, nesting): the
    collector comes back when the last one ends, not the first."""
    global _gc_pauses, _gc_was_enabled
    with _gc_lock:
        if _gc_pauses == 0:
            _gc_was_enabled = gc.isenabled()
            gc.disable()
        _gc_pauses += 1
    try:
        yield
    finally:
        with _gc_lock:
            _gc_pauses -= 1
            if _gc_pauses == 0 and _gc_was_enabled:
                gc.enable()


def realtime_thread() -> bool:
    """Move the calling thread to real-time scheduling (SCHED_FIFO at
    :data:`REALTIME_PRIORITY`); True if that took effect, False where the system does not
    allow it or :data:`REALTIME_ENV` is 0 (the thread then keeps its normal priority)."""
    if os.environ.get(REALTIME_ENV, "1").strip() == "0":
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO | RESET_ON_FORK, os.sched_param(REALTIME_PRIORITY))
    except (AttributeError, OSError):     # not Linux, or not permitted
        return False
    return True


def realtime_allowed() -> str:
    """Whether this process's threads get real-time priority (:func:`realtime_thread`), tried
    on a thread of its own that then ends (nothing else changes): ``granted``, ``off`` (set so
    by :data:`REALTIME_ENV`) or ``refused`` (not Linux, or neither CAP_SYS_NICE nor an
    ``rtprio`` limit)."""
    if os.environ.get(REALTIME_ENV, "1").strip() == "0":
        return "off"
    result: list[bool] = []
    probe = threading.Thread(target=lambda: result.append(realtime_thread()), name="falcon-plan rt probe")
    probe.start()
    probe.join()
    return "granted" if result and result[0] else "refused"


REALTIME_HINT = (f"allow it: run as root, or give your user a real-time limit (a line such as "
                 f"`youruser - rtprio {REALTIME_PRIORITY}` in /etc/security/limits.conf, then log in again); "
                 f"{REALTIME_ENV}=0 turns it off on purpose")
"""How to let the real-time threads have their priority (said where it was refused)."""


SWITCH_INTERVAL_S = 2e-4
"""The interpreter's switch interval while a real-time loop runs or an off-loop worker computes
[s]: a thread waiting for the GIL gets it after this long (Python's default, 5 ms, lets any
other thread, a planning worker, the USB driver's threads or an emulated device, hold the
control loop back for four periods)."""
_switch_lock = threading.Lock()
_switch_users = 0
_switch_before = 0.0

GIVE_WAY_MAX_S = 0.003
"""Longest :func:`give_way` waits for a real-time loop's tick to end [s] (a tick takes about
0.2-0.5 ms; a loop stuck longer is its watchdog's business, not the computation's)."""
_loop_idle = threading.Event()
_loop_idle.set()
_yielding: set[int] = set()     # the threads that give way (giving_way)


@contextlib.contextmanager
def loop_tick() -> Iterator[None]:
    """The duration of one tick of a real-time loop that runs while the same process computes
    (the hold while a run is prepared): a thread :func:`giving_way` waits for its end at its
    next :func:`give_way`. Not nested; one such loop at a time."""
    _loop_idle.clear()
    try:
        yield
    finally:
        _loop_idle.set()


@contextlib.contextmanager
def giving_way() -> Iterator[None]:
    """The calling thread gives way to real-time loop ticks (:func:`give_way`) for the duration:
    a thread that computes beside such a loop (the caller preparing a run during a hold). Only
    such threads do: the loop's own and the USB driver's threads, which run the tick, never
    wait for it."""
    me = threading.get_ident()
    _yielding.add(me)
    try:
        yield
    finally:
        _yielding.discard(me)


def give_way() -> None:
    """In a thread :func:`giving_way`, let a real-time loop's tick (:func:`loop_tick`) finish
    before computing on; long computations call this between steps of well under a period
    (each chunk of a batched kernel, each step of a Riccati pass). The tick's threads (the
    loop's own, the USB driver's writer and reader) each take the interpreter lock in turn;
    with the computation busy, each waited a switch interval for it, and the hold ticked at
    200-300 Hz instead of 1 kHz (its commands ringing at the limit) while a run's gain schedule
    was designed. About 0.1 us when no loop ticks or the thread does not give way."""
    if not _loop_idle.is_set() and threading.get_ident() in _yielding:
        _loop_idle.wait(GIVE_WAY_MAX_S)


class responsive_gil:
    """Context manager: :data:`SWITCH_INTERVAL_S` as the interpreter's switch interval while
    anyone is inside (nested and concurrent uses share it; the old value returns when the last
    one leaves)."""

    def __enter__(self) -> "responsive_gil":
        global _switch_users, _switch_before
        with _switch_lock:
            if _switch_users == 0:
                _switch_before = sys.getswitchinterval()
                sys.setswitchinterval(min(_switch_before, SWITCH_INTERVAL_S))
            _switch_users += 1
        return self

    def __exit__(self, *exc: object) -> None:
        global _switch_users
        with _switch_lock:
            _switch_users -= 1
            if _switch_users == 0:
                sys.setswitchinterval(_switch_before)


CPU_LATENCY_FILE = "/dev/cpu_dma_latency"
"""Linux's PM QoS CPU-latency request: while a process keeps it open with a 32-bit value
written to it, no CPU enters an idle state that takes longer than that [us] to leave (what
``cyclictest`` does while it measures)."""
_idle_lock = threading.Lock()
_idle_users = 0
_idle_request: "object | None" = None


class shallow_cpu_idle:
    """Context manager: while anyone is inside (nested and concurrent uses share one request),
    the CPUs idle only in states they leave at once (a CPU-latency request of 0 us,
    :data:`CPU_LATENCY_FILE`), so that the loop, the USB reader and the USB writer, which wake
    one another every period, do not each pay a deep idle state's exit latency. On this 2-core
    VM an idle core halts and waking it costs hundreds of microseconds: the emulated Falcon at
    1 kHz, all 29 benchmark problems, quiet machine, missed 21-173 deadlines a round and
    tracked above 0.3 mm on 1-2 problems (max 0.56-1.19 mm); holding the request, 2-32 missed
    and none above 0.3 mm (max 0.04-0.27 mm). Costs power while a run lasts. Where the file
    is not writable (not root and no udev rule for it), or with :data:`REALTIME_ENV` 0,
    nothing changes; :attr:`active` says whether the request holds."""

    def __init__(self) -> None:
        self.active = False

    def __enter__(self) -> "shallow_cpu_idle":
        global _idle_users, _idle_request
        with _idle_lock:
            if _idle_users == 0 and os.environ.get(REALTIME_ENV, "1").strip() != "0":
                try:
                    request = open(CPU_LATENCY_FILE, "wb", buffering=0)  # noqa: SIM115 - held open
                    request.write((0).to_bytes(4, sys.byteorder, signed=True))
                    _idle_request = request
                except OSError:
                    _idle_request = None
            _idle_users += 1
            self.active = _idle_request is not None
        return self

    def __exit__(self, *exc: object) -> None:
        global _idle_users, _idle_request
        with _idle_lock:
            _idle_users -= 1
            if _idle_users == 0 and _idle_request is not None:
                with contextlib.suppress(OSError):
                    _idle_request.close()   # closing the file ends the request
                _idle_request = None


@contextlib.contextmanager
def realtime_priority() -> Iterator[bool]:
    """The calling thread at real-time priority (:func:`realtime_thread`) for the duration,
    then back to the scheduling it had; yields whether the priority was raised."""
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
    except (AttributeError, OSError):
        yield False
        return
    raised = (before[0] & ~RESET_ON_FORK) != os.SCHED_FIFO and realtime_thread()
    try:
        yield raised
    finally:
        if raised:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, *before)


@contextlib.contextmanager
def realtime_section() -> Iterator[None]:
    """Everything a real-time loop's process needs while the loop lasts (a paced run, a hold,
    the doctor's paced loop): the collector paused (:func:`gc_paused`), the calling thread at
    real-time priority (:func:`realtime_priority`), the GIL handed back often
    (:class:`responsive_gil`) and the CPUs out of deep idle states (:class:`shallow_cpu_idle`)."""
    with gc_paused(), realtime_priority(), responsive_gil(), shallow_cpu_idle():
        yield


ARRIVAL_LEAD_S = 4e-4
"""Where a paced loop's deadlines sit after the phase at which the device's readings arrive
[s] (:meth:`DeadlineTimer.align`). A Falcon moves its packets in 1 ms USB frames, so at a
1 kHz loop the phase between the loop's deadlines and the frames stays put for a whole run
and decides how old the reading each command is computed from is, and in which frame the
command leaves: the loop's delay. Measured on the emulated Falcon (threaded USB, the device
on wall-clock time, readings arriving about 0.1 ms after a frame boundary), LQR, 4 problems
a phase: deadlines 0.2-0.6 ms after the boundary tracked at 0.033-0.039 mm RMS (one run
0.11), deadlines 0.8-1.0 ms after it at 0.15-0.21 mm in 6 of 8 runs (a command handed over
late in a frame often misses it: one period more delay than the LQR was designed for).
0.4 ms after the arrivals' early edge (:func:`arrival_phase`) puts the deadlines about 0.5 ms
after the boundary (with the mean arrival instead, a loaded host's late reader wakeups put
them at 0.65-0.8 ms in 4 of 29 runs, which tracked at 0.17-0.24 mm), and leaves the loop
time to compute before the next: the exchange after a deadline waits for the next reading,
which comes about a period less this lead later (see
:data:`~falcon_plan.devices.usb_falcon.STATUS_WAIT_PERIODS`)."""
ARRIVAL_LOCK_MIN_RESULTANT = 0.5
"""Smallest mean resultant length of the arrival phases for which the arrivals are locked
to the loop's period (1: every arrival at the same phase; arrivals spread evenly give ~0,
e.g. 1 ms frames against an 800 Hz loop, where no single phase exists; a loaded host's late
reader wakeups spread them too, to about 0.6 in the worst holds measured)."""


ARRIVAL_EDGE_QUANTILE = 0.1
"""The quantile of the arrival phases taken as the phase at which readings arrive: their early
edge, where the frame delivers them to a reader thread that wakes at once (a loaded host
wakes it later, which moves the mean but not the edge)."""


def arrival_phase(arrivals_s: Any, period_s: float) -> float | None:
    """The phase [s, in [0, period_s)] at which readings arrive, modulo the loop period, from
    their arrival times ``arrivals_s`` [s, monotonic]: the :data:`ARRIVAL_EDGE_QUANTILE` of
    their phases around the circular mean. None with fewer than 16 arrivals or when they hold
    no phase (mean resultant length below :data:`ARRIVAL_LOCK_MIN_RESULTANT`)."""
    t = np.asarray(arrivals_s, dtype=float)
    if t.size < 16:
        return None
    phases = np.mod(t, period_s)
    mean = np.exp(2j * np.pi * phases / period_s).mean()
    if abs(mean) < ARRIVAL_LOCK_MIN_RESULTANT:
        return None
    centre = np.angle(mean) / (2.0 * np.pi) * period_s
    around = np.mod(phases - centre + 0.5 * period_s, period_s) - 0.5 * period_s
    return float((centre + np.quantile(around, ARRIVAL_EDGE_QUANTILE)) % period_s)


@dataclass(frozen=True)
class TimingSummary:
    """Statistics of tick start errors (actual start minus deadline) over one run.

    Attributes
    ----------
    ticks : number of ticks timed.
    missed_deadlines : ticks that started more than one period late.
    skipped_slots : deadline slots skipped when resynchronising after misses.
    p50_us, p99_us, max_us : percentiles of the start error [µs] (None if nothing was timed).
    busy_p50_us, busy_p99_us : percentiles of the tick's busy time, from its start to the next
        wait [µs] (the loop's own work and its device I/O; None with fewer than 2 ticks).
    work_p50_us, work_p99_us : percentiles of the tick's work after its device I/O, from
        :meth:`DeadlineTimer.io_done` to the next wait [µs] (controller, kinematics, guards,
        logging; None when the loop never marked its I/O).
    aligned_shift_us : how far the deadline grid was moved to lock onto the device's reading
        arrivals (:meth:`DeadlineTimer.align`) [µs]; None when it was not.
    work_cpu_p50_us, work_cpu_p99_us : the same span as ``work`` in the loop thread's own CPU
        time [µs] (:func:`time.thread_time`): the tick's computation without the time other
        threads of the process (the USB driver's, an emulated device's) held the interpreter
        or the core meanwhile.
    longest_late_us : the latest any tick started after its own deadline [µs], the missed ones
        included (a host stall; the start-error percentiles are taken after resynchronising,
        so they leave it out); None when nothing was timed.
    """

    ticks: int
    missed_deadlines: int
    skipped_slots: int
    p50_us: float | None
    p99_us: float | None
    max_us: float | None
    busy_p50_us: float | None = None
    busy_p99_us: float | None = None
    work_p50_us: float | None = None
    work_p99_us: float | None = None
    aligned_shift_us: float | None = None
    work_cpu_p50_us: float | None = None
    work_cpu_p99_us: float | None = None
    longest_late_us: float | None = None

    @property
    def missed_share(self) -> float:
        """Missed deadlines over ticks (0 if no tick)."""
        return self.missed_deadlines / self.ticks if self.ticks else 0.0

    def to_dict(self) -> dict[str, float | int | None]:
        """JSON-ready dict."""
        return {"ticks": self.ticks, "missed_deadlines": self.missed_deadlines,
                "skipped_slots": self.skipped_slots, "missed_share": self.missed_share,
                "jitter_p50_us": self.p50_us, "jitter_p99_us": self.p99_us,
                "jitter_max_us": self.max_us, "busy_p50_us": self.busy_p50_us,
                "busy_p99_us": self.busy_p99_us, "work_p50_us": self.work_p50_us,
                "work_p99_us": self.work_p99_us, "aligned_shift_us": self.aligned_shift_us,
                "work_cpu_p50_us": self.work_cpu_p50_us, "work_cpu_p99_us": self.work_cpu_p99_us,
                "longest_late_us": self.longest_late_us}


class DeadlineTimer:
    """Absolute-deadline pacing of a periodic loop (see the module docstring).

    Parameters
    ----------
    rate_hz : loop rate [Hz].
    spin_s : busy-wait window before each deadline [s] (default 0.3 ms).
    capacity : expected number of ticks (the start-error buffer grows if exceeded).
    clock, sleep : injectable for tests (default :func:`time.perf_counter`, :func:`time.sleep`).
    record : keep every tick's start error for :meth:`summary` (False for loops without an
        end, such as a device's own pacing: only the missed deadlines are counted).
    """

    def __init__(self, rate_hz: float, spin_s: float = DEFAULT_SPIN_S, capacity: int = 1024,
                 clock: Callable[[], float] = time.perf_counter,
                 sleep: Callable[[float], None] = time.sleep, record: bool = True) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidParameterError(f"rate_hz must be a positive number, got {rate_hz!r}")
        if not 0.0 <= spin_s < 1.0 / rate_hz:
            raise InvalidParameterError(f"spin_s must be in [0, one period), got {spin_s!r}")
        self.period_s = 1.0 / float(rate_hz)
        self.spin_s = float(spin_s)
        self._clock = clock
        self._sleep = sleep
        self._record_ticks = bool(record)
        self._t0: float | None = None
        self._late = np.empty(max(int(capacity), 16))
        self._busy = np.empty_like(self._late)
        self._work = np.full_like(self._late, np.nan)
        self._work_cpu = np.full_like(self._late, np.nan)
        self._n = 0
        self._last_start: float | None = None
        self._io_end: float | None = None
        self._io_end_cpu = 0.0
        self._waiting: int | None = None   # the slot a wait ended early for (by ``wake``)
        self.missed_deadlines = 0
        self._longest_late_s = 0.0
        self.skipped_slots = 0
        self.aligned_shift_s: float | None = None
        self.running_slot: int | None = None
        """The slot of the tick under way: the last that :meth:`wait` returned (None before)."""

    @property
    def t0(self) -> float:
        """Clock time of slot 0 [s] (set by :meth:`start`)."""
        if self._t0 is None:
            raise RuntimeError("DeadlineTimer.start() was not called")
        return self._t0

    def start(self, t0: float | None = None) -> float:
        """Set slot 0's deadline to ``t0`` (default: now) on the timer's clock; returns it."""
        self._t0 = self._clock() if t0 is None else float(t0)
        return self._t0

    def deadline(self, slot: int) -> float:
        """Clock time at which ``slot`` is due [s]."""
        return self.t0 + slot * self.period_s

    def to_monotonic_s(self) -> float:
        """What to add to a time on the timer's clock to put it on :func:`time.monotonic`'s, the
        clock device I/O stamps arrivals with [s] (0 up to the reading's jitter on Linux)."""
        return time.monotonic() - self._clock()

    def current_deadline(self) -> float:
        """When the tick that runs now was due: the latest deadline at or before now [s,
        monotonic (:meth:`to_monotonic_s`)]."""
        to_monotonic = self.to_monotonic_s()
        now = self._clock()
        return self.deadline(math.floor((now - self.t0) / self.period_s)) + to_monotonic

    def align(self, phase_s: float, lead_s: float = ARRIVAL_LEAD_S) -> float:
        """Move the grid later by less than one period so that every deadline falls ``lead_s``
        [s] after ``phase_s`` [s] modulo the period (the phase at which the device's readings
        arrive, :func:`arrival_phase`); returns the shift [s]. The tick in progress simply
        lasts longer: no deadline is missed by it."""
        shift = (float(phase_s) + float(lead_s) - self.t0) % self.period_s
        self._t0 = self.t0 + shift
        self.aligned_shift_s = shift
        return shift

    def wait(self, slot: int, wake: threading.Event | None = None) -> int | None:
        """Wait for ``slot``'s deadline and return the slot the tick runs in.

        Returns ``slot`` when on time; when the tick starts more than one period late, counts
        a missed deadline and returns the current slot (``> slot``) instead. ``wake``: an
        event that ends the wait as soon as it is set (e.g. a cancel, so that this very tick's
        command can change): then returns None without starting the tick; call ``wait(slot)``
        again when ready.
        """
        deadline = self.deadline(slot)
        entry = self._clock()
        if self._waiting != slot:        # the tick's first wait: its busy and work times end here
            self._waiting = slot
            if self._last_start is not None and self._record_ticks:
                self._busy[self._n - 1] = entry - self._last_start
                if self._io_end is not None:
                    self._work[self._n - 1] = entry - self._io_end
                    self._work_cpu[self._n - 1] = time.thread_time() - self._io_end_cpu
            self._io_end = None
        remaining = deadline - entry
        if remaining > self.spin_s:
            if wake is None:
                self._sleep(remaining - self.spin_s)
            elif wake.wait(remaining - self.spin_s):
                return None
        now = self._clock()
        while now < deadline:
            if wake is not None and wake.is_set():
                return None
            now = self._clock()
        self._waiting = None
        late = now - deadline
        self._longest_late_s = max(self._longest_late_s, late)
        if late > self.period_s:
            self.missed_deadlines += 1
            current = slot + int(late // self.period_s)
            self.skipped_slots += current - slot
            slot = current
            late = now - self.deadline(slot)
        self._record(late)
        self._last_start = now
        self.running_slot = slot
        return slot

    def io_done(self) -> None:
        """Mark the end of this tick's device I/O: the time from here to the next
        :meth:`wait` is the tick's work (``TimingSummary.work_p50_us``)."""
        self._io_end = self._clock()
        self._io_end_cpu = time.thread_time()

    def _record(self, late_s: float) -> None:
        if not self._record_ticks:
            return
        if self._n == self._late.shape[0]:
            self._late = np.concatenate([self._late, np.empty_like(self._late)])
            self._busy = np.concatenate([self._busy, np.empty_like(self._busy)])
            self._work = np.concatenate([self._work, np.full_like(self._work, np.nan)])
            self._work_cpu = np.concatenate([self._work_cpu, np.full_like(self._work_cpu, np.nan)])
        self._late[self._n] = late_s
        self._n += 1

    @property
    def start_errors_s(self) -> np.ndarray:
        """Start error of every timed tick [s] (a copy)."""
        return self._late[: self._n].copy()

    def summary(self) -> TimingSummary:
        """Tick count, missed deadlines, skipped slots and start-error percentiles."""
        shift_us = None if self.aligned_shift_s is None else self.aligned_shift_s * 1e6
        if self._n == 0:
            return TimingSummary(0, self.missed_deadlines, self.skipped_slots, None, None, None,
                                 aligned_shift_us=shift_us)
        late_us = self._late[: self._n] * 1e6
        p50, p99 = np.percentile(late_us, [50.0, 99.0])
        busy50 = busy99 = None
        (work50, work99), (cpu50, cpu99) = self._percentiles(self._work), self._percentiles(self._work_cpu)
        if self._n >= 2:  # the last tick's busy time ends with the loop, not at a wait
            busy50, busy99 = (float(x) for x in np.percentile(self._busy[: self._n - 1] * 1e6, [50.0, 99.0]))
        return TimingSummary(self._n, self.missed_deadlines, self.skipped_slots,
                             float(p50), float(p99), float(late_us.max()), busy50, busy99, work50, work99,
                             shift_us, cpu50, cpu99, 1e6 * self._longest_late_s)

    def _percentiles(self, spans_s: np.ndarray) -> tuple[float | None, float | None]:
        """p50 and p99 [µs] of the recorded ``spans_s`` [s] of the ticks before the last one
        (whose span ends with the loop, not at a wait); (None, None) when none was recorded."""
        spans = spans_s[: max(self._n - 1, 0)]
        spans = spans[np.isfinite(spans)]
        if not spans.size:
            return None, None
        p50, p99 = np.percentile(spans * 1e6, [50.0, 99.0])
        return float(p50), float(p99)


class HandOvers:
    """When the last ``size`` ticks of a loop were due [s, monotonic], to tell which tick a
    reading was read for (:meth:`reading_tick`). A paced loop notes each slot's deadline,
    missed slots included; a loop without deadlines (a simulation stepped as fast as it goes)
    notes when it handed each tick's command to the driver."""

    def __init__(self, size: int = 8) -> None:
        self._ticks: deque[tuple[int, float]] = deque(maxlen=size)

    def note(self, tick: int, due_s: float) -> None:
        """Tick ``tick`` was due at ``due_s`` [s, monotonic] (notes come in tick order)."""
        self._ticks.append((int(tick), float(due_s)))

    def note_slots(self, timer: "DeadlineTimer", after: int, tick: int) -> None:
        """The slots of a loop paced by ``timer`` after slot ``after`` up to ``tick`` were due at
        their deadlines (the missed ones too: a reading that arrives after a missed slot's
        deadline was read for the slot after it)."""
        to_monotonic = timer.to_monotonic_s()
        for slot in range(max(int(after) + 1, int(tick) + 1 - self._ticks.maxlen), int(tick) + 1):
            self.note(slot, timer.deadline(slot) + to_monotonic)

    def reading_tick(self, arrived_s: float) -> int | None:
        """The tick a reading that arrived at ``arrived_s`` [s, monotonic] was read for: the one
        after the last tick due before it arrived. Threaded I/O answers a hand-over with the
        first status after it; when none comes in time (a host stall) it returns the newest,
        which came before the tick's deadline and was read for an earlier tick. The deadline,
        not the hand-over, decides: a command handed over late (the loop held up) is answered
        by a status that arrives on the device's frame grid at the time of the next tick's
        reading, and it is that tick's reading (its age is the usual one). None when nothing
        was noted yet; -1 when the reading is older than every tick remembered."""
        if not self._ticks:
            return None
        for tick, due_s in reversed(self._ticks):
            if due_s < arrived_s:
                return tick + 1
        return -1


ARRIVAL_LOCK_READINGS = 64
"""New readings an :class:`ArrivalLock` collects before it moves its timer's grid."""


class ArrivalLock:
    """Moves the grid of ``timer`` once onto the phase at which a device's readings arrive
    (:func:`arrival_phase`, :meth:`DeadlineTimer.align`), from ``readings`` new readings of a
    paced loop (a run's hold, a diagnostic's hold), so that every paced loop on a USB Falcon
    sees the same delay. Readings without a phase (a burst of host load) are dropped and the
    next ``readings`` tried, for as long as moving is allowed. The move waits for a reference at
    rest: moving the grid by s [s] shifts the reference in time under the device, an error of
    its speed times s (5.7 to 65 counts on every leg, measured, when it moved during the approach
from homing)."""

    def __init__(self, timer: DeadlineTimer, readings: int = ARRIVAL_LOCK_READINGS) -> None:
        self.timer = timer
        self.readings = int(readings)
        self.done = False
        """True once the grid moved or the lock gave up (no phase, or moving was not allowed)."""
        self._arrivals: collections.deque[float] = collections.deque(maxlen=self.readings)
        # once, here and not in the loop: numpy's first quantile of a process took 7.5 ms, a
        # stall of 8-9 ms at the same tick of every run that aligned its grid
        arrival_phase(np.arange(16) * timer.period_s, timer.period_s)

    def note(self, arrived_s: float, may_move: bool = True, still: bool = True) -> None:
        """Note a new reading's arrival ``arrived_s`` [s, monotonic]; with ``readings`` of
        them and ``still`` (the loop's reference is at rest now), move the grid onto the phase of
        the last ``readings`` and be done; without a phase, start again. Once ``may_move`` is
        False, be done without moving."""
        if self.done:
            return
        if not may_move:
            self.done = True
            return
        self._arrivals.append(float(arrived_s))
        if len(self._arrivals) < self.readings or not still:
            return
        phase = arrival_phase(np.asarray(self._arrivals) - self.timer.to_monotonic_s(), self.timer.period_s)
        self._arrivals.clear()
        if phase is not None:
            self.timer.align(phase)
            self.done = True


def run_bare_loop(rate_hz: float, ticks: int, spin_s: float = DEFAULT_SPIN_S) -> TimingSummary:
    """The timer's own jitter: a loop that does nothing but wait for ``ticks`` deadlines at
    ``rate_hz`` with the executor's scheme and busy-wait window ``spin_s`` [s] (the reference
    of the executor benchmark), at the priority a paced executor run has
    (:func:`realtime_priority`)."""
    timer = DeadlineTimer(rate_hz, spin_s, capacity=ticks)
    with realtime_priority():
        timer.start(timer._clock() + timer.period_s)
        slot = 0
        while slot < ticks:
            slot = timer.wait(slot) + 1
    return timer.summary()
