"""The deadline timer: absolute deadlines (no drift), sleep then spin, missed deadlines."""
from __future__ import annotations

import threading

import pytest

from falcon_plan.errors import InvalidParameterError
import numpy as np

from falcon_plan.timing import ARRIVAL_LEAD_S, ArrivalLock, DeadlineTimer, arrival_phase, run_bare_loop


class FakeClock:
    """A clock that only moves when slept on or when work is simulated; spinning costs 1 µs."""

    def __init__(self) -> None:
        self.now = 0.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        self.now += 1e-6
        return self.now

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)
        self.now += s + 50e-6  # the OS oversleeps by 50 µs


def test_deadlines_are_absolute_and_sleep_stops_short_of_them():
    fake = FakeClock()
    timer = DeadlineTimer(1000.0, spin_s=3e-4, clock=fake.clock, sleep=fake.sleep)
    timer.start(0.0)
    for k in range(100):
        assert timer.wait(k) == k
        fake.now += 0.4e-3  # the tick's work
    # slept to 0.3 ms before each deadline, spun the rest: every start within a few µs
    assert all(s <= 1e-3 - 0.4e-3 - 3e-4 + 1e-5 for s in fake.sleeps[1:])
    summary = timer.summary()
    assert summary.ticks == 100 and summary.missed_deadlines == 0
    assert summary.max_us < 5.0
    # no drift: tick 99 ran at 99 ms, not 99 x (period + overhead)
    assert fake.now == pytest.approx(0.099 + 0.4e-3, abs=1e-5)


def test_a_late_tick_counts_as_missed_and_resynchronises_without_catch_up_burst():
    fake = FakeClock()
    timer = DeadlineTimer(1000.0, clock=fake.clock, sleep=fake.sleep)
    timer.start(0.0)
    assert timer.wait(0) == 0
    fake.now += 3.5e-3  # a 3.5 ms hiccup
    slot = timer.wait(1)
    assert slot == 3  # slots 1 and 2 skipped; the loop runs in the current slot
    assert timer.missed_deadlines == 1 and timer.skipped_slots == 2
    assert timer.wait(slot + 1) == 4  # back on the grid
    # a tick late by less than one period is late, not missed
    fake.now += 1.5e-3
    assert timer.wait(5) == 5 and timer.missed_deadlines == 1
    # the summary's jitter is after resynchronising; the stall itself is its longest lateness
    summary = timer.summary()
    assert summary.max_us < 1000.0 and summary.longest_late_us == pytest.approx(2500.0, abs=5.0)


def test_a_wake_event_ends_the_wait_and_the_tick_starts_at_the_next_one():
    """A set ``wake`` ends the wait at once, without starting the tick (the loop changes the
    tick's command, then waits again); the tick's work ended at its first wait."""
    fake = FakeClock()
    timer = DeadlineTimer(1000.0, spin_s=3e-4, clock=fake.clock, sleep=fake.sleep)
    timer.start(0.0)
    assert timer.wait(0) == 0
    fake.now += 0.4e-3                          # tick 0's work
    wake = threading.Event()
    wake.set()
    assert timer.wait(1, wake=wake) is None
    assert timer.summary().ticks == 1 and not fake.sleeps
    fake.now += 0.2e-3                          # what the wake asked for (e.g. a brake's first command)
    assert timer.wait(1) == 1
    summary = timer.summary()
    assert summary.ticks == 2 and summary.missed_deadlines == 0
    assert summary.busy_p50_us == pytest.approx(400.0, abs=5.0)   # tick 0's busy time, to its first wait


def test_a_wake_from_another_thread_ends_a_long_wait():
    """Set from another thread while the loop waits for a deadline 30 s away: the wait ends
    (without the wake it would last the 30 s)."""
    timer = DeadlineTimer(1.0 / 30.0)
    timer.start()
    wake = threading.Event()
    threading.Thread(target=wake.set).start()
    assert timer.wait(1, wake=wake) is None
    assert timer.summary().ticks == 0


