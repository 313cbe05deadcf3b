"""Trajectory sampling computes commands from a model (never interpolates them), and a
zero-length move gets an answer of its own."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from falcon_plan.errors import InvalidParameterError, InvalidProblemError
from falcon_plan.model.effects import Effects
from falcon_plan.planning.api import plan
from falcon_plan.planning.problem import PlanOptions
from falcon_plan.trajectory import Trajectory


@pytest.fixture(scope="module", params=["linear", "constant"])
def trajectory(request, model) -> Trajectory:
    return plan((0.0, 0.0, 0.12), (0.03, 0.02, 0.14), PlanOptions.fast(profile=request.param), model).trajectory


def test_sample_without_a_model_refuses(trajectory) -> None:
    with pytest.raises(InvalidProblemError, match="needs the model"):
        trajectory.sample(800.0)


def test_sampled_commands_are_the_models_inverse_dynamics(model, trajectory) -> None:
    samples = trajectory.sample(800.0, model)
    np.testing.assert_allclose(np.diff(samples.t_s)[:-1], 1 / 800.0, rtol=1e-9)
    p, v, a = trajectory.at_time(samples.t_s)
    np.testing.assert_allclose(samples.position_m, p, atol=1e-12)
    np.testing.assert_allclose(samples.commands, model.inverse_dynamics(p, v, a), atol=1e-6)
    # what interpolating the node commands would have given instead (the old behaviour): far
    # off across the acceleration steps of a constant profile (the linear one is continuous)
    if trajectory.interpolation == "constant":
        assert np.abs(trajectory.commands_at(samples.t_s) - samples.commands).max() > 1000.0
    # a payload is part of the model: its commands differ
    heavy = model.with_effects(Effects(payload_kg=0.1))
    assert np.abs(trajectory.sample(800.0, heavy).commands - samples.commands).max() > 50.0


def test_json_round_trip_keeps_the_interpolation(trajectory) -> None:
    again = Trajectory.from_json(trajectory.to_json())
    assert again.interpolation == trajectory.interpolation
    t = np.linspace(0.0, trajectory.duration_s, 101)
    np.testing.assert_allclose(again.at_time(t)[0], trajectory.at_time(t)[0], atol=1e-15)


def test_zero_length_move_is_refused_with_its_own_message(model) -> None:
    with pytest.raises(InvalidProblemError, match="zero_length_move"):
        plan((0.0, 0.0, 0.12), (0.0, 0.0, 0.12), PlanOptions(), model)
    with pytest.raises(InvalidProblemError, match="zero_length_move"):
        plan((0.0, 0.0, 0.12), (0.0, 0.0, 0.12 + 1e-7), PlanOptions.fast(), model)
    # a short but real move plans (and a loop back to the start while moving is not zero-length)
    short = plan((0.0, 0.0, 0.12), (0.0, 0.0, 0.1201), PlanOptions.fast(), model).report
    assert short.status == "optimal" and short.duration_s > 0.002


@pytest.mark.slow
def test_zero_length_move_on_the_command_line_is_one_line() -> None:
    run = subprocess.run([sys.executable, "-m", "falcon_plan.cli", "plan", "--from", "0,0,0.12", "--to",
                          "0,0,0.12", "--fast"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2
    # on a loaded machine the CLI may first report the planner's warm-up (progress lines,
    # "falcon-plan: ..."); the error itself is one line
    lines = [line for line in run.stderr.strip().splitlines() if not line.startswith("falcon-plan: ")]
    assert len(lines) == 1 and "zero_length_move" in lines[0] and "toppra" not in run.stderr
    assert "optimal" not in run.stdout


@pytest.mark.slow
def test_cli_plans_with_the_device_limit() -> None:
    run = subprocess.run([sys.executable, "-m", "falcon_plan.cli", "plan", "--from", "0,0,0.12", "--to",
                          "0.03,0.02,0.14", "--limit", "device", "--fast", "--json"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    report = json.loads(run.stdout)
    assert report["status"] == "optimal" and report["command_bound"].startswith("device limit 2500..4096")
    assert report["options"]["limits"] == {"tc_max": 2500.0, "limit": "device", "feedback_reserve": 150.0}


def test_node_gaps_follow_the_interpolation(model, trajectory) -> None:
    """A plan's nodes agree with its own interpolation (to ~0.2 um); one node moved by 1 mm does
    not, and is refused as a jump: :func:`node_gaps` is measured against ``Trajectory.at_time``
    (an independent evaluation of the same motion)."""
    from falcon_plan.planning.verify import NODE_POSITION_TOLERANCE_M, node_gaps, require_executable

    dp, dv = node_gaps(trajectory)
    assert dp.max() < 1e-6 and dv.max() < 1e-4   # 0.15 um: the plan's RK4 nodes against its interpolation
    assert require_executable(model, trajectory) is None
    # the left limit of at_time at each next node: where the motion from the node before lands
    t = trajectory.t_s
    p, v, _ = trajectory.at_time(t[1:] - 1e-12)
    np.testing.assert_allclose(np.linalg.norm(p - trajectory.position_m[1:], axis=1), dp, atol=1e-9)
    moved = trajectory.position_m.copy()
    moved[len(t) // 2, 2] += 1e-3
    bumped = Trajectory(t, moved, trajectory.velocity_m_s, trajectory.acceleration_m_s2, trajectory.commands,
                        interpolation=trajectory.interpolation)
    gaps = node_gaps(bumped)[0]
    assert gaps[len(t) // 2 - 1] == pytest.approx(1e-3, rel=1e-3) and gaps.max() > NODE_POSITION_TOLERANCE_M
    with pytest.raises(InvalidParameterError, match="jumps at t = "):
        require_executable(model, bumped, "the bumped plan")


def test_a_faster_copy_of_a_plan_needs_more_than_the_device_has(model, trajectory) -> None:
    """Time-scaled by 1/k (velocities times k, accelerations times k^2: its nodes stay
    consistent) a minimum-time plan needs about k^2 times the inertial command: refused, with the
    peak the model's inverse dynamics gives at the dense points."""
    from falcon_plan.planning.verify import require_executable

    k = 2.0
    fast = Trajectory(trajectory.t_s / k, trajectory.position_m, k * trajectory.velocity_m_s,
                      k * k * trajectory.acceleration_m_s2, trajectory.commands, interpolation=trajectory.interpolation)
    t = np.linspace(0.0, fast.duration_s, 4001)
    peak = np.abs(model.inverse_dynamics(*fast.at_time(t))).max()
    assert peak > 4096 * 1.5
    with pytest.raises(InvalidParameterError, match="more than the device can give") as info:
        require_executable(model, fast, "the fast copy")
    needed = float(str(info.value).split("|Tc| = ")[1].split()[0])
    assert needed == pytest.approx(peak, rel=0.02)
