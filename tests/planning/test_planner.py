"""The planner end to end: feasibility on a dense re-check, agreement with toppra on its own
path, no slower than toppra on the straight line, ruckig slower but feasible, fallback,
refusals, JSON, CLI. Several problems, including moves along the edge of the workspace."""
from __future__ import annotations

import json

import numpy as np
import pytest

from falcon_plan.errors import InvalidProblemError, PlanningFailed, WorkspaceError
from falcon_plan.model.workspace import in_workspace
from falcon_plan.planning import fallback
from falcon_plan.planning.api import plan, plan_problem
from falcon_plan.planning.transcription import payload_model
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.trajectory import Trajectory

PROBLEMS = {
    "centre_diagonal": (PlanProblem((0.0, 0.0, 0.12), (0.03, 0.02, 0.14)), 2500.0),
    "edge_to_edge_x": (PlanProblem((-0.0648, 0.0, 0.125), (0.063, 0.0, 0.125)), 2500.0),
    "edge_lower_front": (PlanProblem((0.0, -0.0403, 0.1532), (0.0458, -0.0265, 0.1443)), 2500.0),
    "moving_start": (PlanProblem((-0.015, 0.0, 0.125), (0.015, 0.0, 0.125), start_velocity_m_s=(0.2, 0.0, 0.0)), 2500.0),
    "payload_up_tc3500": (PlanProblem((0.0, -0.02, 0.125), (0.0, 0.02, 0.125), payload_kg=0.1), 3500.0),
}


@pytest.fixture(scope="module", params=sorted(PROBLEMS))
def planned(request, model):
    problem, tc_max = PROBLEMS[request.param]
    options = PlanOptions.of(tc_max=tc_max, refine=False, plant_check=False)
    return problem, tc_max, plan_problem(problem, options, model)


def _dense_commands(model, traj: Trajectory, per_interval: int = 10) -> np.ndarray:
    """|Tc| at per_interval points inside every interval, recomputed here from the
    trajectory's own interpolation (independent of verify.py)."""
    t = np.concatenate([np.linspace(a, b, per_interval, endpoint=False) for a, b in zip(traj.t_s[:-1], traj.t_s[1:])])
    p, v, a = traj.at_time(t)
    return np.abs(model.inverse_dynamics(p, v, a)), p


def test_optimal_and_meets_the_boundary_conditions(planned) -> None:
    problem, _, result = planned
    traj, report = result.trajectory, result.report
    assert report.status == "optimal" and report.method == "casadi", report.summary()
    np.testing.assert_allclose(traj.position_m[0], problem.start_m, atol=1e-9)
    np.testing.assert_allclose(traj.position_m[-1], problem.goal_m, atol=1e-9)
    np.testing.assert_allclose(traj.velocity_m_s[0], problem.start_velocity_m_s, atol=1e-8)
    np.testing.assert_allclose(traj.velocity_m_s[-1], problem.goal_velocity_m_s, atol=1e-8)
    assert 0.02 < report.duration_s < 0.3


def test_commands_within_tc_max_on_dense_recheck(planned, model) -> None:
    problem, tc_max, result = planned
    limit = tc_max - PlanOptions().limits.feedback_reserve   # the reserve is kept free for feedback
    tc, points = _dense_commands(payload_model(model, problem), result.trajectory)
    assert tc.max() <= 1.01 * limit           # nodes and midpoints: < 1 % between
    assert tc.max() >= 0.98 * limit           # and it is a minimum-time plan: the limit is used
    assert in_workspace(points, model.params, model.limits).all()
    assert result.report.worst_command_ratio <= 1.01
    assert result.report.worst_workspace_margin >= 0.0


def test_agrees_with_toppra_on_its_own_path(planned) -> None:
    _, _, result = planned
    ratio = result.report.planner_over_toppra_same_path
    assert ratio is not None, result.report.notes
    assert abs(ratio - 1.0) <= 0.01


def test_no_slower_than_toppra_on_the_straight_line(planned) -> None:
    problem, _, result = planned
    ratio = result.report.planner_over_toppra_straight
    if not problem.is_rest_to_rest:
        assert ratio is None                  # not applicable with moving ends
        return
    assert ratio is not None and ratio <= 1.002