def test_arrival_phase_finds_frame_arrivals_and_none_where_there_is_no_phase():
    """Readings arriving 0.1 ms after 1 ms frame boundaries, with a late tail (a reader thread
    held up), have phase 0.1 ms at a 1 kHz loop (their early edge: the tail does not move
    it), also across the wrap at 0 (around the circular mean, not the arithmetic one); 1 ms
    frames seen by an 800 Hz loop have no phase."""
    rng = np.random.default_rng(3)
    frames = 1000.0 + np.arange(200) * 1e-3
    late = np.where(rng.random(200) < 0.3, rng.uniform(0, 4e-4, 200), 0.0)
    assert arrival_phase(frames + 1e-4 + late, 1e-3) == pytest.approx(1e-4, abs=1e-6)
    wrapped = frames + np.where(np.arange(200) % 2 == 0, 0.96e-3, 0.06e-3)   # half at -0.04, half at +0.06
    assert arrival_phase(wrapped, 1e-3) == pytest.approx(0.96e-3, abs=1e-6)
    at_800_hz = 1000.0 + np.arange(200) * 1e-3 + 1e-4
    assert arrival_phase(at_800_hz, 1.25e-3) is None
    assert arrival_phase(frames[:10], 1e-3) is None     # too few to say


def test_align_moves_the_grid_later_by_less_than_a_period_without_a_missed_deadline():
    """The deadlines after :meth:`DeadlineTimer.align` sit ``lead`` after the arrival phase
    (modulo the period); the tick in progress only lasts longer; the shift is reported."""
    fake = FakeClock()
    timer = DeadlineTimer(1000.0, clock=fake.clock, sleep=fake.sleep)
    timer.start(0.0107)                      # phase 0.7 ms
    for k in range(5):
        assert timer.wait(k) == k
    shift = timer.align(phase_s=1e-4)        # readings arrive at 0.1 ms: deadlines at 0.1 ms + lead
    assert 0.0 <= shift < 1e-3
    assert timer.deadline(5) % 1e-3 == pytest.approx(1e-4 + ARRIVAL_LEAD_S, abs=1e-9)
    for k in range(5, 10):
        assert timer.wait(k) == k
    summary = timer.summary()
    assert summary.missed_deadlines == 0 and summary.aligned_shift_us == pytest.approx(shift * 1e6)
    assert DeadlineTimer(1000.0).summary().aligned_shift_us is None


def _phase_gap(t_s: float, phase_s: float, period_s: float = 1e-3) -> float:
    """``t_s`` less ``phase_s`` modulo the period, in [-period/2, period/2) [s]."""
    return (t_s - phase_s + period_s / 2) % period_s - period_s / 2


def test_an_arrival_lock_moves_the_grid_once_after_its_readings_and_only_if_allowed():
    """The lock moves the grid at its last reading (not before, not again); with moving not
    allowed then (e.g. too little of a hold left), it gives up and the grid stays; readings
    without a phase are dropped and the next ones tried."""
    import time as _time

    offset = _time.monotonic()        # the timers below run on the monotonic clock, as arrivals
    for may_move in (True, False):
        timer = DeadlineTimer(1000.0, clock=_time.monotonic)
        timer.start(offset + 0.0107)
        lock = ArrivalLock(timer, readings=20)
        arrivals = offset + 1e-4 + np.arange(30) * 1e-3
        for t in arrivals[:19]:
            lock.note(t)
        assert not lock.done and timer.aligned_shift_s is None
        lock.note(arrivals[19], may_move=may_move)
        assert lock.done
        if may_move:
            assert _phase_gap(timer.deadline(3), offset + 1e-4 + ARRIVAL_LEAD_S) == pytest.approx(0.0, abs=1e-5)
        else:
            assert timer.aligned_shift_s is None
        before = timer.t0
        for t in arrivals[20:]:
            lock.note(t)
        assert timer.t0 == before
    timer = DeadlineTimer(1000.0, clock=_time.monotonic)
    timer.start(offset + 0.0107)
    lock = ArrivalLock(timer, readings=20)
    for t in offset + np.arange(20) * 1.25e-3:          # spread over the period: no phase
        lock.note(t)
    assert not lock.done and timer.aligned_shift_s is None
    for t in offset + 0.1 + 1e-4 + np.arange(20) * 1e-3:
        lock.note(t)
    assert lock.done and timer.aligned_shift_s is not None


