"""The goal queue, the planning pool and the request handlers without Zenoh: a real simulated
device, real planning processes and the real planner, results collected from the ``publish``
callable instead of a session."""
from __future__ import annotations

import json
import threading
import time
from typing import Any, Iterator

import numpy as np
import pytest

from falcon_plan.errors import PlanningFailed
from falcon_plan.planning.problem import PlanProblem
from service.codec import RequestError
from service.device import make_runner
from service.goals import GoalManager
from service.handlers import (falcon_planner, parse_goal_request, parse_plan_request, plan_cache_key, planning_error,
                              require_in_workspace)
from service.keys import ServiceKeys
from service.workers import PlanJob, PlanningPool
from service.testing import GOAL_A_M, GOAL_B_M, HOME_M, left_at_tolerance_mm, wait_until

KEYS = ServiceKeys("nozenoh", "gm0")
LONG = {"hessian": "exact", "n_intervals": 400, "switching": False, "refine": True, "plant_check": True, "crosscheck": True}
"""Legal options that keep a planner busy for ~30 s."""
MEDIUM = {"hessian": "exact", "n_intervals": 60, "switching": False, "refine": True, "plant_check": True, "crosscheck": True}
"""Legal options that keep a planner busy for a few seconds."""


@pytest.fixture(scope="module")
def pool() -> Iterator[PlanningPool]:
    """One planning process with the real planner."""
    p = PlanningPool(1, falcon_planner, name="gm-test")
    p.start()
    yield p
    p.close()


class Published:
    """The ``publish`` callable: keeps every (key, body) and wakes waiters."""

    def __init__(self) -> None:
        self.items: list[tuple[str, dict[str, Any]]] = []
        self.cond = threading.Condition()

    def __call__(self, key: str, body: dict[str, Any]) -> None:
        with self.cond:
            self.items.append((key, json.loads(json.dumps(body))))
            self.cond.notify_all()

    def result(self, goal_id: str, timeout_s: float = 20.0) -> dict[str, Any]:
        """The final result published for ``goal_id``."""
        key = KEYS.goal_result(goal_id)
        with self.cond:
            ok = self.cond.wait_for(lambda: any(k == key for k, _ in self.items), timeout_s)
            assert ok, f"no result for {goal_id}"
            return [b for k, b in self.items if k == key][-1]


@pytest.fixture
def manager(model: Any, pool: PlanningPool) -> Iterator[tuple[GoalManager, Published]]:
    """A goal manager on a simulated device, not started yet (its worker starts with ``start()``)."""
    published = Published()
    runner = make_runner("sim", model)
    runner.open()
    gm = GoalManager(KEYS, runner, lambda problem, options, cancel: _plan(pool, problem, options, cancel), published,
                     queue_limit=3)
    try:
        yield gm, published
    finally:
        gm.stop()
        runner.close()


def _plan(pool: PlanningPool, problem, options, cancel):
    result = pool.plan_blocking(problem, options, cancel, 10.0)
    return result.trajectory, result.report


def _goal(goal_m, goal_id=None, options=None, **fields: Any) -> Any:
    body: dict[str, Any] = {"goal_m": list(goal_m), **fields}
    if goal_id:
        body["id"] = goal_id
    if options:
        body["options"] = options
    return parse_goal_request(json.dumps(body).encode(), require_id=False)


def test_goals_run_in_order_and_the_queue_is_bounded(manager):
    gm, published = manager
    acks = [gm.submit(_goal(GOAL_A_M, "o1")), gm.submit(_goal(GOAL_B_M, "o2")), gm.submit(_goal(GOAL_A_M, "o3"))]
    assert [a["position"] for a in acks] == [0, 1, 2]
    with pytest.raises(RequestError) as info:
        gm.submit(_goal(GOAL_B_M, "o4"))
    assert info.value.code == "queue_full"
    with pytest.raises(RequestError) as info:
        gm.submit(_goal(GOAL_B_M, "o1"))
    assert info.value.code == "duplicate_goal_id" and info.value.field == "id"
    assert gm.cancel("o3") == {"schema_version": 1, "id": "o3", "instance": "gm0", "cancelled": True,
                               "status": "cancelled"}
    gm.start()
    results = [published.result(g) for g in ("o1", "o2", "o3")]
    assert [r["status"] for r in results] == ["done", "done", "cancelled"]
    assert results[0]["finished_at"] <= results[1]["started_at"]
    assert results[2]["started_at"] is None and results[2]["tracking_report"] is None
    # o2 started where o1 left the device: o1's final tracking error away from o1's goal
    offset_mm = 1e3 * float(np.linalg.norm(np.subtract(results[1]["start_m"], GOAL_A_M)))
    track = results[0]["tracking_report"]
    assert offset_mm == pytest.approx(track["tracking"]["final_mm"], abs=left_at_tolerance_mm(track))
    assert gm.cancel("o1")["cancelled"] is False  # finished goals are left alone
    with pytest.raises(RequestError) as info:
        gm.result("nope")
    assert info.value.code == "unknown_goal"


