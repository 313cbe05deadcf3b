"""How close the plans are to the true optimum, and the report's estimate of it.

The durations converge at second order in 1/N with the linear acceleration profile and at
first order with a constant acceleration per interval; the report's converged duration is a
Richardson extrapolation of N/2 and N (or N and 2N when the first is not conclusive).
Checked against separate solves at 192 intervals."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.planning.api import plan
from falcon_plan.planning.min_time import solve_min_time
from falcon_plan.planning.transcription import MinTimeSettings
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.refinement import extrapolate, grid_refinement, resampled_guess

PROBLEM = PlanProblem((-0.025, -0.025, 0.105), (0.025, 0.025, 0.145))   # across_diagonal


def _durations(model, profile: str, ns: tuple[int, ...]) -> list[float]:
    bound = PlanOptions.of(profile=profile).command_bound(model.params)
    out = []
    for n in ns:
        result = solve_min_time(model, PROBLEM, bound, MinTimeSettings(n, profile=profile))
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
    """The transcription alone (``switching=False``): the plan is within 0.3 % of a separate
    192-interval solve, and the report's extrapolated converged duration and gap agree with
    it: to 0.2 % when estimated from the N/2 partner (the cheap refinement sequence), to
    0.03 % from 2N."""
    report = plan(start, goal, PlanOptions.of(crosscheck=False, plant_check=False, switching=False), model).report
    bound = PlanOptions().command_bound(model.params)
    fine = solve_min_time(model, PlanProblem(start, goal), bound, MinTimeSettings(192))
    assert fine.success
    true_gap = (report.duration_s - fine.duration_s) / fine.duration_s
    assert 0.0 < true_gap <= 0.003
    accuracy = 2e-3 if report.refinement_intervals < report.n_intervals else 3e-4
    assert report.converged_duration_s == pytest.approx(fine.duration_s, rel=accuracy)
    assert report.optimality_gap == pytest.approx(true_gap, abs=accuracy)
    assert "converged duration" in report.summary()


def test_coarse_partner_estimates_like_two_separate_solves(model) -> None:
    """grid_refinement(coarser=True) from a plan at N gives the same N/2 duration as a cold
    solve at N/2 (the warm start changes only the starting point) and Richardson's value
    from those two durations."""
    bound = PlanOptions().command_bound(model.params)
    plan24 = solve_min_time(model, PROBLEM, bound, MinTimeSettings(24))
    cold12 = solve_min_time(model, PROBLEM, bound, MinTimeSettings(12))
    partner = grid_refinement(model, PROBLEM, plan24.trajectory, bound, coarser=True)
    assert partner.n_intervals == 12
    assert partner.duration_s == pytest.approx(cold12.duration_s, rel=1e-5)
    t_inf = plan24.duration_s + (plan24.duration_s - cold12.duration_s) / 3.0
    assert partner.converged_duration_s == pytest.approx(t_inf, rel=1e-5)
    assert partner.gap == pytest.approx((plan24.duration_s - t_inf) / t_inf, abs=1e-5)


def test_resampled_guess_is_exact_on_a_nested_grid(model) -> None:
    """Splitting every interval of a linear-acceleration plan in two describes the same motion:
    the guess's nodes lie on the plan, and the old nodes are every other new node."""
    traj = solve_min_time(model, PROBLEM, PlanOptions().command_bound(model.params), MinTimeSettings(12)).trajectory
    guess = resampled_guess(traj, (12,), (24,))
    np.testing.assert_allclose(guess.p[::2], traj.position_m, atol=1e-12)
    np.testing.assert_allclose(guess.a[::2], traj.acceleration_m_s2, atol=1e-9)
    p, v, a = traj.at_time(guess.times_s)
    np.testing.assert_allclose(guess.p, p, atol=1e-12)
    np.testing.assert_allclose(guess.v, v, atol=1e-12)
    assert guess.duration_s == pytest.approx(traj.duration_s, rel=1e-12)


def test_extrapolation_is_exact_for_a_pure_power_law() -> None:
    for order in (1, 2):
        t = [1.0 + 0.3 / n ** order for n in (10, 20)]
        assert extrapolate(t[0], t[1], order) == pytest.approx(1.0, abs=1e-14)
        t = [1.0 + 0.3 / n ** order for n in (12, 30)]
        assert extrapolate(t[0], t[1], order, ratio=2.5) == pytest.approx(1.0, abs=1e-14)


def test_linear_profile_trajectory_is_exact_between_the_nodes(model) -> None:
    """at_time of a linear-acceleration plan: velocity is the derivative of position and
    acceleration that of velocity (central differences), continuous across the nodes."""
    traj = plan((0.0, 0.0, 0.12), (0.02, 0.01, 0.13), PlanOptions.fast(switching=False), model).trajectory
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
    """The transcription alone: the long move at tc_max 1500 is about 0.4 % above the
    converged duration at the default N; with refine (default) the report says so and
    returns the 2N plan, within the target."""
    start, goal = (-0.025, -0.025, 0.105), (0.025, 0.025, 0.145)
    options = PlanOptions.of(tc_max=1500, crosscheck=False, plant_check=False, switching=False)
    report = plan(start, goal, options, model).report
    coarse = plan(start, goal, PlanOptions.fast(tc_max=1500, switching=False), model).report
    assert report.n_intervals == 2 * coarse.n_intervals
    assert any("returned the N=" in note for note in report.notes)
    assert report.optimality_gap <= options.checks.optimality_target < (coarse.duration_s - report.converged_duration_s) \
        / report.converged_duration_s
    assert report.worst_command_ratio <= 1.01
    # the sequence's other grid is then the N plan
    assert report.refinement_intervals == coarse.n_intervals
    assert report.refined_duration_s == pytest.approx(coarse.duration_s, rel=1e-9)
    assert report.refinement_change > 0
