"""The switching-time solve (exact bang-bang plans), checked against what it does not share:
separate 192-interval transcriptions (another formulation of the same problem), finite
differences of its own equations, a full re-solve, and the simulated plant."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.errors import InvalidProblemError
from falcon_plan.execution.executor import Executor
from falcon_plan.planning import integration, pattern, shooting
from falcon_plan.planning.api import plan, plan_problem
from falcon_plan.planning.min_time import solve_min_time
from falcon_plan.planning.transcription import MinTimeSettings, payload_model
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.trajectory import Trajectory

PROBLEMS = {
    "across_diagonal": PlanProblem((-0.025, -0.025, 0.105), (0.025, 0.025, 0.145)),
    "short_x": PlanProblem((0.0, 0.0, 0.125), (0.02, 0.0, 0.125)),   # a leg starts with a short pulse
    "payload_moving_goal": PlanProblem((0.0, 0.03, 0.10), (0.0, -0.02, 0.13), goal_velocity_m_s=(0.0, -0.2, 0.1),
                                       payload_kg=0.1),
}


def _solved(model, problem: PlanProblem, tc_max: float = 2500.0):
    bound = PlanOptions.of(tc_max=tc_max).command_bound(model.params)
    coarse = pattern.coarse_solve(model, problem, bound, time_budget_s=5.0, hessian="limited-memory")
    guess = pattern.candidate_patterns(coarse.trajectory, bound.tc_max - bound.reserve,
                                           pattern.via_times(problem, coarse.trajectory))[0]
    return bound, shooting.solve_switching(model, problem, bound, guess, coarse.duration_s)


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_duration_matches_an_independent_high_resolution_solve(model, name: str) -> None:
    """Within 0.02 % of a separate 192-interval transcription (whose own error is ~0.01 %),
    and shorter than the transcription at the default N = 24."""
    problem = PROBLEMS[name]
    bound, solved = _solved(model, problem)
    assert solved.success, solved.reason
    assert solved.worst_help >= -shooting.CHECK_TOLERANCE
    fine = solve_min_time(model, problem, bound, MinTimeSettings(192))
    default = solve_min_time(model, problem, bound, MinTimeSettings(24))
    assert fine.success and default.success
    assert solved.duration_s == pytest.approx(fine.duration_s, rel=2e-4)
    assert solved.duration_s < default.duration_s


@pytest.mark.parametrize("limit", ["constant", "device"])
def test_terminal_jacobian_matches_finite_differences(model, limit: str) -> None:
    """linearise's Jacobian (forward differences in the phase durations, each run again from
    its phase on) against central differences in every event time and T of whole runs, under
    both command rules (the device's L(w_s) has kinks in its second derivative)."""
    from falcon_plan.planning.replan import pattern_of_report

    problem = PROBLEMS["across_diagonal"]
    options = PlanOptions.fast(limit=limit)
    report = plan_problem(problem, options, model).report
    solved = shooting.solve_switching(model, problem, options.command_bound(model.params),
                                      pattern_of_report(report.switching), report.duration_s)
    assert solved.success, solved.reason
    equations = shooting.Shooting(model, problem, solved.pattern, solved.rule, list(solved.counts))
    z = np.append(solved.pattern.times_s, solved.duration_s)
    _, g = equations.linearise(z)
    delta = 1e-7
    fd = np.column_stack([(equations.residual(z + delta * e) - equations.residual(z - delta * e)) / (2 * delta)
                          for e in np.eye(len(z))])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_optimality_check_sensitivities_match_finite_differences(model) -> None:
    """The check's per-step figure, -dT/du in the command's own direction, from the adjoint
    pass, equals a finite difference: raise one step's command, re-solve the terminal
    equations for (switch times, T) by Newton's method, and see T change."""
    problem = PROBLEMS["short_x"]
    bound, solved = _solved(model, problem)
    equations = shooting.Shooting(model, problem, solved.pattern, solved.rule, shooting.STEPS_PER_PHASE)
    z = np.append(solved.pattern.times_s, solved.duration_s)
    _, g = equations.linearise(z)
    helps = shooting._helps(equations, z, g)
    phases, steps = equations.plan(z)
    hs, u0s, u1s, phase, signs = steps.h, steps.u0, steps.u1, steps.phase, phases.signs
    regular = [n for n, j in enumerate(phase) if j >= 0]
    delta = 1.0  # command units
    level = solved.rule.level
    for pick in (0, len(regular) // 2, len(regular) - 1):
        n = regular[pick]
        leg = int(np.argmax(np.abs(helps[pick])))
        bump = np.zeros((len(hs), 3))
        bump[n, leg] = delta * signs[leg, phase[n]]
        bumped = equations.stepper.run(equations.x0, equations.eff, level, hs, u0s, u1s, deltas=bump)
        base = equations.stepper.run(equations.x0, equations.eff, level, hs, u0s, u1s)
        dz = np.linalg.solve(g, -(bumped[-1] - base[-1]))   # re-solve to first order
        assert -dz[-1] / delta == pytest.approx(helps[pick, leg], rel=2e-3)


def test_refinement_step_equals_a_full_solve_with_twice_the_steps(model) -> None:
    problem = PROBLEMS["across_diagonal"]
    bound, solved = _solved(model, problem)
    t_fine, t_inf = shooting.refinement(model, problem, solved)
    full = shooting.solve_switching(model, problem, bound, solved.pattern, solved.duration_s,
                                     2 * solved.steps_per_phase)
    assert full.success
    # both are converged to the solve's tolerance (1e-7 m, 1e-5 m/s at the goal): they agree
    # within 1e-8 s (~1e-7 of T; measured 5.5e-9 s from 2 steps per phase to 4)
    assert t_fine == pytest.approx(full.duration_s, abs=1e-8)
    # the solve's own integration error (2 RK4 steps per phase): 1.1e-5 of T here, a hundredth
    # of the 0.3 % the planner promises
    assert abs(t_inf - solved.duration_s) < 3e-5 * solved.duration_s


def test_default_plan_is_the_exact_bang_bang_motion_and_is_tracked_from_rest(model, tmp_path) -> None:
    """The default plan: solved by switching times, within 0.001 % of its own converged
    estimate, commands within the bound between the nodes, ends on the goal at rest, and the
    executor on the simulated plant tracks it from rest within 0.3 mm RMS."""
    start, goal = (-0.025, -0.025, 0.105), (0.025, 0.025, 0.145)
    result = plan(start, goal, PlanOptions.of(crosscheck=False), model)
    report = result.report
    assert report.method == "casadi" and report.switching is not None and report.switching["success"]
    assert report.n_intervals == pattern.COARSE_INTERVALS
    assert abs(report.optimality_gap) < 1e-5
    assert report.refinement_intervals == 2 * shooting.STEPS_PER_PHASE * (sum(len(s) for s in report.switching["switches_s"]) + 1)
    assert report.worst_command_ratio <= 1.005
    traj = result.trajectory
    np.testing.assert_allclose(traj.position_m[[0, -1]], [start, goal], atol=1e-12)
    np.testing.assert_allclose(traj.velocity_m_s[-1], 0.0, atol=1e-12)
    assert report.plant["ran"] and report.plant["passed"], report.plant
    assert "bang-bang" in report.summary()
    with SimDevice(model=model, seed=0, start_position_m=np.asarray(start)) as device:
        device.home()
        run = Executor(device, model, log_path=tmp_path / "run.csv", preroll_s=0.5).run(traj)
    assert run.status == "completed", run.reason
    assert run.tracking.norm_rms_mm <= 0.3, run.summary()


def test_a_via_point_is_passed_exactly_and_faster_than_the_transcription(model) -> None:
    """With a via point the solve adds the time it is passed and its position (3 equations):
    the plan goes through it at a node, within 0.02 % of a 192-interval transcription."""
    via = PlanProblem((0.0, 0.0, 0.125), (0.03, 0.0, 0.125), via_m=((0.015, 0.0, 0.155),))   # via_depth
    report_plan = plan_problem(via, PlanOptions.of(crosscheck=False, plant_check=False), model)
    report = report_plan.report
    assert report.switching is not None and len(report.switching["via_s"]) == 1, report.notes
    # the finer integration's steps: twice the plan's per phase, the via point an event of its own
    assert report.refinement_intervals == 2 * shooting.STEPS_PER_PHASE * (sum(len(s) for s in report.switching["switches_s"]) + 1 + 1)
    traj = report_plan.trajectory
    assert np.min(np.linalg.norm(traj.position_m - np.asarray(via.via_m[0]), axis=1)) < 1e-12
    bound = PlanOptions().command_bound(model.params)
    fine = solve_min_time(model, via, bound, MinTimeSettings(192))
    assert report.duration_s == pytest.approx(fine.duration_s, rel=2e-4)
    assert abs(report.optimality_gap) < 1e-4


VIA_OVER_TOP = PlanProblem((-0.035, 0.0, 0.125), (0.035, 0.0, 0.125), via_m=((0.0, 0.03, 0.125),))  # problems/via_over_top.json


def test_more_switches_than_equations_minimise_the_duration_over_the_surplus(model) -> None:
    """via_over_top: leg 1 switches four times, 8 switches + the via time + T against 9
    equations. The plan is the minimum of T over the one surplus switch time (the others
    solved from the equations): within 0.02 % of a separate 192-interval transcription
    (whose own error here is ~6e-5), and moving the surplus switch either way, the others
    re-solved by Newton's method, lengthens the motion."""
    problem = VIA_OVER_TOP
    report = plan_problem(problem, PlanOptions.fast(refine=True), model).report
    assert report.switching is not None and report.switching["surplus"] == 1, report.notes
    bound = PlanOptions().command_bound(model.params)
    fine = solve_min_time(model, problem, bound, MinTimeSettings(192))
    assert report.duration_s == pytest.approx(fine.duration_s, rel=2e-4)
    assert report.duration_s < 0.9985 * plan_problem(problem, PlanOptions.fast(switching=False, refine=True),
                                                     model).report.duration_s

    _, solved = _solved(model, problem)
    equations = shooting.Shooting(payload_model(model, problem), problem, solved.pattern, solved.rule,
                                    solved.steps_per_phase)
    z = np.append(solved.pattern.times_s, solved.duration_s)
    r, g = equations.linearise(z)
    dependent, free = shooting._family_split(g)
    for shift in (-5e-4, 5e-4):  # s
        moved = z.copy()
        moved[free] += shift
        z_moved, _, _, _, why = shooting._newton(equations, moved, equations.residual(moved), g, dependent)
        assert not why
        assert z_moved[-1] > solved.duration_s + 1e-8


def test_a_minimisation_that_cannot_beat_a_given_duration_gives_up(model) -> None:
    """via_over_top's surplus switch: asked to beat a T 1 % below its minimum, the
    minimisation gives up (CANNOT_BEAT) after fewer exact Jacobians than the full solve; asked
    to beat one 1 % above, it finds the same minimum."""
    problem = VIA_OVER_TOP
    bound, solved = _solved(model, problem)
    assert solved.success and solved.surplus == 1, solved.reason
    times = np.array(solved.pattern.times_s)
    times[1::3] += 1.5e-3  # s: off the minimum, so that the minimisation takes steps
    start = solved.pattern.with_times(times), solved.duration_s
    free = shooting.solve_switching(model, problem, bound, *start)
    assert free.success
    short = shooting.solve_switching(model, problem, bound, *start, beat_s=0.99 * free.duration_s)
    assert not short.success and short.reason == shooting.CANNOT_BEAT
    assert short.jacobians < free.jacobians and short.duration_s > 0.99 * free.duration_s
    long = shooting.solve_switching(model, problem, bound, *start, beat_s=1.01 * free.duration_s)
    assert long.success and long.duration_s == pytest.approx(free.duration_s, rel=1e-9)


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_the_trajectory_is_continuous_and_arrives(model, name: str) -> None:
    """Read between its nodes (linear acceleration), the trajectory meets every next node and
    the goal within 1 um and 1 mm/s (the executor's feed-forward differentiates the sampled
    positions twice: a jump of a few um was a spike of ~700 command units): its event times
    are solved again on the output grid."""
    problem = PROBLEMS[name]
    traj = plan_problem(problem, PlanOptions.fast(), model).trajectory
    p, v, _ = traj.at_time(traj.t_s[1:] - 1e-12)
    assert np.abs(p - traj.position_m[1:]).max() < 1e-6
    assert np.abs(v - traj.velocity_m_s[1:]).max() < 1e-3
    np.testing.assert_allclose(p[-1], problem.goal_m, atol=1e-6)
    np.testing.assert_allclose(v[-1], problem.goal_velocity_m_s, atol=1e-3)


def test_without_the_option_the_transcription_plans(model) -> None:
    report = plan_problem(PROBLEMS["short_x"], PlanOptions.fast(switching=False), model).report
    assert report.switching is None and report.n_intervals == 24


def test_pattern_of_reads_switches_and_a_pulse_too_short_for_the_grid() -> None:
    """Leg 0 switches once in the middle; leg 1 starts short of the limit (a pulse of the
    other sign hides in the first interval); leg 2 wanders around zero without reaching the
    hysteresis level on the other side (no switch)."""
    t = np.linspace(0.0, 0.08, 9)
    level = 2000.0
    commands = np.array([[2000, 2000, 2000, 2000, -2000, -2000, -2000, -2000, -2000],
                         [-800, -2000, -2000, -2000, -2000, 2000, 2000, 2000, 2000],
                         [2000, 2000, 300, -300, 300, 2000, 2000, 2000, 2000]], float).T
    zeros = np.zeros((9, 3))
    traj = Trajectory(t, zeros, zeros, zeros, commands, "test", "test", {}, interpolation="linear")
    read = pattern.pattern_of(traj, level)
    assert read.signs == (1.0, 1.0, 1.0)
    assert read.switches_s[0] == pytest.approx((0.035,))
    assert len(read.switches_s[1]) == 2 and 0.0 < read.switches_s[1][0] < 0.01
    assert read.switches_s[1][1] == pytest.approx(0.045)
    assert read.switches_s[2] == ()


def test_switching_option_is_a_flag() -> None:
    with pytest.raises(InvalidProblemError, match="switching must be true or false"):
        PlanOptions.of(switching="yes")
    assert PlanOptions.from_dict({"switching": False}).transcription.switching is False


def test_planner_threads_get_the_plans_they_would_get_alone(model) -> None:
    """The compiled RK4 step and the model's compiled batches keep their inputs and outputs
    in buffers shared by every planner thread of a process (the service's thread workers):
    each run holds their lock. Plans made by four threads at once equal those made alone."""
    from concurrent.futures import ThreadPoolExecutor

    problems = [PROBLEMS[name] for name in sorted(PROBLEMS)] + [VIA_OVER_TOP]
    options = PlanOptions.fast(refine=True)

    def planned(problem: PlanProblem) -> tuple[float, float]:
        report = plan_problem(problem, options, model).report
        return report.duration_s, report.converged_duration_s

    alone = [planned(problem) for problem in problems]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(planned, problems * 3))
    assert together == alone * 3


CALIBRATED = {"coulomb_Nm": 0.005921589428144334, "motor_gain": 0.8998187387030073}
"""What ``calibrate --device emulated --effects coulomb_Nm=0.006,motor_gain=0.9`` fitted
(issue 28 item 7)."""
CALIBRATED_MOVE = PlanProblem((-3.576e-05, -0.0053223, 0.14476), (0.03, 0.02, 0.14))
"""That issue's move: from where the emulated device homes to its goal."""


@pytest.fixture(scope="module")
def friction_model(model):
    from falcon_plan.model.effects import Effects

    return model.with_effects(Effects(**CALIBRATED))


def test_a_friction_model_plans_by_switching_times_as_exactly_as_without(friction_model) -> None:
    """A corrected model with Coulomb friction: the switching-time plan (steps graded where the
    friction changes sign, :func:`integration.find_reversals`) is within 0.02 % of a separate
    192-interval transcription with the same model, and its command stays within the bound
    between its nodes, as without friction (on the coarse steps alone it was 2.9 % over)."""
    options = PlanOptions.fast()
    result = plan_problem(CALIBRATED_MOVE, options, friction_model)
    report = result.report
    assert report.method == "casadi" and report.switching is not None, report.notes
    assert report.switching["graded_reversals"] >= 3  # the start at rest and two legs reversing
    fine = solve_min_time(friction_model, CALIBRATED_MOVE, options.command_bound(friction_model.params),
                          MinTimeSettings(192))
    assert fine.success
    assert report.duration_s == pytest.approx(fine.duration_s, rel=2e-4)
    assert report.worst_command_ratio < 1.003


def test_reversals_are_where_the_leg_speeds_change_sign(friction_model) -> None:
    """Every graded reversal of the plan lies within a width of a zero of a leg speed read off
    the planned trajectory itself (a separate computation: the trajectory's velocities through
    the kinematic Jacobian, on a 20 us grid)."""
    from falcon_plan.model.kinematics import inverse_jacobian

    bound, solved = _solved(friction_model, CALIBRATED_MOVE)
    assert solved.success and solved.reversals
    t = np.arange(0.0, solved.duration_s, 2e-5)
    p, v, _ = plan_problem(CALIBRATED_MOVE, PlanOptions.fast(), friction_model).trajectory.at_time(t)
    w = np.linalg.solve(inverse_jacobian(p, friction_model.params), v[:, :, None])[:, :, 0]
    zeros = [t[k] for leg in range(3) for k in np.nonzero(w[:-1, leg] * w[1:, leg] < 0.0)[0]]
    phases = solved.pattern.phases(solved.duration_s)
    inner = [r for r in solved.reversals if 1e-9 < r.at < 1.0 - 1e-9]  # not the ends at rest
    assert len(inner) == len(zeros) >= 2
    for rev in inner:
        start = phases.bounds[rev.phase] + (pattern.SWITCH_RAMP_S if rev.phase and phases.ramp[rev.phase - 1] else 0)
        span = phases.bounds[rev.phase + 1] - start
        assert min(abs(start + rev.at * span - z) for z in zeros) < max(rev.width * span, 4e-5)


def test_a_transcription_over_its_bound_by_a_hair_is_repaired_not_replaced(friction_model) -> None:
    """Without the switching-time solve, the transcription's friction model plan exceeds its
    bound between the constraint points at N = 24 and 48 (1.2 %, 1.1 %): it is re-solved with
    the bound tightened by the overshoot, not replaced by the ruckig fallback (1.8x longer)."""
    report = plan_problem(CALIBRATED_MOVE, PlanOptions.fast(switching=False), friction_model).report
    assert report.method == "casadi", report.fallback_reason
    assert any("tightened" in note for note in report.notes)
    assert report.worst_command_ratio <= 1.0 + PlanOptions().checks.command_tolerance


CALIBRATED_PAYLOAD = {"coulomb_Nm": 0.007914, "payload_kg": 0.04002}
"""What ``calibrate --device emulated --effects coulomb_Nm=0.008,payload_kg=0.04`` fitted
(issue 23 item 2: its model fell back to ruckig, 174.7 ms where 108.5 ms were planned)."""


def test_a_calibrated_coulomb_and_payload_model_plans_by_switching_times(model) -> None:
    """The corrected model ``calibrate`` writes for a device with hidden Coulomb friction and a
    payload plans by switching times, not by the ruckig fallback: within 0.05 % of a separate
    192-interval transcription with the same model, its command within the bound on the dense
    re-check; under the device's limit too, and faster there (the limit rises in motion)."""
    from falcon_plan.model.effects import Effects

    corrected = model.with_effects(Effects(**CALIBRATED_PAYLOAD))
    reports = {}
    for limit in ("constant", "device"):
        options = PlanOptions.fast(limit=limit)
        report = reports[limit] = plan_problem(CALIBRATED_MOVE, options, corrected).report
        assert report.method == "casadi" and report.switching is not None, (report.fallback_reason, report.notes)
        assert report.switching["graded_reversals"] >= 1
        assert report.worst_command_ratio <= 1.0 + options.checks.command_tolerance
    fine = solve_min_time(corrected, CALIBRATED_MOVE, PlanOptions.fast().command_bound(corrected.params),
                          MinTimeSettings(192))
    assert fine.success
    assert reports["constant"].duration_s == pytest.approx(fine.duration_s, rel=5e-4)
    assert reports["device"].duration_s < reports["constant"].duration_s


def test_a_collapsed_pulse_is_removed_and_a_missed_one_added() -> None:
    """The follow-ups of a failed attempt: a first switch at the start flips the leg's sign, a
    last one at the end goes, two that met go; a pulse goes where the check failed, its
    switches first in line for the minimisation over surplus times."""
    gone = pattern.COLLAPSE_S / 2
    given = pattern.CommandPattern((1.0, -1.0, 1.0), ((gone, 0.02), (0.03, 0.03 + gone, 0.05), (0.01, 0.1 - gone)))
    reduced = pattern.without_collapsed(given, 0.1)
    assert reduced == pattern.CommandPattern((-1.0, -1.0, 1.0), ((0.02,), (0.05,), (0.01,)))
    assert pattern.without_collapsed(reduced, 0.1) is None
    failed = shooting.SwitchingResult(False, "not optimal", reduced, 0.1, 1, 1, 2, 0.0, hurting=(2, 0.04, 0.046))
    pulsed = shooting.with_pulse(failed)
    assert pulsed.switches_s[:2] == reduced.switches_s[:2] and pulsed.signs == reduced.signs
    first, second = pulsed.switches_s[2][1:]
    assert 0.04 < first < second < 0.046 and second - first >= 2 * pattern.COLLAPSE_S - 1e-12
    assert [pulsed.times_s[k] for k in pulsed.pulse] == [first, second]
    at_start = shooting.with_pulse(failed.__class__(**{**failed.__dict__, "hurting": (0, 0.0, 0.002)}))
    assert at_start.signs[0] == -reduced.signs[0] and at_start.switches_s[0][0] < 0.002


def test_execute_with_a_calibrated_friction_model_plans_it_and_logs_no_warning(model, tmp_path, capsys) -> None:
    """Issue 28 item 7 end to end: ``execute`` on the emulated device with the corrected model
    ``calibrate`` writes (Coulomb friction and a motor gain) plans by the optimiser, not the
    ruckig fallback, and prints no logging line among its own."""
    from falcon_plan.cli import main
    from falcon_plan.model.effects import Effects
    from falcon_plan.model.modelfile import save_model

    path = save_model(tmp_path / "model.json", model.with_effects(Effects(**CALIBRATED)))
    code = main(["execute", "--device", "emulated", "--effects", "coulomb_Nm=0.006,motor_gain=0.9",
                 "--model", str(path), "--to", "0.03,0.02,0.14"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "plan: casadi" in out.out and "fallback" not in out.out
    assert "WARNING" not in out.err and "WARNING" not in out.out


def test_a_step_loaded_by_its_recipe_is_the_step_built_afresh(model, monkeypatch) -> None:
    """A process loads the compiled switching-time step by the recipe a build recorded (no
    symbolics): its step, adjoint and command give what a step built afresh gives,
    at a moving state under the device's limit."""
    from falcon_plan.model.saturation import SaturationModel

    saturation = SaturationModel.of(model.params)
    built_first = integration._Stepper(model, "device", saturation)      # records the recipe if new
    recipe = integration._recipe_file(model, "device", saturation)
    if built_first.step.compiled:
        assert integration.recorded_recipe(recipe, 2) is not None
    loaded = integration._Stepper(model, "device", saturation)
    monkeypatch.setattr(integration, "recorded_recipe", lambda recipe, libraries: None)
    fresh = integration._Stepper(model, "device", saturation)
    values = [np.array([0.01, -0.005, 0.13, 0.2, -0.1, 0.05]), np.array([1.0, -1.0, 0.5]),
              np.array([-1.0, 1.0, 1.0]), np.array([2e-3]), model.effects.smooth_vector(), np.array([150.0]),
              np.array([3.0, -2.0, 1.0]), np.arange(1.0, 7.0)]
    for name in ("step", "adjoint", "command"):
        outputs = []
        for stepper in (loaded, fresh):
            fn = getattr(stepper, name)
            for buf, value in zip(fn.inputs, values if name != "command" else [values[0], values[1], values[4], values[5]]):
                buf[:] = np.asarray(value, dtype=float).reshape(buf.shape)
            fn()
            outputs.append([out.copy() for out in fn.outputs])
        for a, b in zip(*outputs):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12, err_msg=name)


@pytest.mark.parametrize("rule", ["constant", "device"])
def test_a_run_in_compiled_chunks_equals_one_step_a_call(model, rule: str) -> None:
    """The compiled runs of 16 and 4 steps a call (:data:`integration.RUN_CHUNKS`) give the
    states one call a step gives, step for step: 16 + 16 + 4 + 3 steps of different lengths,
    signs ramping within some, the commands offset by ``deltas`` (the optimality check's
    finite differences) and not."""
    from falcon_plan.model.saturation import SaturationModel

    stepper = integration._Stepper(model, rule, SaturationModel.of(model.params))
    assert stepper.runners or not stepper.step.compiled   # compiled: the runs are too (FALCON_PLAN_NO_COMPILE: not)
    rng = np.random.default_rng(3)
    n = 39
    hs = rng.uniform(5e-4, 4e-3, n)
    s0s = np.sign(rng.uniform(-1, 1, (n, 3)))
    s1s = np.where(rng.uniform(size=(n, 3)) < 0.2, -s0s, s0s)
    deltas = rng.uniform(-50, 50, (n, 3))
    x0 = np.array([0.005, -0.01, 0.125, 0.05, 0.1, -0.02])
    level = 2300.0 if rule == "constant" else 150.0
    for offsets in (None, deltas):
        chunked = stepper.run(x0, model.effect_vector, level, hs, s0s, s1s, offsets)
        runners, stepper.runners = stepper.runners, {}
        try:
            single = stepper.run(x0, model.effect_vector, level, hs, s0s, s1s, offsets)
        finally:
            stepper.runners = runners
        assert np.all(np.isfinite(single)) and np.abs(single[-1, :3] - x0[:3]).max() > 1e-4   # it moved
        np.testing.assert_allclose(chunked, single, rtol=1e-12, atol=1e-14)