def test_cancel_while_planning_ends_the_goal_at_once(manager, pool):
    gm, published = manager
    gm.start()
    before = dict(pool.stats)
    gm.submit(_goal(GOAL_B_M, "long", LONG))
    wait_until(lambda: pool.busy()[0] == 1, "the plan to start", 30.0)
    assert gm.result("long")["status"] == "running"
    assert gm.cancel("long")["cancelled"]
    result = published.result("long", timeout_s=30)
    assert result["status"] == "cancelled"
    # the watchdog ended the plan on the cancel, not at its 10 s deadline (planning takes ~30 s)
    assert pool.stats["cancelled"] == before["cancelled"] + 1
    assert pool.stats["deadline_exceeded"] == before["deadline_exceeded"]


def test_a_planning_only_manager_refuses_goals():
    gm = GoalManager(KEYS, None, lambda *a: (None, {}), lambda *a: None)
    with pytest.raises(RequestError) as info:
        gm.submit(_goal(GOAL_A_M))
    assert info.value.code == "no_device"


def test_a_job_past_its_deadline_is_never_planned(pool):
    box: list[Any] = []
    done = threading.Event()
    before = dict(pool.stats)
    job = PlanJob(PlanProblem(HOME_M, (0.013, 0.0, 0.13)), None, time.monotonic() - 0.01,
                  lambda _j, o: (box.append(o), done.set()))
    pool.submit(job)
    assert done.wait(30)
    assert isinstance(box[0], RequestError) and box[0].code == "deadline_exceeded"
    assert "not planned" in str(box[0])
    assert pool.stats["dropped"] == before["dropped"] + 1 and pool.stats["planned"] == before["planned"]


def test_a_process_killed_after_it_answered_is_restarted_before_the_next_job(pool):
    """The watchdog may kill a planning process just after it answered (a cancel or a deadline
    at the moment the plan came back): the next job on that slot starts a new process instead
    of failing with ``internal_error``."""
    pool.plan_blocking(PlanProblem(HOME_M, GOAL_B_M), None, threading.Event(), 30.0)
    before = pool.stats["restarts"]
    slot = pool._slots[0]
    slot.kill()  # what the watchdog's late kill leaves: an idle slot whose process is gone
    assert slot.needs_restart()
    result = pool.plan_blocking(PlanProblem(HOME_M, GOAL_A_M), None, threading.Event(), 60.0)
    assert np.allclose(result.trajectory.position_m[-1], GOAL_A_M, atol=1e-4)
    assert pool.stats["restarts"] == before + 1 and not slot.needs_restart()


def test_thread_workers_answer_a_late_plan_on_time():
    pool = PlanningPool(1, falcon_planner, processes=False, name="thr-test")
    pool.start()
    try:
        with pytest.raises(RequestError) as info:
            pool.plan_blocking(PlanProblem(HOME_M, GOAL_A_M), MEDIUM, threading.Event(), 0.5)
        # the watchdog answered at the deadline (it counts what it ends), not the planner at its
        # end (planning takes seconds)
        assert info.value.code == "deadline_exceeded" and pool.stats["deadline_exceeded"] == 1
    finally:
        pool.close()


def test_option_errors_name_the_field_and_what_it_takes():
    def refusal(options: dict[str, Any]) -> RequestError:
        with pytest.raises(RequestError) as info:
            parse_plan_request(json.dumps({"start_m": list(HOME_M), "goal_m": list(GOAL_A_M),
                                           "options": options}).encode(), cap_s=30.0)
        return info.value

    err = refusal({"tc_max": -5})
    assert (err.code, err.field) == ("invalid_problem", "options.tc_max") and "4096" in err.allowed
    err = refusal({"warp": 1})
    assert (err.code, err.field) == ("invalid_request", "options.warp") and "hessian" in err.allowed
    err = refusal({"hessian": "magic"})
    assert err.field == "options.hessian" and "exact" in err.allowed
    err = refusal({"time_budget_s": 31})
    assert err.field == "options.time_budget_s" and err.allowed == "at most 30 s"
    request = parse_plan_request(json.dumps({"start_m": list(HOME_M), "goal_m": list(GOAL_A_M),
                                             "timeout_s": 2.5}).encode())
    assert request.timeout_s == 2.5


def test_the_budget_given_to_the_planner_binds_the_optimiser():
    planner = falcon_planner()
    outcome = planner(PlanProblem(HOME_M, GOAL_A_M), {"hessian": "exact", "n_intervals": 200}, 0.05)
    # the optimiser stopped at its 0.05 s budget (an exact-Hessian solve at N=200 takes
    # seconds) and the ruckig fallback answered; the report says so
    report = outcome.report
    assert report["method"] == "ruckig-fallback" and report["options"]["solver"]["time_budget_s"] == 0.05
    assert "time budget" in report["fallback_reason"], report["fallback_reason"]


