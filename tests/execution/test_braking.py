"""The safe stop: a cancel brakes to rest within the command limit and holds there with gravity
compensation (or, with release, drops to zero force at once), on the simulated device."""
from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from falcon_plan.execution.braking import (BRAKE_TC_MAX, DECELERATION_RESOLUTION, FIRST_BRAKE_TICKS, STOP_HOLD_S,
                                          brake_profile, first_commands, plan_brake, quick_brake)
from falcon_plan.execution.splice import STOP_BUDGET_S
from falcon_plan.execution.executor import Executor
from falcon_plan.falconlog import read_log
from falcon_plan.model.kinematics import counts_to_position

CANCEL_AT = 100  # rows: mid-motion of make_move() after the 0.05 s pre-roll (40 rows)


def _cancel_at(rows: int) -> tuple[threading.Event, object]:
    cancel = threading.Event()

    def progress(done: int, total: int) -> None:
        if done >= rows:
            cancel.set()

    return cancel, progress


def _run(model, dev, traj, tmp_path, *, release: bool = False, kind: str = "lqr", rows: int = CANCEL_AT):
    cancel, progress = _cancel_at(rows)
    path = tmp_path / f"run-{kind}-{release}.csv"
    report = Executor(dev, model, log_path=path, preroll_s=0.05, progress_period_s=1 / 800, release=release,
                      controller_kind=kind).run(traj, cancel=cancel, progress=progress)
    return report, read_log(path)


