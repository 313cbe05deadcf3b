"""The device's speed-dependent command limit in the planner, the feedback reserve, and plans
the simulated device really follows.

The saturation rule has one definition (falcon_plan.model.saturation) that the plant and the
planner share; the checks here recompute the limit independently (numpy kinematics, the
paper's numbers written out) and measure what the plant really did: a plant that records the
command it was asked for and the command that reached its motors."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.execution.executor import Executor
from falcon_plan.falconlog import read_log
from falcon_plan.model.kinematics import jacobian
from falcon_plan.model.saturation import speed_limit
from falcon_plan.planning import shooting
from falcon_plan.planning.api import plan, plan_problem
from falcon_plan.planning.min_time import solve_min_time
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.transcription import MinTimeSettings, payload_model
from falcon_plan.planning.verify import log_limit_ratio
from falcon_plan.sim.equations import PlantLayout, plant_functions
from falcon_plan.sim.plant import SimPlant

PROBLEMS_DIR = Path(__file__).resolve().parents[2] / "problems"
START, GOAL = (0.0, 0.0, 0.12), (0.03, 0.02, 0.14)
PREROLL_S = 0.5


class RecordingPlant(SimPlant):
    """SimPlant that keeps, per period, the command acting (before saturation) and the one
    that drove the motors (after it)."""

    def step(self, commands):  # noqa: ANN001, ANN201 - same signature as SimPlant.step
        counts = super().step(commands)
        self.record.append((self.acting_commands, self.motor_commands))
        return counts


def _execute(model, traj, problem: PlanProblem, tmp_path: Path):
    """Run ``traj`` with the executor on a simulated device with the saturation rule; returns
    (report, log, recorded (acting, motor) commands (K, 2, 3))."""
    plant = RecordingPlant(model, rate_hz=800.0)
    plant.reset(np.asarray(problem.start_m))
    plant.record = []
    log_path = tmp_path / "run.csv"
    with SimDevice(plant) as device:
        device.home()
        report = Executor(device, model, log_path=log_path, preroll_s=PREROLL_S).run(traj)
    return report, read_log(log_path), np.array(plant.record)


def test_the_plant_and_the_planner_share_one_saturation_rule(model) -> None:
    # the paper's numbers written out: 2500 at rest, 4096 from 2 rad/s, smoothstep between
    assert speed_limit(0.0, 2500, 4096) == 2500
    assert speed_limit(-2.5, 2500, 4096) == 4096
    assert speed_limit(1.0, 2500, 4096) == pytest.approx(2500 + 1596 * 0.5)
    # the plant's compiled motor command is that rule, at the motor speed of its state
    fns = plant_functions(PlantLayout(model.params, model.limits, False, 1))
    rng = np.random.default_rng(3)
    p = np.array(START)
    pp = np.array([1 / 800, 2500, 4096, 2.0, 1.0, 1.0, 0.0, -1.0, 2.0, 50.0, 1.0, 0.0, 0.0, 0.0])  # no external force
    for _ in range(20):
        v = rng.normal(scale=0.1, size=3)
        tc = rng.uniform(-4096, 4096, size=3)
        x = np.concatenate([p, v])
        w = jacobian(p, model.params) @ v
        expected = np.clip(tc, -speed_limit(w, 2500, 4096), speed_limit(w, 2500, 4096))
        got = np.asarray(fns.motor_command(x, tc, model.effect_vector, pp)).ravel()
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("n", [1, 150])
def test_leg_motion_is_the_kinematic_jacobian_and_its_rate(model, n: int) -> None:
    """The planner's compiled leg motion (chunks of 64 points, a single point too) against
    numpy kinematics: w = J(p) v, and dw/dt as the central difference of J(p) v along the
    motion (p + v t + a t^2 / 2, v + a t)."""
    from falcon_plan.planning.bound import leg_motion

    rng = np.random.default_rng(7)
    p = np.column_stack([rng.uniform(-0.03, 0.03, n), rng.uniform(-0.03, 0.03, n), rng.uniform(0.11, 0.15, n)])
    v, a = rng.normal(0.0, 0.3, (n, 3)), rng.normal(0.0, 20.0, (n, 3))
    w, rate = leg_motion(model, p, v, a)

    def speeds(t: float) -> np.ndarray:
        return np.einsum("nij,nj->ni", jacobian(p + v * t + 0.5 * a * t * t, model.params), v + a * t)

    dt = 1e-6
    np.testing.assert_allclose(w, speeds(0.0), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(rate, (speeds(dt) - speeds(-dt)) / (2 * dt), rtol=1e-5, atol=1e-4)


@pytest.fixture(scope="module")
def device_plan(model):
    return plan(START, GOAL, PlanOptions.of(limit="device", crosscheck=False), model)


def test_device_limit_plan_respects_the_limit_between_the_nodes(model, device_plan) -> None:
    """|Tc| against L(w) recomputed independently (numpy Jacobian, the rule's numbers) at 20
    points per interval: within the limit minus the reserve (1 % tolerance, as the planner's
    dense re-check), and it uses more than the static 2500 (else why bother)."""
    traj, report = device_plan.trajectory, device_plan.report
    assert report.status == "optimal", report.summary()
    t = np.concatenate([np.linspace(a, b, 20, endpoint=False) for a, b in zip(traj.t_s[:-1], traj.t_s[1:])])
    p, v, a = traj.at_time(t)
    tc = np.abs(model.inverse_dynamics(p, v, a))
    w = np.einsum("nij,nj->ni", jacobian(p, model.params), v)
    limit = speed_limit(w, 2500.0, 4096.0)
    assert np.max(tc / limit) <= 1.0
    assert np.max(tc / (limit - PlanOptions().limits.feedback_reserve)) <= 1.01
    assert tc.max() > 3500


def test_output_nodes_follow_the_limits_curvature(model, device_plan, monkeypatch) -> None:
    """The device-limit plan's output splits a solve step only as finely as the limit's
    curvature needs (sampling.output_splits): fewer nodes than every such step split at
    DEVICE_OUTPUT_STEP_S (tolerance 0 gives that), the same duration (both land on the goal
    from the same solve) and the limit still held between the nodes (the dense re-check).
    Where a split was coarser than that cap, the curvature bound it was chosen by holds."""
    from falcon_plan.planning import sampling
    from falcon_plan.planning.bound import leg_motion, sampled_speed

    monkeypatch.setattr(sampling, "DEVICE_CURVATURE_TOLERANCE", 0.0)
    finest = plan(START, GOAL, PlanOptions.of(limit="device", crosscheck=False), model)
    traj, report = device_plan.trajectory, device_plan.report
    assert len(traj.t_s) < 0.8 * len(finest.trajectory.t_s)
    assert report.duration_s == pytest.approx(finest.report.duration_s, rel=1e-5)
    assert report.worst_command_ratio <= 1.0 + PlanOptions().checks.command_tolerance
    # the rule itself, on the plan's own nodes taken as steps
    monkeypatch.undo()
    saturation = PlanOptions.of(limit="device").command_bound(model.params).saturation
    states = np.hstack([traj.position_m, traj.velocity_m_s])
    h = np.diff(traj.t_s)
    splits = sampling.output_splits(model, saturation, states, traj.acceleration_m_s2, h)
    cap = np.ceil(h / sampling.DEVICE_OUTPUT_STEP_S)
    assert np.all(splits >= 1) and np.all(splits <= cap)
    w, rate = leg_motion(model, traj.position_m, traj.velocity_m_s, traj.acceleration_m_s2)
    limit = saturation.limit(sampled_speed(w, rate))
    band = (limit > saturation.static + 1e-6) & (limit < saturation.full - 1e-6)
    assert np.all(splits[~np.any(band[:-1] | band[1:], axis=1)] == 1)
    curvature = 6.0 * (saturation.full - saturation.static) / saturation.release_speed_rad_s ** 2 * \
        np.maximum(np.where(band, rate ** 2, 0.0)[:-1], np.where(band, rate ** 2, 0.0)[1:]).max(axis=1)
    coarser = splits < cap
    assert np.all(curvature[coarser] * (h[coarser] / splits[coarser]) ** 2 / 8.0
                  <= sampling.DEVICE_CURVATURE_TOLERANCE * (1 + 1e-9))


def test_device_limit_is_faster_than_the_constant_2500(model, device_plan) -> None:
    constant = plan(START, GOAL, PlanOptions.fast(), model).report.duration_s
    assert device_plan.report.duration_s < 0.9 * constant


def test_device_limit_plan_tracked_from_rest(model, device_plan, tmp_path) -> None:
    """The executor runs the device-limit plan from rest on the plant with its saturation
    rule: tracking within 0.3 mm RMS, and no command was ever clipped by the device."""
    report, _, record = _execute(model, device_plan.trajectory, PlanProblem(START, GOAL), tmp_path)
    assert report.status == "completed", report.reason
    assert report.tracking.norm_rms_mm <= 0.3, report.summary()
    acting, motor = record[:, 0], record[:, 1]
    np.testing.assert_array_equal(acting, motor)          # the saturation never cut in
    assert np.abs(acting).max() > 3500


def test_constant_4096_plan_is_not_trackable_from_rest(model, tmp_path) -> None:
    """The contrast the device limit exists for: the same move planned to a constant 4096 asks
    more than the device gives at low speed; cut there (by the controller's clamp at the
    device's limit, or by the device), it tracks far worse."""
    traj = plan(START, GOAL, PlanOptions.fast(tc_max=4096, feedback_reserve=0), model).trajectory
    p, v, a = traj.at_time(traj.t_s)
    w = np.einsum("nij,nj->ni", jacobian(p, model.params), v)
    assert np.max(np.abs(model.inverse_dynamics(p, v, a)) / speed_limit(w, 2500.0, 4096.0)) > 1.05
    report, _, record = _execute(model, traj, PlanProblem(START, GOAL), tmp_path)
    assert report.tracking.norm_rms_mm > 1.0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["across_diagonal", "edge_lower_front", "payload_50g", "short_y_up", "tc_sweep_1500"])
def test_executed_command_within_the_device_limit_on_benchmark_problems(model, name, tmp_path) -> None:
    """Benchmark problems (rest to rest) planned with the default options (constant tc_max minus
    the default reserve) and with the device limit, executed: the executed peak command stays
    within the device's limit (log_limit_ratio), and the plant confirms it never clipped."""
    spec = json.loads((PROBLEMS_DIR / f"{name}.json").read_text())
    problem = PlanProblem(spec["start_m"], spec["goal_m"], payload_kg=spec.get("payload_kg", 0.0))
    loaded = payload_model(model, problem)
    for options in (PlanOptions.fast(tc_max=spec["tc_max"]), PlanOptions.fast(limit="device")):
        traj = plan_problem(problem, options, model).trajectory
        report, log, record = _execute(loaded, traj, problem, tmp_path)
        assert report.status == "completed", report.reason
        assert log_limit_ratio(loaded, traj, log, PREROLL_S) <= 1.0
        np.testing.assert_array_equal(record[:, 0], record[:, 1])


def test_plan_report_gives_the_executed_peak_command(model) -> None:
    report = plan(START, (0.02, 0.01, 0.13), PlanOptions.of(crosscheck=False, refine=False), model).report
    assert report.plant is not None and report.plant["ran"]
    assert report.plant["max_command"] > 2000
    peak, ratio = report.plant["max_command"], report.plant["max_command_over_limit"]
    assert peak / 4096 <= ratio <= peak / 2500            # 2500 <= L(w) <= 4096
    assert "executed peak" in report.summary()


def test_feedback_reserve_and_limit_options_are_validated() -> None:
    from falcon_plan.errors import InvalidProblemError

    with pytest.raises(InvalidProblemError, match="limit must be one of"):
        PlanOptions.of(limit="soft")
    with pytest.raises(InvalidProblemError, match="feedback_reserve"):
        PlanOptions.of(feedback_reserve=-1)
    with pytest.raises(InvalidProblemError, match="smaller than tc_max"):
        PlanOptions.of(tc_max=100, feedback_reserve=150)
    assert PlanOptions.from_dict(PlanOptions.of(limit="device").to_dict()).limits.limit == "device"


SWITCHING_CASES = {
    "start_to_goal": PlanProblem(START, GOAL),
    "short_y_up": None,              # benchmark problems, read below
    "via_over_top": None,
    "via_depth": None,               # a pulse added where the check failed (issue 23 items 1, 3)
    "moving_start_reverse": None,    # a guessed start pulse collapses, a missed one is added
    "via_two_points": None,          # the coarse solve needs more than the screening's iterations
    "short_z": None,                 # two legs' pulses read off dips of the coarse command
}


def _case(name: str) -> PlanProblem:
    if SWITCHING_CASES[name] is not None:
        return SWITCHING_CASES[name]
    spec = json.loads((PROBLEMS_DIR / f"{name}.json").read_text())
    return PlanProblem(**{k: spec[k] for k in ("start_m", "goal_m", "start_velocity_m_s", "goal_velocity_m_s",
                                                 "via_m", "payload_kg") if k in spec})


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n == "via_two_points" else n
                                  for n in sorted(SWITCHING_CASES)])