# --- the problem fields of plan and goal requests ----------------------------------------------
VIA_M = (0.008, 0.012, 0.125)
"""A via point off the straight line HOME_M -> GOAL_A_M, inside the workspace."""


def _plan_body(**fields: Any) -> bytes:
    return json.dumps({"start_m": list(HOME_M), "goal_m": list(GOAL_A_M), **fields}).encode()


def test_a_plan_request_carries_the_whole_problem():
    old = parse_plan_request(_plan_body())  # the fields before via points and payloads still read
    assert old.problem == PlanProblem(HOME_M, GOAL_A_M)
    request = parse_plan_request(_plan_body(via_m=[list(VIA_M)], payload_kg=0.1, goal_velocity_m_s=[0.0, 0.05, 0.0],
                                            start_velocity_m_s=[0.01, 0.0, 0.0]))
    assert request.problem == PlanProblem(HOME_M, GOAL_A_M, (0.01, 0.0, 0.0), (0.0, 0.05, 0.0), (VIA_M,), 0.1)
    # the cache tells problems apart by every field, not only by their ends
    keys = {plan_cache_key(p, None) for p in (old.problem, request.problem,
                                               PlanProblem(HOME_M, GOAL_A_M, payload_kg=0.1))}
    assert len(keys) == 3 and plan_cache_key(old.problem, {"tc_max": 2000}) != plan_cache_key(old.problem, None)


BAD_PROBLEM_FIELDS = [
    ({"via_m": [[0.0, 0.0]]}, "invalid_request", "via_m[0]"),
    ({"via_m": [list(VIA_M), [0.0, True, 0.12]]}, "invalid_request", "via_m[1][1]"),
    ({"via_m": [list(VIA_M)] * 9}, "invalid_request", "via_m"),
    ({"payload_kg": -0.1}, "invalid_request", "payload_kg"),
    ({"payload_kg": 1.5}, "invalid_request", "payload_kg"),
    ({"payload_kg": "heavy"}, "invalid_request", "payload_kg"),
    ({"goal_velocity_m_s": [0.0, 9.0, 0.0]}, "invalid_request", "goal_velocity_m_s[1]"),
    ({"start_velocity_m_s": [4.0, 4.0, 0.0]}, "invalid_problem", "start_velocity_m_s"),  # speed 5.7 m/s
]


@pytest.mark.parametrize("fields,code,field", BAD_PROBLEM_FIELDS, ids=[b[2] + "-" + b[1] for b in BAD_PROBLEM_FIELDS])
def test_bad_problem_fields_name_the_field_and_what_is_allowed(fields, code, field):
    with pytest.raises(RequestError) as info:
        parse_plan_request(_plan_body(**fields))
    err = info.value
    assert (err.code, err.field) == (code, field), str(err)
    assert err.allowed and "\n" not in str(err) and len(str(err)) > 15


def test_schema_limits_agree_with_the_problem_type():
    """The published schema allows exactly what PlanProblem accepts at its ends."""
    from service.codec import load_schema

    props = load_schema("plan_request")["properties"]
    assert PlanProblem(HOME_M, GOAL_A_M, payload_kg=props["payload_kg"]["maximum"]).payload_kg == 1.0
    with pytest.raises(Exception, match="payload_kg"):
        PlanProblem(HOME_M, GOAL_A_M, payload_kg=props["payload_kg"]["maximum"] + 1e-9)
    n_via = props["via_m"]["maxItems"]
    assert len(PlanProblem(HOME_M, GOAL_A_M, via_m=[VIA_M] * n_via).via_m) == n_via
    with pytest.raises(Exception, match="via"):
        PlanProblem(HOME_M, GOAL_A_M, via_m=[VIA_M] * (n_via + 1))
    assert set(load_schema("goal_request")["properties"]) - {"id", "release", "preempt"} == set(props) - {"request_id", "timeout_s"}


def test_the_workspace_check_names_the_point_against_the_planners_model(model):
    request = parse_plan_request(_plan_body(via_m=[[0.0, 0.0, 0.30]]))
    with pytest.raises(RequestError) as info:
        require_in_workspace(request.problem, model)
    assert (info.value.code, info.value.field) == ("outside_workspace", "via_m[0]")
    assert "via_m[0]" in str(info.value) and "outside the workspace" in str(info.value)
    # the check uses the model it is given (the one the service plans with): limits with a
    # wider singularity margin refuse the start the nominal limits accept
    import dataclasses

    from falcon_plan.model.dynamics import FalconModel

    problem = PlanProblem(HOME_M, GOAL_A_M)
    require_in_workspace(problem, model)
    wary = FalconModel(model.params, limits=dataclasses.replace(model.limits, min_forward_det=0.7))
    with pytest.raises(RequestError) as info:
        require_in_workspace(problem, wary)
    assert info.value.field == "start_m"
    require_in_workspace(problem, wary, skip_start=True)  # a goal's start is where the device is