def test_an_arrival_lock_waits_for_a_reference_at_rest_and_uses_the_newest_readings():
    """While the loop's reference moves (``still`` False) the lock keeps collecting and does not
    move the grid; at the first still reading it moves onto the phase of the newest
    ``readings`` arrivals (here the device's phase changed meanwhile: the newest phase wins)."""
    import time as _time

    offset = _time.monotonic()
    timer = DeadlineTimer(1000.0, clock=_time.monotonic)
    timer.start(offset + 0.0107)
    lock = ArrivalLock(timer, readings=20)
    for t in offset + 1e-4 + np.arange(30) * 1e-3:          # an old phase, while moving
        lock.note(t, still=False)
    for t in offset + 0.0304 + np.arange(19) * 1e-3:        # a new phase, still moving
        lock.note(t, still=False)
    assert not lock.done and timer.aligned_shift_s is None
    lock.note(offset + 0.0304 + 19e-3, still=True)
    assert lock.done
    assert _phase_gap(timer.deadline(3), offset + 4e-4 + ARRIVAL_LEAD_S) == pytest.approx(0.0, abs=1e-5)


def test_a_reading_was_read_for_the_tick_after_the_last_tick_due_before_it_arrived():
    """A loop without deadlines notes its hand-overs: a reading that arrived after tick 7's was
    read for tick 8, one between ticks 4's and 5's for tick 5; one older than every tick
    remembered, for none (-1); before any note nothing is known (None)."""
    from falcon_plan.timing import HandOvers

    handovers = HandOvers(size=3)
    assert handovers.reading_tick(1.0) is None
    for tick, sent_s in ((5, 10.001), (6, 10.002), (7, 10.003)):
        handovers.note(tick, sent_s)
    assert handovers.reading_tick(10.0035) == 8
    assert handovers.reading_tick(10.0025) == 7
    assert handovers.reading_tick(10.0015) == 6
    assert handovers.reading_tick(10.0005) == -1
    handovers.note(8, 10.004)         # tick 5 is forgotten
    assert handovers.reading_tick(10.0015) == -1


def test_a_paced_loop_dates_its_readings_by_deadlines_not_hand_overs():
    """A paced loop notes its slots' deadlines, a missed slot's too. Slot 6 missed (its
    deadline passed, no hand-over): a reading that arrived after it was read for slot 7. A
    hand-over 0.7 ms late (slot 8's): the status that arrived before it, on the device's frame
    grid 0.6 ms after slot 8's deadline, is slot 9's reading, as a tick on time would get it;
    by hand-over times it would be slot 8's, a period older than it is, and an observer fed
    it so reads a period of motion as error. :meth:`DeadlineTimer.current_deadline` is the
    deadline of the slot that runs now."""
    import time

    from falcon_plan.timing import DeadlineTimer, HandOvers

    timer = DeadlineTimer(1000.0, clock=time.monotonic)
    t0 = timer.start(time.monotonic() - 0.0105)          # now: 0.5 ms into slot 10
    assert timer.current_deadline() == pytest.approx(t0 + 0.010, abs=1e-5)
    handovers = HandOvers(size=8)
    handovers.note_slots(timer, -1, 5)                   # slots 0..5
    handovers.note_slots(timer, 5, 7)                    # slot 6 missed
    assert handovers.reading_tick(t0 + 0.0066) == 7
    assert handovers.reading_tick(t0 + 0.0056) == 6
    handovers.note_slots(timer, 7, 8)                    # slot 8 handed over at t0 + 8.7 ms
    assert handovers.reading_tick(t0 + 0.0086) == 9
    assert handovers.reading_tick(t0 + 0.0005) == -1     # before every slot remembered


