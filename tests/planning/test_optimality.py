"""How close the plans are to the true optimum, and the report's estimate of it.

The durations converge at second order in 1/N with the linear acceleration profile and at
first order with a constant acceleration per interval; the report's converged duration is a
Richardson extrapolation of N and 2N. Checked against separate solves at 192 intervals."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.planning.api import plan
from falcon_plan.planning.casadi_planner import solve_min_time
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.verify import extrapolate

PROBLEM = PlanProblem((-0.025, -0.025, 0.105), (0.025, 0.025, 0.145))   # across_diagonal


def _durations(model, profile: str, ns: tuple[int, ...]) -> list[float]:
    bound = PlanOptions.of(profile=profile).command_bound(model.params)
    out = []
    for n in ns:
        result = solve_min_time(model, PROBLEM, n_intervals=n, bound=bound, profile=profile)
        assert result.success, result.solver_status
        out.append(result.duration_s)
    return out


@pytest.mark.parametrize("profile, order", [("linear", 2), ("constant", 1)])
def test_durations_converge_at_the_stated_order(model, profile: str, order: int) -> None:
    t12, t24, t48 = _durations(model, profile, (12, 24, 48))
    assert t12 > t24 > t48
    ratio = (t12 - t24) / (t24 - t48)          # 2^order for a clean asymptotic sequence
    assert 0.7 * 2 ** order < ratio < 1.4 * 2 ** order


@pytest.mark.slow
@pytest.mark.parametrize("start, goal", [((-0.025, -0.025, 0.105), (0.025, 0.025, 0.145)),
                                         ((0.0, 0.0, 0.125), (0.02, 0.0, 0.125)),
                                         ((0.0, 0.03, 0.10), (0.0, -0.02, 0.13))])
def test_report_estimates_the_converged_duration(model, start, goal) -> None:
    """Default options: the plan is within 0.3 % of a separate 192-interval solve, and the
    report's extrapolated converged duration and gap agree with it."""
    report = plan(start, goal, PlanOptions.of(crosscheck=False, plant_check=False), model).report
    bound = PlanOptions().command_bound(model.params)
    fine = solve_min_time(model, PlanProblem(start, goal), n_intervals=192, bound=bound, profile="linear")
    assert fine.success
    true_gap = (report.duration_s - fine.duration_s) / fine.duration_s
    assert 0.0 < true_gap <= 0.003
    assert report.converged_duration_s == pytest.approx(fine.duration_s, rel=3e-4)
    assert report.optimality_gap == pytest.approx(true_gap, abs=3e-4)
    assert "converged duration" in report.summary()


def test_extrapolation_is_exact_for_a_pure_power_law() -> None:
    for order in (1, 2):
        t = [1.0 + 0.3 / n ** order for n in (10, 20)]
        assert extrapolate(t[0], t[1], order) == pytest.approx(1.0, abs=1e-14)


def test_linear_profile_trajectory_is_exact_between_the_nodes(model) -> None:
    """at_time of a linear-acceleration plan: velocity is the derivative of position and
    acceleration that of velocity (central differences), continuous across the nodes."""
    traj = plan((0.0, 0.0, 0.12), (0.02, 0.01, 0.13), PlanOptions.fast(), model).trajectory
    assert traj.interpolation == "linear"
    dt = 1e-6
    t = np.linspace(0.0, traj.duration_s, 997)[1:-1]
    t = t[np.min(np.abs(t[:, None] - traj.t_s[None, :]), axis=1) > 2 * dt]   # inside the intervals
    p1, v1, _ = traj.at_time(t + dt)
    p0, v0, _ = traj.at_time(t - dt)
    _, v, a = traj.at_time(t)
    np.testing.assert_allclose((p1 - p0) / (2 * dt), v, atol=1e-8)
    np.testing.assert_allclose((v1 - v0) / (2 * dt), a, atol=1e-4 * np.abs(a).max())
    # each interval's end meets the next node: continuous position, velocity, acceleration
    p_left, v_left, a_left = traj.at_time(traj.t_s[1:-1] - 1e-12)
    np.testing.assert_allclose(p_left, traj.position_m[1:-1], atol=1e-9)
    np.testing.assert_allclose(v_left, traj.velocity_m_s[1:-1], atol=1e-7)
    np.testing.assert_allclose(a_left, traj.acceleration_m_s2[1:-1], atol=1e-6 * np.abs(a).max())


@pytest.mark.slow
def test_a_plan_too_far_from_the_optimum_is_replaced_by_its_refinement(model) -> None:
    """The long move at tc_max 1500 is about 0.4 % above the converged duration at the default
    N; with refine (default) the report says so and returns the 2N plan, within the target."""
    start, goal = (-0.025, -0.025, 0.105), (0.025, 0.025, 0.145)
    options = PlanOptions.of(tc_max=1500, crosscheck=False, plant_check=False)
    report = plan(start, goal, options, model).report
    coarse = plan(start, goal, PlanOptions.fast(tc_max=1500), model).report
    assert report.n_intervals == 2 * coarse.n_intervals
    assert any("returned the N=" in note for note in report.notes)
    assert report.optimality_gap <= options.checks.optimality_target < (coarse.duration_s - report.converged_duration_s) \
        / report.converged_duration_s
    assert report.worst_command_ratio <= 1.01