def test_ruckig_is_slower_but_feasible(planned, model) -> None:
    problem, tc_max, result = planned
    loaded = payload_model(model, problem)
    ref = fallback.ruckig_reference(loaded, problem, tc_max)
    assert ref.duration_s > result.report.duration_s
    assert ref.inside_workspace
    tc, _ = _dense_commands(loaded, ref.trajectory, per_interval=2)
    assert tc.max() <= tc_max
    np.testing.assert_allclose(ref.trajectory.position_m[-1], problem.goal_m, atol=1e-9)


def test_grid_refinement_changes_duration_little(model) -> None:
    """The transcription's refinement sequence: its other grid (N/2 or 2N) changes the
    duration by well under 1 % (second-order convergence), in the expected direction."""
    problem, tc_max = PROBLEMS["centre_diagonal"]
    options = PlanOptions.of(tc_max=tc_max, crosscheck=False, plant_check=False, switching=False)
    report = plan_problem(problem, options, model).report
    assert report.refinement_change is not None and abs(report.refinement_change) < 0.01
    coarser = report.refinement_intervals < report.n_intervals
    assert (report.refinement_change > 0) == coarser


def test_active_workspace_limit_is_imposed_and_held() -> None:
    """With theta1_min raised by 0.3 rad, the minimum-time move edge_left_to_bottom (whose
    leg 2 dips 0.16 rad lower inside the move than at its ends) must bend around the limit:
    the screening solve leaves the workspace, the full NLP imposes it, and the dense re-check
    finds every margin >= 0; toppra on that path still agrees."""
    import math

    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.workspace import WorkspaceLimits
    tight = FalconModel(limits=WorkspaceLimits(theta1_min_rad=math.radians(-20.0) + 0.3))
    problem = PlanProblem((-0.0648, 0.0, 0.125), (-0.0315, -0.0545, 0.125))
    # budgets far above the ~2 s these take, so a loaded machine cannot turn them into fallbacks
    free = plan_problem(problem, PlanOptions.fast(time_budget_s=120.0)).report
    report = plan_problem(problem, PlanOptions.of(refine=False, plant_check=False, time_budget_s=120.0), tight).report
    assert free.workspace_constraints.startswith("inactive")
    assert report.method == "casadi" and report.workspace_constraints == "imposed (active)"
    assert 0.0 <= report.worst_workspace_margin < 0.01 and report.worst_margin_name.startswith("theta1_low")
    assert report.duration_s > free.duration_s
    assert abs(report.planner_over_toppra_same_path - 1.0) <= 0.01


def test_via_points_are_passed(model) -> None:
    problem = PlanProblem((-0.03, 0.0, 0.12), (0.03, 0.0, 0.12), via_m=[(0.0, 0.02, 0.13)])
    result = plan_problem(problem, PlanOptions.fast(), model)
    assert result.report.method == "casadi"
    gaps = np.linalg.norm(result.trajectory.position_m - np.array(problem.via_m[0]), axis=1)
    assert gaps.min() < 1e-9


def test_tiny_time_budget_uses_the_ruckig_fallback(model) -> None:
    problem, _ = PROBLEMS["centre_diagonal"]
    result = plan_problem(problem, PlanOptions.fast(time_budget_s=1e-4), model)
    report = result.report
    assert report.method == "ruckig-fallback" and report.status == "fallback"
    assert "time budget" in report.fallback_reason
    assert report.worst_command_ratio <= 1.0
    np.testing.assert_allclose(result.trajectory.position_m[-1], problem.goal_m, atol=1e-9)
    with pytest.raises(PlanningFailed) as info:
        plan_problem(problem, PlanOptions.fast(time_budget_s=1e-4, fallback=False), model)
    assert info.value.report.status == "failed"


def test_refusals_are_clear_errors_not_solver_crashes(model) -> None:
    with pytest.raises(WorkspaceError, match="goal .* outside the workspace"):
        plan((0.0, 0.0, 0.12), (0.0, 0.0, 0.22), PlanOptions.fast(), model)
    with pytest.raises(WorkspaceError, match="start .* outside the workspace"):
        plan((0.1, 0.0, 0.125), (0.0, 0.0, 0.12), PlanOptions.fast(), model)
    with pytest.raises(InvalidProblemError, match="tc_max_too_small"):
        plan((0.0, -0.03, 0.125), (0.0, 0.0, 0.125), PlanOptions.fast(), model, payload_kg=0.5)