def test_timer_rejects_bad_settings():
    with pytest.raises(InvalidParameterError):
        DeadlineTimer(0.0)
    with pytest.raises(InvalidParameterError):
        DeadlineTimer(1000.0, spin_s=2e-3)
    with pytest.raises(RuntimeError):
        DeadlineTimer(1000.0).deadline(0)


def test_bare_loop_on_the_real_clock():
    summary = run_bare_loop(1000.0, 100)
    assert summary.ticks <= 100 <= summary.ticks + summary.skipped_slots
    assert summary.p50_us is not None and 0.0 <= summary.p50_us < 1000.0


def test_gc_paused_restores_the_collector_as_it_was() -> None:
    import gc

    from falcon_plan.timing import gc_paused

    assert gc.isenabled()
    with pytest.raises(RuntimeError):
        with gc_paused():
            assert not gc.isenabled()
            raise RuntimeError("a run that fails")
    assert gc.isenabled()
    gc.disable()
    try:
        with gc_paused():
            assert not gc.isenabled()
        assert not gc.isenabled()
    finally:
        gc.enable()


def test_overlapping_gc_pauses_end_with_the_last_one() -> None:
    """A planner's or a doctor's pause ending first does not bring the collector back
    under another thread's run that is still going (the run that started first ends last
    or first: either way the collector stays off until both have ended)."""
    import gc
    import threading

    from falcon_plan.timing import gc_paused

    first_in, first_may_end = threading.Event(), threading.Event()
    seen: list[bool] = []

    def first() -> None:
        with gc_paused():
            first_in.set()
            first_may_end.wait(5)

    thread = threading.Thread(target=first)
    thread.start()
    first_in.wait(5)
    with gc_paused():
        first_may_end.set()
        thread.join(5)
        seen.append(gc.isenabled())   # the first pause has ended, this one has not
    assert seen == [False] and gc.isenabled()


def test_realtime_priority_says_what_it_did_and_restores_the_thread(monkeypatch) -> None:
    """Inside, the thread is real-time exactly when the context says it raised it (where the
    system allows it; not at all with FALCON_PLAN_REALTIME=0); afterwards it has the
    scheduling it had."""
    import os

    from falcon_plan.timing import REALTIME_ENV, REALTIME_PRIORITY, RESET_ON_FORK, realtime_priority

    if not hasattr(os, "sched_getscheduler"):
        pytest.skip("no POSIX scheduling on this platform")
    before = os.sched_getscheduler(0), os.sched_getparam(0).sched_priority
    with realtime_priority() as raised:
        inside = os.sched_getscheduler(0) & ~RESET_ON_FORK, os.sched_getparam(0).sched_priority
        assert (inside == (os.SCHED_FIFO, REALTIME_PRIORITY)) == raised
    assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before
    monkeypatch.setenv(REALTIME_ENV, "0")
    with realtime_priority() as raised:
        assert not raised
        assert (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) == before


def test_a_process_started_from_a_real_time_thread_starts_at_normal_priority() -> None:
    """A child process (the recording process, a replan worker, the C compiler) started while
    the calling thread is real-time does not inherit the real-time policy: it would take a
    core from the loop for as long as it computes (the recording process's start, 100-140 ms,
    made a hold miss 74-114 ticks in a row on 2 cores). Where the system refuses real-time
    priority the child simply has the parent's normal policy."""
    import os
    import subprocess
    import sys

    from falcon_plan.timing import realtime_priority

    if not hasattr(os, "sched_getscheduler"):
        pytest.skip("no POSIX scheduling on this platform")
    normal = os.sched_getscheduler(0)
    with realtime_priority():
        child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
                               capture_output=True, text=True, check=True)
    assert int(child.stdout) == normal == os.SCHED_OTHER