def test_goal_requests_carry_the_problem_and_start_where_the_device_is():
    goal = _goal(GOAL_A_M, via_m=[list(VIA_M)], payload_kg=0.05, goal_velocity_m_s=[0.0, 0.0, 0.02])
    assert goal.start_m is None and goal.goal_m == GOAL_A_M
    problem = goal.problem_from(HOME_M)
    assert problem == PlanProblem(HOME_M, GOAL_A_M, goal_velocity_m_s=(0.0, 0.0, 0.02), via_m=(VIA_M,),
                                  payload_kg=0.05)
    given = _goal(GOAL_A_M, start_m=list(HOME_M), start_velocity_m_s=[0.01, 0.0, 0.0])
    assert given.start_m == HOME_M and given.problem_from(HOME_M).start_velocity_m_s == (0.01, 0.0, 0.0)
    with pytest.raises(RequestError) as info:
        _goal(GOAL_A_M, start_velocity_m_s=[0.01, 0.0, 0.0])
    err = info.value
    assert (err.code, err.field) == ("invalid_request", "start_velocity_m_s") and "start_m" in str(err)
    with pytest.raises(RequestError) as info:
        _goal(GOAL_A_M, via_m=[[0.0, 0.1]])
    assert info.value.field == "via_m[0]"


def test_a_goal_with_a_via_point_and_a_payload_runs_through_the_via_point(manager):
    gm, published = manager
    gm.start()
    gm.submit(_goal(GOAL_B_M, "via-1", via_m=[list(VIA_M)], payload_kg=0.05))
    result = published.result("via-1", timeout_s=30)
    assert result["status"] == "done", result["error"]
    problem = result["plan_report"]["problem"]
    assert problem["payload_kg"] == 0.05 and problem["via_m"] == [list(VIA_M)]
    np.testing.assert_allclose(problem["start_m"], result["start_m"], atol=1e-12)


def test_a_fallback_that_skips_the_via_points_is_refused():
    planner = falcon_planner()
    # the optimiser cannot finish in 1 ms; the ruckig fallback would ignore the via point
    with pytest.raises(PlanningFailed) as info:
        planner(PlanProblem(HOME_M, GOAL_A_M, via_m=[VIA_M]), {"time_budget_s": 0.001}, None)
    assert "via points" in str(info.value) and info.value.report.method == "ruckig-fallback"
    err = planning_error(info.value)
    assert err.code == "planning_failed" and err.detail["fallback_reason"]
    # without via points the fallback is a valid answer, as before
    assert planner(PlanProblem(HOME_M, GOAL_A_M), {"time_budget_s": 0.001}, None).report["status"] == "fallback"


def test_plan_summary_states_the_peak_against_the_plans_own_bound() -> None:
    """The report's worst command ratio is against the bound the plan used (tc_max minus the
    feedback reserve, or the device limit), so the summary names that bound, not tc_max."""
    from service.commands.request import plan_summary

    line = plan_summary({"method": "casadi", "status": "optimal", "duration_s": 0.1, "total_time_s": 0.05,
                         "worst_command_ratio": 0.97, "tc_max": 2500.0,
                         "command_bound": "constant 2500 - 150 reserve"})
    assert line.endswith("peak |Tc| 97 % of its bound (constant 2500 - 150 reserve)")


def test_a_goal_says_whether_a_cancel_releases():
    body = {"schema_version": 1, "goal_m": [0.0, 0.0, 0.12]}
    assert parse_goal_request(json.dumps(body).encode(), require_id=False).release is False
    body["release"] = True
    assert parse_goal_request(json.dumps(body).encode(), require_id=False).release is True
    body["release"] = "yes"
    with pytest.raises(RequestError):
        parse_goal_request(json.dumps(body).encode(), require_id=False)


def test_a_preempting_goal_is_taken_when_the_queue_is_full(manager):
    """A full queue refuses a new goal, not a preempting one: that one takes over the motion (or,
    with nothing executing, goes first) instead of waiting behind the queue."""
    gm, _ = manager
    for k in range(3):
        gm.submit(_goal(GOAL_A_M if k % 2 else GOAL_B_M, f"f{k}"))
    with pytest.raises(RequestError) as info:
        gm.submit(_goal(GOAL_B_M, "late"))
    assert info.value.code == "queue_full"
    ack = gm.submit(_goal(GOAL_B_M, "now", preempt=True))
    assert ack["status"] == "pending" and ack["position"] == 0