def test_device_limit_plans_ride_the_limit_by_switching_times(model, name) -> None:
    """Under the device's limit the commands ride L(w_s) - reserve on every arc (the limit
    rises with the leg speed): the switching-time plan (with via points too, and from a moving
    start that must turn) is within 0.05 % of a separate 192-interval transcription of the same
    problem (0.1 % with two via points, where that solve's own error is larger: the plan is
    0.07 % shorter than it), passes Pontryagin's check,
    and its command at the nodes is the limit itself (recomputed by the bound's own numpy
    evaluation, not the expression the plan integrated)."""
    problem = _case(name)
    options = PlanOptions.fast(limit="device", time_budget_s=120.0)   # what it finds, not how fast: a loaded machine must not cut it short
    result = plan_problem(problem, options, model)
    report = result.report
    assert report.method == "casadi" and report.switching is not None, report.notes
    bound = options.command_bound(model.params)
    fine = solve_min_time(model, problem, bound, MinTimeSettings(192))
    assert fine.success
    assert abs(report.duration_s - fine.duration_s) / fine.duration_s < (1e-3 if name == "via_two_points" else 5e-4)
    assert report.switching["worst_help"] >= -shooting.CHECK_TOLERANCE
    traj = result.trajectory
    loaded = payload_model(model, problem)
    ratio = np.abs(traj.commands) / bound.allowed(loaded, traj.position_m, traj.velocity_m_s, traj.acceleration_m_s2)
    on_arcs = np.median(ratio, axis=0)
    np.testing.assert_allclose(on_arcs, 1.0, atol=2e-3)
    assert report.worst_command_ratio <= 1.0 + options.checks.command_tolerance


def test_a_coarse_solve_stopped_early_still_gives_the_pattern(model, monkeypatch) -> None:
    """A coarse solve stopped before it converged (its iteration limit here; on a loaded
    machine its wall-time limit does the same): the pattern is read off its last iterate all
    the same, and the switching-time plan (checked by Pontryagin's principle and the dense
    re-check) is the one a converged coarse solve gives (same duration within 1e-5), not the
    transcription's nor the ruckig fallback."""
    from falcon_plan.planning import min_time

    problem = _case("start_to_goal")
    options = PlanOptions.fast(limit="device")
    converged = plan_problem(problem, options, model).report
    monkeypatch.setattr(min_time, "IGNORED_MAX_ITER", 12)
    stopped = plan_problem(problem, options, model).report
    assert stopped.solver_status == "Maximum_Iterations_Exceeded" and not stopped.solver_success
    assert stopped.method == "casadi" and stopped.switching is not None, stopped.notes
    assert stopped.duration_s == pytest.approx(converged.duration_s, rel=1e-5)