def test_a_shallow_idle_request_is_held_once_while_anyone_is_inside(monkeypatch, tmp_path) -> None:
    """The CPU-latency request (a 0 written to the PM QoS file, held open) is made once for
    nested and concurrent users, held until the last one leaves, and ends when the file is
    closed; a file that cannot be opened (not root), or REALTIME_ENV=0, changes nothing."""
    import sys

    from falcon_plan import timing

    request = tmp_path / "cpu_dma_latency"
    request.write_bytes(b"")
    monkeypatch.setattr(timing, "CPU_LATENCY_FILE", str(request))
    monkeypatch.delenv(timing.REALTIME_ENV, raising=False)
    opened = []
    real_open = open

    def counting_open(*args, **kwargs):
        opened.append(args[0])
        return real_open(*args, **kwargs)

    monkeypatch.setattr("builtins.open", counting_open)
    with timing.shallow_cpu_idle() as outer:
        assert outer.active and request.read_bytes() == (0).to_bytes(4, sys.byteorder, signed=True)
        with timing.shallow_cpu_idle() as inner:
            assert inner.active
        assert timing._idle_request is not None and not timing._idle_request.closed   # the outer one holds it
    assert timing._idle_request is None and opened == [str(request)]

    monkeypatch.setattr(timing, "CPU_LATENCY_FILE", str(tmp_path / "no" / "such" / "file"))
    with timing.shallow_cpu_idle() as denied:
        assert not denied.active
    monkeypatch.setattr(timing, "CPU_LATENCY_FILE", str(request))
    monkeypatch.setenv(timing.REALTIME_ENV, "0")
    with timing.shallow_cpu_idle() as off:
        assert not off.active
    assert timing._idle_users == 0


def test_a_computation_gives_way_to_a_loop_tick_until_it_ends(monkeypatch) -> None:
    """In a thread ``giving_way``: ``give_way`` returns at once when no loop ticks, waits while
    a ``loop_tick`` lasts and returns when it ends, and never waits longer than
    ``GIVE_WAY_MAX_S`` (a stuck loop does not stop the computation). A thread not giving way
    (the loop's own, the USB driver's) never waits."""
    from falcon_plan import timing

    def computing(done: threading.Event | None = None) -> None:
        with timing.giving_way():
            timing.give_way()
            order.append("gave way")
            if done is not None:
                done.set()

    order: list[str] = []
    computing()                           # no loop: nothing to wait for
    assert order == ["gave way"]
    order.clear()
    monkeypatch.setattr(timing, "GIVE_WAY_MAX_S", 60.0)
    ticking, end_tick = threading.Event(), threading.Event()

    def loop() -> None:
        with timing.loop_tick():
            ticking.set()
            end_tick.wait(30.0)
            order.append("tick ended")

    looper = threading.Thread(target=loop)
    looper.start()
    assert ticking.wait(30.0)
    not_giving_way = threading.Thread(target=timing.give_way)    # not giving_way: no wait
    not_giving_way.start()
    not_giving_way.join(30.0)
    assert not not_giving_way.is_alive() and not end_tick.is_set()
    computation = threading.Thread(target=computing)
    computation.start()
    computation.join(0.2)
    assert computation.is_alive() and order == []      # still waiting for the tick
    end_tick.set()
    computation.join(30.0)
    looper.join(30.0)
    assert order == ["tick ended", "gave way"]
    # a tick that does not end: the wait is bounded
    monkeypatch.setattr(timing, "GIVE_WAY_MAX_S", 0.01)
    end_tick.clear()
    ticking.clear()
    stuck = threading.Thread(target=loop)
    stuck.start()
    assert ticking.wait(30.0)
    done = threading.Event()
    bounded = threading.Thread(target=computing, args=(done,))
    bounded.start()
    assert done.wait(30.0)
    end_tick.set()
    stuck.join(30.0)
