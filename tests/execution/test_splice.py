"""Switching a running run to a new plan made from its state (issue 24 item 2): the reference
and the controller change at the splice tick, continuous in position and rate; an offer that
arrives after its tick is refused and the run keeps its plan."""
from __future__ import annotations

import threading

import numpy as np

from falcon_plan.execution.executor import Executor, SpliceSlot
from falcon_plan.falconlog import read_log
from falcon_plan.model.kinematics import counts_to_position
from falcon_plan.planning.api import plan_problem
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.replan import replan

PREROLL_S = 0.05
RATE = 800.0


def test_a_run_switches_to_a_new_plan_at_the_splice_tick(model, sim_device, home_m, tmp_path):
    running = plan_problem(PlanProblem(tuple(home_m), tuple(home_m + [0.03, -0.02, 0.01])), PlanOptions.fast(), model)
    traj = running.trajectory
    new_goal = home_m + [0.035, -0.015, 0.012]
    splice_k = int(0.3 * traj.duration_s * RATE)          # on the loop's grid
    splice_s = splice_k / RATE
    new = replan(running, splice_s, new_goal, model=model)
    dev = sim_device(rate_hz=RATE)
    ex = Executor(dev, model, log_path=tmp_path / "splice.csv", preroll_s=PREROLL_S, settle_s=0.2)
    slot = SpliceSlot()
    offered = threading.Event()

    def progress(done: int, total: int) -> None:  # the replanning side: prepare once the run goes
        if not offered.is_set():
            offered.set()
            # a budget of 20 ms from the pre-roll's first ticks reaches no further than the splice
            assert ex.splice_time_after(0.02) <= splice_s
            slot.offer(ex.prepare_splice(new.trajectory, splice_s))

    # the plan starts at home (where a reset plant is)
    report = ex.run(traj, progress=progress, splices=slot)
    assert report.status == "completed", report.reason
    assert len(report.splices) == 1 and report.splices[0]["taken"], report.splices
    sp = report.splices[0]
    n_pre = int(round(PREROLL_S * RATE))
    assert sp["tick"] == n_pre + splice_k - 2  # the commands change one command delay (2) early
    assert sp["position_jump_counts"] < 1e-6 and sp["velocity_jump_counts_s"] < 1.0
    log = read_log(tmp_path / "splice.csv")
    # the logged reference: the running plan's before the splice, the new plan's after
    k = n_pre + splice_k
    np.testing.assert_allclose(counts_to_position(log.ref[-1]), new_goal, atol=1e-6)
    left = (3 * log.ref[k] - 4 * log.ref[k - 1] + log.ref[k - 2]) * (RATE / 2)
    right = (-3 * log.ref[k] + 4 * log.ref[k + 1] - log.ref[k + 2]) * (RATE / 2)
    assert np.abs(left).max() > 500 and np.abs(left - right).max() < 20.0, (left, right)
    # it went there: at rest within 2 counts of the new goal, commands within the limit
    assert np.abs(log.enc[-1] - log.ref[-1]).max() <= 2
    assert report.saturated_samples == 0 and report.tracking.norm_max_mm < 0.5


def test_an_offer_after_its_tick_is_refused_and_the_plan_kept(model, sim_device, home_m, tmp_path):
    running = plan_problem(PlanProblem(tuple(home_m), tuple(home_m + [0.03, -0.02, 0.01])), PlanOptions.fast(), model)
    traj = running.trajectory
    splice_k = int(0.3 * traj.duration_s * RATE)
    new = replan(running, splice_k / RATE, home_m + [0.035, -0.015, 0.012], model=model)
    ex = Executor(sim_device(rate_hz=RATE), model, preroll_s=PREROLL_S)
    slot = SpliceSlot()
    late = int(round(PREROLL_S * RATE)) + splice_k + 10

    def progress(done: int, total: int) -> None:  # offered only well after its tick
        if done >= late and not slot_used:
            slot_used.append(True)
            slot.offer(offer[0])

    slot_used: list[bool] = []
    offer: list = []

    def prepare(done: int, total: int) -> None:
        if not offer:
            offer.append(ex.prepare_splice(new.trajectory, splice_k / RATE))
        progress(done, total)

    ex.progress_period_s = 1.0 / RATE
    report = ex.run(traj, progress=prepare, splices=slot)
    assert report.status == "completed"
    assert len(report.splices) == 1 and not report.splices[0]["taken"]
    assert report.planned_samples == int(round(PREROLL_S * RATE)) + int(np.ceil(traj.duration_s * RATE - 1e-9)) + 1


def test_the_splice_time_leaves_the_budget_and_the_command_delay(model, sim_device, make_move):
    ex = Executor(sim_device(rate_hz=RATE), model, preroll_s=PREROLL_S, progress_period_s=1 / RATE)
    seen: list[tuple[int, float]] = []

    def progress(done: int, total: int) -> None:
        if done == 60:  # mid-motion (40 pre-roll rows)
            seen.append((done, ex.splice_time_after(0.01)))

    ex.run(make_move(), progress=progress)
    done, splice_s = seen[0]
    k_s = int(round(PREROLL_S * RATE)) + splice_s * RATE
    assert abs(k_s - round(k_s)) < 1e-9                      # on the loop's grid
    assert k_s - 2 >= done + 0.01 * RATE                     # its commands change after the budget