@pytest.mark.parametrize("kind", ["lqr", "pd"])
def test_cancel_brakes_to_rest_and_holds_with_gravity(model, sim_device, make_move, tmp_path, kind):
    dev = sim_device()
    traj = make_move()
    report, log = _run(model, dev, traj, tmp_path, kind=kind)
    assert report.status == "cancelled", report.reason
    brake = report.brake
    assert brake is not None and brake.tick == CANCEL_AT  # the next command after the cancel
    assert brake.stop_s > 0.005 and brake.peak_feedforward <= BRAKE_TC_MAX
    # the stop begins at once: the logged reference is the quick brake's from the cancel's tick
    # (the plan's for the command delay, then braking), not the plan's
    lead = brake.lead
    ahead = CANCEL_AT + lead + 4
    np.testing.assert_array_equal(log.ref[CANCEL_AT:ahead], brake.ref_counts[:ahead - CANCEL_AT])
    plan_ref = Executor(sim_device(), model, preroll_s=0.05).prepare(traj).ref_counts
    assert np.abs(log.ref[ahead - 1] - plan_ref[ahead - 1]).max() > 0.5
    # the minimum-time brake took over later, continuous in position and rate
    (refine,) = report.splices
    assert refine["taken"] and refine["source"].startswith("min-time brake"), refine
    assert refine["tick"] > CANCEL_AT and refine["position_jump_counts"] < 1e-6
    assert refine["velocity_jump_counts_s"] < 1.0
    # the run is the rows up to the cancel, the brakes and the hold, all logged
    hold_rows = int(round(STOP_HOLD_S * 800))
    assert report.samples == len(log) >= refine["tick"] + hold_rows
    # never clamped; the feed-forward leaves the feedback its reserve below the device's static
    # limit (2500), which the feedback's noise (a couple of hundred units) overshoots rarely
    assert report.saturated_samples == 0 and np.sum(np.abs(log.tc).max(axis=1) > 2500) <= 3
    # at rest where the reference stopped: the last 50 ms still, near the stop point (the PD,
    # lightly damped, still rings by a few counts)
    still = log.enc[-40:]
    wobble, off = (2, 2) if kind == "lqr" else (6, 8)   # LQR: still settling by a count or two
    assert np.ptp(still, axis=0).max() <= wobble
    stop = log.ref[-1]
    assert np.abs(still[-1] - stop).max() <= off, (still[-1], stop)
    assert np.ptp(log.ref[-hold_rows // 2:], axis=0).max() == 0.0
    # ... and short of where the plan would have gone (it braked; the plan had 50 more ms)
    goal = traj.position_m[-1]
    stop_m = counts_to_position(stop)
    assert np.linalg.norm(stop_m - goal) > 1e-3
    # held, not released: the last commands are the gravity feed-forward (plus feedback within
    # its reserve), far from zero
    gravity = np.asarray(model.inverse_dynamics(stop_m, np.zeros(3), np.zeros(3)), dtype=float)
    assert np.abs(gravity).max() > 500
    # (on average over the last 50 ms: a stop between two counts dithers the feedback by a few hundred)
    np.testing.assert_allclose(log.tc[-40:].mean(axis=0), gravity, atol=150)
    # the executor still ends the run with zero force (as a completed run does)
    np.testing.assert_array_equal(dev.last_commands, 0)


def test_the_stop_begins_at_the_command_after_the_cancel(model, sim_device, make_move, tmp_path):
    """Judged by ticks in a simulated run: the cancel arrives after row CANCEL_AT - 1 was sent;
    every command before is the uncancelled run's, and command CANCEL_AT (the next one) is
    already the brake's: the same feedback with the brake's feed-forward instead of the plan's."""
    traj = make_move()
    report, log = _run(model, sim_device(), traj, tmp_path)
    path = tmp_path / "plain.csv"
    Executor(sim_device(), model, log_path=path, preroll_s=0.05).run(traj)
    plain = read_log(path)
    brake = report.brake
    assert brake.tick == CANCEL_AT
    np.testing.assert_array_equal(log.tc[:CANCEL_AT], plain.tc[:CANCEL_AT])
    change = np.abs(log.tc[CANCEL_AT] - plain.tc[CANCEL_AT]).max()
    assert brake.command_jump > 100 and abs(change - brake.command_jump) <= 1.0, (change, brake.command_jump)


def test_a_paced_cancel_brakes_from_the_next_deadline(model, sim_device, make_move):
    """A paced run (100 Hz: 10 ms periods) cancelled from another thread while the loop waits
    for tick T + 1's deadline (T the last row sent): tick T + 1's command is the brake's (the
    wait wakes at the cancel), sent in its own slot; judged by ticks."""
    rate = 100.0
    trigger = threading.Event()
    cancel = threading.Event()
    sent: list[int] = []

    class Rows:
        def start(self, meta, model) -> None:  # noqa: ANN001
            pass

        def row(self, t_s, *rest) -> None:  # noqa: ANN001
            sent.append(int(round(t_s * rate)))
            if len(sent) == 8:                 # mid-motion (after the 2-tick pre-roll)
                trigger.set()

        def finish(self, report) -> None:  # noqa: ANN001
            pass

    def canceller() -> None:
        trigger.wait(30.0)
        cancel.set()

    threading.Thread(target=canceller, daemon=True).start()
    report = Executor(sim_device(rate), model, preroll_s=0.02, pace=True, sink=Rows()).run(
        make_move(rate_hz=rate), cancel=cancel)
    assert report.status == "cancelled" and report.brake is not None
    assert report.brake.tick == 8 and 8 in sent, (report.brake.tick, sent[:12])


def test_release_drops_to_zero_force_at_once(model, sim_device, make_move, tmp_path):
    dev = sim_device()
    report, log = _run(model, dev, make_move(), tmp_path, release=True)
    assert report.status == "cancelled" and report.brake is None
    assert CANCEL_AT <= report.samples <= CANCEL_AT + 1 < report.planned_samples
    np.testing.assert_array_equal(dev.last_commands, 0)


def test_splice_is_continuous_and_the_brake_within_the_bound(model, sim_device, make_move, tmp_path):
    """The spliced reference continues the plan in position and rate (zero to the plan's
    tolerance), and the brake's commands, recomputed by the model's inverse dynamics at its
    analytic accelerations, are within the bound."""
    dev = sim_device()
    traj = make_move()
    ex = Executor(dev, model, preroll_s=0.05)
    s = ex.prepare(traj)
    c = ex.controller
    for tick in (60, 80, 100, 120):
        b = plan_brake(s.ref_counts, s.position_m, s.velocity_m_s, tick, model, c.feedforward_effects, 800.0,
                       c.feedforward_lead_samples, 200)
        assert b is not None and b.position_jump_counts < 1e-6 and b.velocity_jump_counts_s < 1.0
        # the reference before the brake is the plan's, exactly
        np.testing.assert_array_equal(b.ref_counts[:b.lead], s.ref_counts[tick:tick + b.lead])
        # the rate at the brake's start from the plan's samples before it and from the brake's
        # after it (second-order one-sided differences): equal, where the plan's rate is thousands
        j = b.lead
        left = (3 * s.ref_counts[tick + j] - 4 * s.ref_counts[tick + j - 1] + s.ref_counts[tick + j - 2]) * 400.0
        right = (-3 * b.ref_counts[j] + 4 * b.ref_counts[j + 1] - b.ref_counts[j + 2]) * 400.0
        assert np.abs(left).max() > 500 and np.abs(left - right).max() < 10.0, (left, right)
        # independent check of the bound: analytic brake accelerations through inverse dynamics
        p0, v0 = s.position_m[tick + j], s.velocity_m_s[tick + j]
        pos, t_stop = brake_profile(p0, v0, b.deceleration_m_s2, 800.0)
        t = np.minimum(np.arange(pos.shape[0]) / 800.0, t_stop)[:, None]
        direction = v0 / np.linalg.norm(v0)
        vel = v0 - b.deceleration_m_s2 * direction * t
        acc = np.where(t < t_stop, -b.deceleration_m_s2, 0.0) * direction
        tau = np.asarray(model.inverse_dynamics(pos, vel, acc), dtype=float)
        assert np.abs(tau).max() <= BRAKE_TC_MAX + 50, np.abs(tau).max()
        # minimum time among constant decelerations: 5 % harder exceeds the bound
        harder = brake_profile(p0, v0, 1.05 * b.deceleration_m_s2, 800.0)[0]
        t_h = np.minimum(np.arange(harder.shape[0]) / 800.0, np.linalg.norm(v0) / (1.05 * b.deceleration_m_s2))[:, None]
        acc_h = -1.05 * b.deceleration_m_s2 * direction * np.ones_like(t_h)
        tau_h = np.asarray(model.inverse_dynamics(harder, v0 - 1.05 * b.deceleration_m_s2 * direction * t_h, acc_h))
        assert np.abs(tau_h).max() > BRAKE_TC_MAX - 50


def test_cancel_at_rest_holds_where_it_is(model, sim_device, make_move, tmp_path):
    dev = sim_device()
    traj = make_move()
    report, log = _run(model, dev, traj, tmp_path, rows=10)  # in the pre-roll
    assert report.status == "cancelled" and report.brake is not None
    assert report.brake.stop_s == 0.0
    np.testing.assert_allclose(report.brake.stop_counts, log.ref[0], atol=1e-6)
    assert np.abs(log.enc[-1] - log.ref[0]).max() <= 2


def _analytic_feedforward(model, p0, v0, decel):
    """The brake's inverse dynamics at its analytic velocities and accelerations (not the
    executor's differences of counts) [command units]."""
    pos, t_stop = brake_profile(p0, v0, decel, 800.0)
    t = np.minimum(np.arange(pos.shape[0]) / 800.0, t_stop)[:, None]
    direction = v0 / np.linalg.norm(v0)
    acc = np.where(t < t_stop, -decel, 0.0) * direction
    return np.asarray(model.inverse_dynamics(pos, v0 - decel * direction * t, acc), dtype=float)


def test_the_loops_quick_brake_is_feasible_and_near_the_minimum_time(model, sim_device, make_move):
    """The quick brake (for the loop at the cancel's tick) continues the plan, is within the
    bound by an independent computation, starts as its first commands (the loop's command at
    the cancel's tick) do, and brakes within 15 % of the minimum-time brake."""
    ex = Executor(sim_device(), model, preroll_s=0.05)
    s = ex.prepare(make_move())
    c = ex.controller
    for tick in (50, 70, 90, 110, 130):
        args = (s.ref_counts, s.position_m, s.velocity_m_s, tick, model, c.feedforward_effects, 800.0,
                c.feedforward_lead_samples, 200)
        quick, best = quick_brake(*args), plan_brake(*args)
        assert quick is not None and best is not None
        assert quick.position_jump_counts < 1e-6 and quick.velocity_jump_counts_s < 1.0
        np.testing.assert_array_equal(quick.ref_counts[:quick.lead], s.ref_counts[tick:tick + quick.lead])
        assert quick.peak_feedforward <= BRAKE_TC_MAX
        p0, v0 = s.position_m[tick + quick.lead], s.velocity_m_s[tick + quick.lead]
        assert np.abs(_analytic_feedforward(model, p0, v0, quick.deceleration_m_s2)).max() <= BRAKE_TC_MAX + 50
        ratio = quick.deceleration_m_s2 / best.deceleration_m_s2
        assert 0.85 <= ratio <= 1.0 + DECELERATION_RESOLUTION, ratio
        # the loop's first command at the tick is this brake's: reference, feed-forward, clamp
        # (made with the plan for every tick, and for this tick alone: the same)
        ref, ff = s.first_brake.at(tick)
        alone = first_commands(s.ref_counts, s.position_m, s.velocity_m_s, range(tick, tick + 1), *args[4:-1]).at(tick)
        np.testing.assert_allclose(alone[0], ref, atol=1e-9)
        np.testing.assert_allclose(alone[1], ff, atol=1e-9)
        np.testing.assert_allclose(ff[0], quick.feedforward[0], atol=1e-9)
        np.testing.assert_allclose(ref[:quick.lead + 3], quick.ref_counts[:quick.lead + 3], atol=1e-9)
        first, whole = (c.quick_tail(ex.controller.tracker(s.ref_counts, model), tick, r, f, model)
                        for r, f in ((ref, ff), (quick.ref_counts, quick.feedforward)))
        np.testing.assert_allclose(first.command_limits[0], whole.command_limits[0])
        np.testing.assert_allclose(first.acting_rate[0], whole.acting_rate[0])
        # the velocities it carries (where the minimum-time brake takes over) are the profile's
        j = quick.lead + 3
        np.testing.assert_allclose(quick.velocity_m_s[j], v0 - quick.deceleration_m_s2 * 3 / 800.0 * v0 / np.linalg.norm(v0),
                                   atol=1e-12)


def test_the_rest_of_the_stop_comes_from_a_worker_at_its_tick(model, sim_device, make_move, tmp_path):
    """Judged by ticks in a simulated run: from the cancel the loop follows the stop's first
    commands made with the plan, a worker's rest of the stop takes over at the tick after its
    first budget (before those run out), the minimum-time brake later; the loop's only work on
    the stop is at those ticks (a look-up, two hand-overs: no brake computed in the loop), and
    the stop is continuous in position and velocity throughout, within the bound."""
    traj = make_move()
    report, log = _run(model, sim_device(), traj, tmp_path)
    brake, (refine,) = report.brake, report.splices
    rate = 800.0
    handover = CANCEL_AT + math.ceil(STOP_BUDGET_S * rate) + 1
    assert CANCEL_AT < handover < CANCEL_AT + FIRST_BRAKE_TICKS
    assert [k for k, _ in report.stop_work_us] == [CANCEL_AT, handover, handover + 1, refine["tick"]]
    # the loop's reference: the table's first commands, then the rest, as the report's stop says
    row = Executor(sim_device(), model, preroll_s=0.05).prepare(traj).first_brake.row(CANCEL_AT)
    np.testing.assert_array_equal(log.ref[CANCEL_AT:handover], row.ref_counts[:handover - CANCEL_AT])
    np.testing.assert_array_equal(log.ref[CANCEL_AT:refine["tick"]], brake.ref_counts[:refine["tick"] - CANCEL_AT])
    # continuous: each period the velocity changes by at most one period of the harder
    # deceleration, and while it brakes (after the plan's command delay, before the period it
    # stops in) the points advance by the mean velocity (a constant deceleration)
    v, p = brake.velocity_m_s, brake.position_m
    harder = max(row.deceleration_m_s2, brake.deceleration_m_s2)
    assert np.linalg.norm(np.diff(v, axis=0), axis=1).max() <= harder / rate * (1 + 1e-9)
    braking = slice(brake.lead, int(np.flatnonzero(np.linalg.norm(v, axis=1) > 1e-9)[-1]))
    assert braking.stop > handover - CANCEL_AT + brake.lead          # still braking at the hand-over
    np.testing.assert_allclose(np.diff(p, axis=0)[braking], (0.5 * (v[1:] + v[:-1]) / rate)[braking], atol=1e-12)
    assert brake.position_jump_counts < 1e-6 and brake.velocity_jump_counts_s < 1.0
    assert brake.peak_feedforward <= BRAKE_TC_MAX and np.abs(brake.feedforward).max() <= BRAKE_TC_MAX


def test_a_cancel_after_a_splice_looks_its_first_command_up(model, sim_device, home_m, tmp_path):
    """The stop's first commands along a plan spliced in are made off the loop once it is taken
    (a simulated run: as if they were in by the cancel): a cancel after the splice follows them
    from its tick, as before any splice."""
    from falcon_plan.execution.executor import SpliceSlot
    from falcon_plan.planning.api import plan_problem
    from falcon_plan.planning.problem import PlanOptions, PlanProblem
    from falcon_plan.planning.replan import replan

    rate = 800.0
    running = plan_problem(PlanProblem(tuple(home_m), tuple(home_m + [0.03, -0.02, 0.01])), PlanOptions.fast(), model)
    splice_k = int(0.3 * running.trajectory.duration_s * rate)
    new = replan(running, splice_k / rate, home_m + [0.035, -0.015, 0.012], model=model)
    ex = Executor(sim_device(), model, log_path=tmp_path / "run.csv", preroll_s=0.05, progress_period_s=1 / rate)
    slot, cancel, offers = SpliceSlot(), threading.Event(), []
    cancel_at = 40 + splice_k + 30                            # rows: 30 ticks into the new plan

    def progress(done: int, total: int) -> None:
        if not offers:
            offers.append(ex.prepare_splice(new.trajectory, splice_k / rate))
            slot.offer(offers[0])
        if done >= cancel_at:
            cancel.set()

    report = ex.run(running.trajectory, cancel=cancel, progress=progress, splices=slot)
    assert report.splices[0]["taken"] and report.splices[0]["tick"] < cancel_at
    assert report.brake is not None and report.brake.tick == cancel_at
    row = ex.stop_commands(offers[0]).row(cancel_at)
    log = read_log(tmp_path / "run.csv")
    handover = report.stop_work_us[1][0]
    np.testing.assert_array_equal(log.ref[cancel_at:handover], row.ref_counts[:handover - cancel_at])
    assert report.brake.command_jump > 100 and report.brake.position_jump_counts < 1e-6


def test_a_paced_loop_does_only_a_few_ticks_of_work_on_the_stop(model, sim_device, make_move):
    """A paced run at 800 Hz cancelled mid-motion: the loop's own work on the stop (CPU time of
    its thread, ``stop_work_us``) is recorded at the brake's tick and at a few hand-overs only
    (the rest of the stop comes from a worker), and the run ends cancelled. How that work
    compares with computing the quick brake, and with a period, is measured by
    benchmarks/bench_brake.py against a reference timed in the same run: as a CPU-time assertion
    here it failed on a busy machine when a first call's cost landed in the loop (1.96 ms against
    a median of 1.07 ms for the brake)."""
    traj = make_move()
    cancel = threading.Event()
    sent: list[int] = []

    class Rows:
        def start(self, meta, model) -> None:  # noqa: ANN001
            pass

        def row(self, t_s, *rest) -> None:  # noqa: ANN001
            sent.append(int(round(t_s * 800)))
            if len(sent) == CANCEL_AT:
                cancel.set()

        def finish(self, report) -> None:  # noqa: ANN001
            pass

    ex = Executor(sim_device(), model, preroll_s=0.05, pace=True, sink=Rows())
    report = ex.run(traj, cancel=cancel)
    assert report.status == "cancelled" and report.brake is not None and report.splices
    work = dict(report.stop_work_us)
    assert report.brake.tick in work and len(work) <= 6, work   # the look-up and a few hand-overs
    assert all(us > 0.0 for us in work.values()), work
    assert report.to_dict()["stop_work_max_us"] == max(work.values())