def test_trajectory_and_report_json_round_trip(model) -> None:
    result = plan((0.0, 0.0, 0.12), (0.01, -0.01, 0.125), PlanOptions.fast(), model)
    again = Trajectory.from_json(result.trajectory.to_json())
    np.testing.assert_allclose(again.t_s, result.trajectory.t_s)
    np.testing.assert_allclose(again.position_m, result.trajectory.position_m)
    np.testing.assert_allclose(again.commands, result.trajectory.commands)
    report = json.loads(json.dumps(result.report.to_dict()))
    assert report["method"] == "casadi" and report["duration_s"] == pytest.approx(result.trajectory.duration_s)


def test_cli_prints_the_report(capsys) -> None:
    from falcon_plan.cli import main
    assert main(["plan", "--from", "0,0,0.12", "--to", "0.02,0.01,0.13", "--fast", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["status"] == "optimal" and report["tc_max"] == 2500.0
    assert main(["plan", "--from", "0,0,0.12", "--to", "0.3,0,0.12"]) == 2
    assert "outside the workspace" in capsys.readouterr().err


def test_plant_check_runs_and_passes(model) -> None:
    from falcon_plan.planning import verify
    result = plan((0.0, 0.0, 0.12), (0.02, 0.01, 0.13), PlanOptions.fast(), model)
    check = verify.plant_check(model, result.trajectory)
    assert check.ran and check.note == "", check.note
    # the paper's PD with the plan's feed-forward: ~1.3 mm while moving, settled within 0.5 mm
    assert check.passed and check.max_error_mm < verify.PLANT_MAX_ERROR_MM
    assert check.final_error_mm < verify.PLANT_FINAL_ERROR_MM


def test_plant_check_reports_a_run_that_fails(model) -> None:
    """A plant run that raises (here: a trajectory shifted out of reach) is reported, not
    raised: ``ran`` False, ``passed`` False and the error in ``note``."""
    from falcon_plan.planning import verify
    from falcon_plan.trajectory import Trajectory
    t = plan((0.0, 0.0, 0.12), (0.02, 0.01, 0.13), PlanOptions.fast(), model).trajectory
    shifted = Trajectory(t.t_s, t.position_m + np.array([0.3, 0.0, 0.0]), t.velocity_m_s, t.acceleration_m_s2,
                         t.commands, t.params_name, t.source, t.meta, t.interpolation)
    check = verify.plant_check(model, shifted)
    assert (check.ran, check.passed) == (False, False) and "not reachable" in check.note


def test_report_warns_when_tc_max_exceeds_the_static_saturation() -> None:
    """Above 2500 the device gives more only once the legs move: the report says so."""
    above = plan((0.0, 0.0, 0.12), (0.03, 0.02, 0.14), PlanOptions.fast(tc_max=4096)).report
    at = plan((0.0, 0.0, 0.12), (0.03, 0.02, 0.14), PlanOptions.fast(tc_max=2500)).report
    assert any("static saturation 2500" in note for note in above.notes)
    assert not any("static saturation" in note for note in at.notes)
    assert above.duration_s < at.duration_s


def test_a_plan_failing_the_dense_recheck_is_resolved_on_the_doubled_grid(model) -> None:
    """With a tight tolerance the N plan fails the dense re-check; the re-solve doubles every
    segment (via points stay at segment ends), starts from the same motion and passes."""
    problem = PlanProblem((-0.03, 0.0, 0.12), (0.03, 0.02, 0.14), via_m=[(0.0, 0.03, 0.13)])
    result = plan_problem(problem, PlanOptions.fast(command_tolerance=0.001), model)
    report, traj = result.report, result.trajectory
    assert report.method == "casadi" and any("re-solved with N=72" in n for n in report.notes), report.notes
    assert report.n_intervals == 72 and tuple(traj.meta["segments"]) == (40, 32)
    assert report.worst_command_ratio <= 1.001
    assert np.abs(traj.position_m[40] - np.array([0.0, 0.03, 0.13])).max() < 1e-6


def test_numpys_blas_runs_on_one_thread_once_the_planner_has_solved(model) -> None:
    """The switching-time solve's small Newton steps go through numpy's bundled OpenBLAS, whose
    worker threads wait on a loaded machine (a device-limit plan took 3-4 s of wall time for
    0.6 s of CPU): once the planner has solved, it runs on one thread, as CasADi's does."""
    import ctypes

    from falcon_plan.planning.transcription import SINGLE_THREADED_LIBRARIES

    plan((0.0, 0.0, 0.12), (0.01, 0.0, 0.12), PlanOptions.fast(), model)
    folder, pattern, _ = SINGLE_THREADED_LIBRARIES[2]
    libraries = sorted(folder.glob(pattern))
    if not libraries:
        pytest.skip("this numpy has no bundled OpenBLAS")
    library = ctypes.CDLL(str(libraries[0]))
    getters = [s for s in ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads",
                           "openblas_get_num_threads") if hasattr(library, s)]
    assert getters, f"{libraries[0].name} names no thread-count getter"
    assert getattr(library, getters[0])() == 1


FAST_MOVING_START = PlanProblem((0.040928, -0.002868, 0.150804), (0.022232, -0.0564, 0.134113),
                                start_velocity_m_s=(0.152923, -1.241913, -0.510878))
"""bench_replan's case 66: a nudge of the goal while the grip moves at 1.35 m/s."""


def test_a_fast_moving_start_is_planned_by_the_optimiser(model) -> None:
    """From a straight-line guess that ignored the start's speed IPOPT ran out of iterations
    at every N from 16 to 64 on this problem, and ruckig's fallback left the reachable set:
    no plan. From a guess that carries the speed on and brings it to rest within the motion
    (:func:`~falcon_plan.planning.transcription.initial_guess`) it plans (the switching-time
    plan from the coarse pattern), starts with the start's state, and stays within the bound
    on the dense re-check."""
    problem = FAST_MOVING_START
    report = plan_problem(problem, PlanOptions.of(plant_check=False, crosscheck=False), model).report
    assert report.method == "casadi" and report.switching is not None, report.notes
    traj = plan_problem(problem, PlanOptions.fast(), model).trajectory
    np.testing.assert_allclose(traj.velocity_m_s[0], problem.start_velocity_m_s, atol=1e-9)
    commands, _ = _dense_commands(payload_model(model, problem), traj)
    assert commands.max() <= 2500.0 * (1 + 1e-3)
    assert report.converged_duration_s == pytest.approx(report.duration_s, rel=1e-3)


def test_the_initial_guess_meets_both_ends_and_carries_their_speeds(model) -> None:
    """At rest, the guess is the straight line at +-a then -+a (arc length 0.5 a t^2 to the
    middle, recomputed here); a moving start's guess begins at the start with its speed (the
    first interval's mean velocity tends to it as N grows) and ends at the goal."""
    from falcon_plan.planning.transcription import initial_guess

    rest = PlanProblem((0.0, 0.0, 0.12), (0.03, 0.0, 0.12))
    g = initial_guess(model, rest, 40, 2500.0, [])
    t = np.linspace(0.0, g.duration_s, 41)
    a = 4.0 * 0.03 / g.duration_s ** 2
    s = np.where(t <= g.duration_s / 2, 0.5 * a * t ** 2, 0.03 - 0.5 * a * (g.duration_s - t) ** 2)
    np.testing.assert_allclose(g.p[:, 0], s, atol=1e-12)
    moving = FAST_MOVING_START
    slopes = []
    for n in (50, 400):
        g = initial_guess(model, moving, n, 2500.0, [])
        np.testing.assert_allclose(g.p[0], moving.start_m, atol=1e-12)
        np.testing.assert_allclose(g.p[-1], moving.goal_m, atol=1e-12)
        slopes.append(np.abs((g.p[1] - g.p[0]) * n / g.duration_s - moving.start_velocity_m_s).max())
    assert slopes[1] < 0.2 * slopes[0] and slopes[1] < 0.02


def test_an_unreachable_goal_speed_fails_as_planning_not_as_bad_trajectory_data(model, capfd) -> None:
    """A goal speed within the allowed range (5 m/s) that no motion reaches: the optimiser's
    failed iterate left the reachable set (NaN commands), which used to end the request as
    invalid_problem "trajectory field commands holds NaN" after thousands of CasADi NaN warnings;
    now PlanningFailed, saying the end speed may be out of reach, without the flood."""
    from falcon_plan.errors import PlanningFailed

    with pytest.raises(PlanningFailed, match="an end speed may be more than the device can reach"):
        plan((0.0, 0.0, 0.12), (0.02, 0.01, 0.13), PlanOptions.fast(), model, goal_velocity_m_s=(0.0, 0.0, 4.9))
    assert capfd.readouterr().err.count("NaN detected") == 0
