"""Which rows a replay criterion judges (issue 26, items 3 and 4): a host stall's window and,
for the open-world check, the start before the motion are what the replay cannot know, so a
nominal device recorded on a busy host is not flagged for them; an error in the judged rows
still is."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.discrepancy.checks import UNEXPLAINED_FACTOR, open_world_check
from falcon_plan.discrepancy.motion import estimate_motion
from falcon_plan.discrepancy.replay import (SETTLED_MOVE_COUNTS, STALL_PERIODS, STALL_SETTLE_S, START_TRANSIENT_S, closed_loop_replay,
                                            judged_rows, log_controller, settled_start_s)
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import NOMINAL

from .host_cases import HOST_CASES, host_logs

RATE = 1000.0


def _timed_log(n: int, stall_at: int, gap_periods: int, reused: int, meta: dict[str, str]) -> FalconLog:
    """A still log of ``n`` rows at RATE with timing columns: sends once a period, readings
    0.4 period before them, except a send gap of ``gap_periods`` before row ``stall_at`` and
    ``reused`` rows after it that use that row's reading again."""
    sent = np.arange(n, dtype=np.int64) * 1000 + 400
    sent[stall_at:] += (gap_periods - 1) * 1000
    read = sent - 400
    read[stall_at + 1:stall_at + 1 + reused] = read[stall_at]
    t = np.arange(n) / RATE
    enc = np.zeros((n, 3), np.int64)
    return FalconLog(t, enc, enc.copy(), enc.astype(float), {"rate_hz": "1000", **meta},
                     sent, read, np.zeros(n, np.int64))


def test_a_host_stall_leaves_out_its_settling_window() -> None:
    log = _timed_log(2000, 1000, int(STALL_PERIODS) + 2, 0, {"device_clock": "wall"})
    judged = judged_rows(log, RATE)
    t = np.asarray(log.t_s)
    out = ~judged.mask
    assert judged.stalls == 1
    assert np.all(out[(t >= t[1000]) & (t < t[1000] + STALL_SETTLE_S - 1e-9)])
    assert judged.mask[:1000].all() and judged.mask[t >= t[1000] + STALL_SETTLE_S + 1e-9].all()
    assert judged.stall_s == pytest.approx(STALL_SETTLE_S, abs=2 / RATE)


def test_reused_readings_are_a_stall_and_a_short_gap_is_not() -> None:
    reused = _timed_log(2000, 1000, 1, int(STALL_PERIODS) + 1, {"device_clock": "wall"})
    assert judged_rows(reused, RATE).stalls == 1          # the readings grew old
    jitter = _timed_log(2000, 1000, int(STALL_PERIODS) - 1, 0, {"device_clock": "wall"})
    assert judged_rows(jitter, RATE).mask.all()          # one period late: timing the replay plays


def test_stalls_count_only_on_a_device_that_lived_through_them() -> None:
    """A simulated plant stepped once per tick (device_clock: ticks) did not live through the
    host's stall: nothing is left out; a log mostly stalled is judged whole."""
    ticks = _timed_log(2000, 1000, 5, 0, {"device_clock": "ticks"})
    assert judged_rows(ticks, RATE).mask.all()
    short = _timed_log(150, 20, 5, 0, {"device_clock": "wall"})
    assert judged_rows(short, RATE).mask.all()


def test_the_settled_start_is_the_motions_start() -> None:
    log = _timed_log(2000, 1000, 1, 0, {"device_clock": "wall", "motion_start_s": "0.8"})
    assert settled_start_s(log, RATE) == pytest.approx(0.8)
    assert settled_start_s(_timed_log(2000, 1000, 1, 0, {}), RATE) == START_TRANSIENT_S
    judged = judged_rows(log, RATE, settled_start_s(log, RATE))
    assert judged.start_s == pytest.approx(0.8) and not judged.mask[:800].any() and judged.mask[800:].all()


def test_a_leg_held_where_the_approach_left_it_is_judged_from_when_it_leaves() -> None:
    """Friction holds a leg where the approach left it until the motion moves it: the start
    is not forgotten before every leg that moves has left that pose (at most half the log)."""
    log = _timed_log(4000, 3000, 1, 0, {"device_clock": "wall", "motion_start_s": "0.8"})
    enc = np.asarray(log.enc).copy()
    enc[1500:, 1] += 3 * SETTLED_MOVE_COUNTS                # leg 1 leaves its pose at 1.5 s
    moved = FalconLog(log.t_s, enc, log.tc, log.ref, log.meta, *log.timing_columns)
    assert settled_start_s(moved, RATE) == pytest.approx(1.5)
    enc[1500:, 1] -= 3 * SETTLED_MOVE_COUNTS
    enc[3500:, 2] += 3 * SETTLED_MOVE_COUNTS                # a leg leaving late: half the log
    late = FalconLog(log.t_s, enc, log.tc, log.ref, log.meta, *log.timing_columns)
    assert settled_start_s(late, RATE) == pytest.approx(log.t_s[-1] / 2)


@pytest.fixture(scope="module")
def nominal_host_log() -> FalconLog:
    train, _ = host_logs(HOST_CASES["none"])
    return train.rows(0, 3000)


def _with_counts_off(log: FalconLog, start_s: float, stop_s: float, motion_start_s: float) -> FalconLog:
    """``log`` whose counts are 6 counts off on every leg from ``start_s`` to ``stop_s`` [s]
    (an error the replay cannot follow), with the motion said to start at ``motion_start_s``."""
    t = np.asarray(log.t_s) - log.t_s[0]
    enc = np.asarray(log.enc).copy()
    enc[(t >= start_s) & (t < stop_s)] += 6
    return FalconLog(log.t_s, enc, log.tc, log.ref, {**log.meta, "motion_start_s": f"{motion_start_s:g}"},
                     *log.timing_columns)


@pytest.mark.parametrize("where", ["before the motion", "in the motion"])
def test_the_open_world_check_judges_the_motion_not_the_start(nominal_host_log: FalconLog, where: str) -> None:
    """The same counts error (6 counts for 0.6 s) flags the nominal model when it sits in the
    motion, and not when it sits in the approach before it (the replay does not know the
    device's state there)."""
    model = FalconModel()
    span = (0.0, 0.6) if where == "before the motion" else (1.2, 1.8)
    log = _with_counts_off(nominal_host_log, *span, motion_start_s=0.6)
    spec = log_controller(log)
    sim = closed_loop_replay(log, NOMINAL, model, RATE, spec)
    check = open_world_check(log, estimate_motion(log, RATE, model.params), sim, model, RATE, spec, NOMINAL)
    assert 0.6 <= check.judged["judged_from_s"] <= 0.7   # once the legs have left the start's pose
    flagged = check.replay_rms_counts > UNEXPLAINED_FACTOR * check.floor_counts
    assert check.unexplained == flagged == (where == "in the motion"), check
