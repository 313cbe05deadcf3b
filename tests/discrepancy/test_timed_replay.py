"""The replay with real timing (issue 26, item 2): each logged command acts for the time it
really acted (zero-order hold through skipped slots and jitter), after a fractional transport
delay. The references are worlds written here: the plant run on a grid twice as fine, where
every send time and delay falls on a step, so a command's acting interval is exact there."""
from __future__ import annotations

import math

import numpy as np
import pytest

from falcon_plan.control import Controller
from falcon_plan.discrepancy.excitation import design_trajectory
from falcon_plan.discrepancy.replay import (TRANSPORT_DELAY_KEY, closed_loop_replay, log_controller,
                                            tick_schedule, transport_delay_samples, with_transport_delay)
from falcon_plan.discrepancy.synth import synthesize_log
from falcon_plan.errors import LogFormatError
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import counts_to_position
from falcon_plan.sim.plant import SimPlant

RATE = 1000.0
MODEL = FalconModel()
EFFECTS = Effects(coulomb_Nm=0.004)


@pytest.fixture(scope="module")
def trajectory():
    return design_trajectory("mixed", 2.5, seed=4, rate_hz=RATE)


def _world(trajectory, sub: int, sent_sub: np.ndarray, delay_sub: int, drop: np.ndarray,
           reused: np.ndarray | None = None, held: bool = False) -> FalconLog:
    """The encoder PD run on a SimPlant stepped ``sub`` times per period (at sub x RATE) as the
    executor runs it: row k's reading is the status that came back after the previous row's
    exchange, the counts at step sub k, or, after skipped slots, at the step one period after
    that exchange (a host that stalled has no newer one); rows in ``reused`` had no new status
    and use the previous row's reading again; the PD divides the count difference by the slots
    between the exchanges that returned the two readings. Row k's command is sent at step
    ``sent_sub[k]`` and acts from ``sent_sub[k] + delay_sub`` until the next row's command
    starts (the firmware holds it through the rows in ``drop``, which are not logged and issue
    nothing). With ``held`` a hold's force acts until the first command arrives (the first
    row's command, as the executor's first read repeats the hold's last one) and the log says
    so (``zero_force_periods_before: 0``); else zero force acts until then. Returns the log
    with timing columns (us) as a host would write them."""
    controller = Controller(RATE, kp=10.0, kd=0.1)
    ref = trajectory.counts
    offsets = controller.offsets(ref, MODEL)
    plant = SimPlant(MODEL.with_effects(Effects()), rate_hz=sub * RATE, effects=EFFECTS)
    plant.reset(counts_to_position(np.rint(ref[0]), MODEL.params))  # where the replay starts
    n = ref.shape[0]
    keep = np.ones(n, bool)
    keep[drop] = False
    reuse = np.zeros(n, bool)
    if reused is not None:
        reuse[reused] = True
    rows = np.flatnonzero(keep)
    starts = {int(sent_sub[k]) + delay_sub: k for k in rows}
    acting = np.zeros(3)
    history = np.zeros((sub * n + 1, 3))
    enc, tc = np.zeros((n, 3), np.int64), np.zeros((n, 3), np.int64)
    read_us = np.zeros(n, np.int64)
    prev, v, last, gap = None, np.zeros(3), None, 1
    for h in range(sub * n):
        history[h] = plant.counts
        if h % sub == 0 and keep[h // sub]:
            k = h // sub
            if reuse[k] and last is not None:
                at = read_us[last] // 1000
            else:
                at = k if last is None or k - last == 1 else last + 1
            counts = history[sub * at].astype(float)
            v = v + controller.alpha * ((counts - (counts if prev is None else prev)) * RATE / gap - v)
            raw = controller.kp * (counts - ref[k]) + controller.kd * v + offsets[k]
            tc[k] = np.clip(np.floor(raw + 0.5), -4096, 4096)
            enc[k], read_us[k], prev = counts, at * 1000, counts
            gap, last = (1 if last is None else k - last), k
            if held and h == 0:
                acting = tc[k].astype(float)
        if h in starts:
            acting = tc[starts[h]].astype(float)
        plant.step_acting(acting)
    sent_us = np.rint(sent_sub * 1000.0 / sub).astype(np.int64)
    skipped = np.diff(rows, prepend=-1) - 1
    meta = {**controller.to_meta(), "params": MODEL.params.name, **({"zero_force_periods_before": "0"} if held else {})}
    return FalconLog(trajectory.t_s[rows], enc[rows], tc[rows], ref[rows], meta,
                     sent_us[rows], read_us[rows], skipped)


def _rms(log: FalconLog, counts: np.ndarray) -> float:
    return float(np.sqrt(np.mean((counts - log.enc) ** 2)))


def _replay(log: FalconLog) -> np.ndarray:
    return closed_loop_replay(log, EFFECTS, MODEL, RATE, log_controller(log))


def test_timed_loop_equals_the_compiled_loop_on_a_regular_log(trajectory) -> None:
    """Timing columns that say every tick ran on its slot: the Python loop that honours them
    gives exactly the compiled loop's counts (closed and open loop)."""
    log = synthesize_log(EFFECTS, trajectory, rate_hz=RATE)
    us = np.arange(len(log), dtype=np.int64) * 1000
    timed = FalconLog(log.t_s, log.enc, log.tc, log.ref, log.meta, us + 125, us, np.zeros(len(log), int))
    assert tick_schedule(log, RATE).regular and not tick_schedule(timed, RATE).regular
    shifted = with_transport_delay(timed, 1.875)  # sent 125 us late, acting on the slot
    assert np.array_equal(_replay(log), _replay(shifted))
    assert np.array_equal(closed_loop_replay(log, EFFECTS, MODEL, RATE, None),
                          closed_loop_replay(shifted, EFFECTS, MODEL, RATE, None))


def test_commands_are_held_through_skipped_slots(trajectory) -> None:
    """Skipped slots (the host was late): the previous command keeps acting and no command is
    computed in them. The replay reproduces such a log exactly; a replay that runs the loop
    in the missing slots does not."""
    n = trajectory.counts.shape[0]
    drop = np.concatenate([np.arange(600, 603), np.arange(1200, 1230), [1500]])
    log = _world(trajectory, 1, np.arange(n), 2, drop)
    assert log.skipped.max() == 30
    assert _rms(log, _replay(log)) == 0.0
    plant = SimPlant(MODEL.with_effects(Effects()), rate_hz=RATE, effects=EFFECTS)
    plant.reset(counts_to_position(np.rint(trajectory.counts[0]), MODEL.params))
    run = log_controller(log).run_on(plant, trajectory.counts, MODEL)  # the loop in every slot
    keep = np.setdiff1d(np.arange(n), drop)
    assert np.abs(run.counts[keep] - log.enc).max() >= 3


def test_a_reading_used_again_is_replayed_as_it_was(trajectory) -> None:
    """Rows whose host had no new status by their tick use the previous reading again (the log
    repeats its arrival time; the PD sees no count change): the replay gives them the same
    counts again and reproduces the log exactly; read as new readings (distinct arrival times
    a period on), it does not. After skipped slots the rows read a status that came back
    before the stall, and their reference at the skipped slots comes from the rows around."""
    n = trajectory.counts.shape[0]
    reused = np.concatenate([np.arange(300, 304), np.arange(900, 1200, 7), [1601, 1602]])
    drop = np.concatenate([np.arange(700, 712), [1300, 1301]])
    log = _world(trajectory, 1, np.arange(n), 2, drop, reused)
    schedule = tick_schedule(log, RATE)
    assert (~schedule.fresh).sum() == reused.size
    assert _rms(log, _replay(log)) == 0.0
    read_us = np.asarray(log.read_us).copy()
    stale = np.flatnonzero(~schedule.fresh)
    read_us[stale] = read_us[stale - 1] + 1000
    as_new = FalconLog(log.t_s, log.enc, log.tc, log.ref, log.meta, log.sent_us, read_us, log.skipped)
    assert _rms(log, _replay(as_new)) > 0.2


def test_a_run_taken_over_from_a_hold_starts_under_force(trajectory) -> None:
    """A run that took the device over from a hold (``zero_force_periods_before: 0``): the
    hold's force acts while the first commands travel to the device, so the replay lets the
    first row's command act from the start and reproduces the log exactly. Read as starting
    after zero force (the key left out), the plant sags under gravity for the delay and the
    replay misses; a log that did start after zero force is still reproduced exactly. Without
    its timing columns the log runs on the compiled loop, whose plant starts with the same
    command pending: exactly again."""
    n = trajectory.counts.shape[0]
    no_drop = np.array([], int)
    held = _world(trajectory, 1, np.arange(n), 2, no_drop, held=True)
    assert tick_schedule(held, RATE).held
    assert _rms(held, _replay(held)) == 0.0
    untimed = FalconLog(held.t_s, held.enc, held.tc, held.ref, held.meta)
    assert tick_schedule(untimed, RATE).regular and tick_schedule(untimed, RATE).held
    assert _rms(held, _replay(untimed)) == 0.0
    meta = {k: v for k, v in held.meta.items() if k != "zero_force_periods_before"}
    unsaid = FalconLog(held.t_s, held.enc, held.tc, held.ref, meta, held.sent_us, held.read_us, held.skipped)
    assert not tick_schedule(unsaid, RATE).held
    assert _rms(held, _replay(unsaid)) > 0.1
    released = _world(trajectory, 1, np.arange(n), 2, no_drop)
    assert _rms(released, _replay(released)) == 0.0


def test_fractional_delay_and_jitter_act_as_they_really_did(trajectory) -> None:
    """Sends up to 1.5 periods late at random and a delay of 2.5 periods, in a world stepped
    at 2 x RATE (so its integration differs from the replay's: the floor is that world on
    the slots with a whole delay). Replayed with the log's times and that delay the counts
    follow the log about as well as the floor; with the nominal whole-sample delay, or without
    the times, clearly worse."""
    n = trajectory.counts.shape[0]
    no_drop = np.array([], int)
    regular = _world(trajectory, 2, 2 * np.arange(n), 4, no_drop)
    floor = _rms(regular, _replay(regular))
    rng = np.random.default_rng(7)
    log = _world(trajectory, 2, 2 * np.arange(n) + rng.integers(0, 4, n), 5, no_drop)
    exact = _rms(log, _replay(with_transport_delay(log, 2.5)))
    whole = _rms(log, _replay(with_transport_delay(log, 2.0)))
    untimed = _rms(log, _replay(with_transport_delay(FalconLog(log.t_s, log.enc, log.tc, log.ref, log.meta), 2.5)))
    assert exact < 1.3 * floor, (floor, exact, whole, untimed)
    assert whole > exact + 0.05 and untimed > exact + 0.1, (floor, exact, whole, untimed)


def test_transport_delay_comes_from_the_log_or_the_model() -> None:
    log = FalconLog(np.arange(3) / RATE, np.zeros((3, 3)), np.zeros((3, 3)))
    assert transport_delay_samples(log, Effects(), MODEL) == 2.0
    assert transport_delay_samples(log, Effects(extra_delay_samples=1), MODEL) == 3.0
    assert transport_delay_samples(with_transport_delay(log, 2.37), Effects(), MODEL) == pytest.approx(2.37)
    bad = FalconLog(log.t_s, log.enc, log.tc, meta={TRANSPORT_DELAY_KEY: "0.2"})
    with pytest.raises(LogFormatError, match=r"transport_delay_samples metadata must be a number of periods in \[1, 100\]"):
        transport_delay_samples(bad, Effects(), MODEL)
    assert math.isclose(tick_schedule(log, RATE).sent[-1], 2.0)


def test_a_device_stepped_per_tick_lives_no_skipped_slot() -> None:
    """``device_clock: ticks`` (the executor on a simulated plant): a skipped slot is time the
    plant never lived through, so the rows are consecutive periods to the replay, while the
    PD still scales its count difference by the slots between them."""
    t = np.array([0, 1, 2, 5, 6]) / RATE
    us = np.rint(t * 1e6).astype(np.int64)
    log = FalconLog(t, np.zeros((5, 3)), np.zeros((5, 3)), None, {"device_clock": "ticks"}, us + 100, us,
                    np.array([0, 0, 0, 2, 0]))
    schedule = tick_schedule(log, RATE)
    assert schedule.read.tolist() == schedule.sent.tolist() == [0, 1, 2, 3, 4]
    assert schedule.slot.tolist() == [0, 1, 2, 5, 6] and schedule.timed
    wall = tick_schedule(FalconLog(t, log.enc, log.tc, None, {}, us + 100, us, log.skipped), RATE)
    assert wall.read.tolist() == pytest.approx([0, 1, 2, 5, 6]) and wall.sent[3] == pytest.approx(5.1)


def test_replays_side_by_side_are_the_replays_one_by_one(trajectory) -> None:
    """The workflow runs independent replays on two threads (:func:`side_by_side`): each gives
    exactly the counts it gives alone, for a rigid plant, a backlash plant and a timed log, in
    the jobs' order; a call from inside a job runs its own jobs one by one (no deadlock)."""
    from falcon_plan.discrepancy.replay import at_points, side_by_side

    log = synthesize_log(EFFECTS, trajectory, rate_hz=RATE)
    timed = _world(trajectory, 1, np.arange(trajectory.counts.shape[0]), 2, np.arange(600, 603))
    trials = [(log, EFFECTS), (log, Effects(backlash_rad=0.006)), (timed, EFFECTS), (timed, Effects(payload_kg=0.03))]
    alone = [closed_loop_replay(lg, eff, MODEL, RATE, log_controller(lg)) for lg, eff in trials]
    jobs = [lambda lg=lg, eff=eff: closed_loop_replay(lg, eff, MODEL, RATE, log_controller(lg)) for lg, eff in trials]
    for _ in range(3):
        together = side_by_side(jobs * 2)
        assert all(np.array_equal(a, b) for a, b in zip(alone * 2, together))
    nested = side_by_side([lambda: at_points(lambda x: 2.0 * x, [1.0, 2.0, 3.0]), lambda: 5])
    assert nested == [{1.0: 2.0, 2.0: 4.0, 3.0: 6.0}, 5]


def test_a_failed_replay_side_by_side_raises_after_every_job_ended() -> None:
    """The first failure of the jobs is raised, once every job has ended (none is left running
    on a thread the caller no longer waits for)."""
    import threading

    from falcon_plan.discrepancy.replay import side_by_side

    ended = threading.Event()

    def slow() -> int:
        ended.wait(5.0)
        return 1

    def failing() -> int:
        raise LogFormatError("a bad log")

    def release() -> int:
        ended.set()
        return 2

    with pytest.raises(LogFormatError, match="a bad log"):
        side_by_side([failing, slow, release])
    assert ended.is_set()


def _acting_shares(schedule, delay: float, hold: float) -> tuple[np.ndarray, np.ndarray]:
    """The timed loop's inputs from their definition, period by period: (each row's period j,
    weights (periods, TIMED_LINE)), weight [p, m] the share of period p in which the command
    of the m-th newest row by then acted."""
    from falcon_plan.discrepancy.replay import MIN_TRANSPORT_DELAY_SAMPLES
    from falcon_plan.sim.batch import TIMED_LINE

    n = schedule.read.size
    j = []
    for k in range(n):
        j.append(max(math.ceil(schedule.read[k] - 1e-9), j[-1] + 1 if j else -10**9))
    start = [max(schedule.sent[k] + max(delay, MIN_TRANSPORT_DELAY_SAMPLES), j[k]) for k in range(n)]
    if schedule.held:
        start[0] = 0.0
    for k in range(1, n):
        start[k] = max(start[k], start[k - 1])
    end = [min(start[k + 1] if k + 1 < n else math.inf, start[k] + hold) for k in range(n)]
    weights = np.zeros((j[-1] + 1, TIMED_LINE))
    for p in range(j[-1] + 1):
        newest = max(k for k in range(n) if j[k] <= p) if j[0] <= p else -1
        for m in range(TIMED_LINE):
            k = newest - m
            if k >= 0:
                weights[p, m] = max(0.0, min(end[k], p + 1) - max(start[k], p))
    return np.array(j), weights


@pytest.mark.parametrize("held", [False, True])
def test_the_acting_shares_follow_their_definition(held: bool) -> None:
    """:func:`_timed_inputs` (vectorised) against the shares computed period by period from
    their definition, on a schedule with jitter, readings used again, skipped slots and a
    stall longer than the hold (zero force after it)."""
    from falcon_plan.discrepancy.replay import TickSchedule, _timed_inputs

    rng = np.random.default_rng(26)
    steps = rng.choice([1, 1, 1, 1, 2, 3], size=300)
    steps[150] = 9                                           # a stall past the hold
    slot = np.cumsum(steps) - steps[0]
    read = np.clip(slot + rng.uniform(-0.4, 0.4, slot.size), 0.0, None)
    fresh = rng.uniform(size=slot.size) > 0.05
    fresh[0] = True
    for k in np.flatnonzero(~fresh):
        read[k] = read[k - 1]
    sent = np.maximum.accumulate(read + rng.uniform(0.0, 0.6, slot.size))
    schedule = TickSchedule(read, sent, slot, True, fresh, held)
    for delay in (1.0, 2.5, 4.25):
        for hold in (3.0, 5.0, math.inf):
            j, ticks, weights = _timed_inputs(schedule, delay, hold, RATE)
            j_ref, weights_ref = _acting_shares(schedule, delay, hold)
            assert np.array_equal(j, j_ref)
            assert np.array_equal(weights, weights_ref), (delay, hold, np.abs(weights - weights_ref).max())
            assert np.array_equal(ticks[j, 0], np.ones(j.size)) and ticks.shape[0] == weights.shape[0]
            acting = weights.sum(axis=1)
            assert np.all(acting <= 1.0 + 1e-12)
            if math.isfinite(hold):    # the stall outlasts the hold: zero force for a while
                assert np.any(acting[j[149]:j[150] + 8] < 0.5)


def test_a_timed_log_of_the_lqr_is_refused_with_what_to_do(trajectory) -> None:
    """The replay with a host's timing re-runs the PD law only (the compiled timed loop): a log
    the LQR ran (the executor's default) is refused in one line naming the way out, instead of
    being replayed under a controller that never ran it."""
    timed = _world(trajectory, 1, np.arange(trajectory.counts.shape[0]), 2, np.arange(600, 603))
    lqr = Controller.from_meta({}, text="lqr", rate_hz=RATE)
    with pytest.raises(LogFormatError, match=r"run with the LQR controller.*--controller pd.*--controller open-loop"):
        closed_loop_replay(timed, EFFECTS, MODEL, RATE, lqr)
