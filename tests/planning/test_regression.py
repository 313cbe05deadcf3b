"""PLANNING-NOTES' regression case, 3-axis double integrator, rest to rest, displacement
(0.03, 0.02, 0.04) m, |v| <= 0.5 m/s, |a| <= 10 m/s^2 per axis: exactly 0.1300 s (the 4 cm
axis: 50 ms accelerating, 30 ms cruising, 50 ms braking), 0.1500 s with |jerk| <= 500 m/s^3.
Reproduced by toppra, ruckig and the planner's own transcription machinery."""
from __future__ import annotations

import numpy as np
import pytest
import ruckig
import toppra
import toppra.algorithm as algo
import toppra.constraint as constraint

from falcon_plan.planning.transcription import MinTimeSettings, NodeMotion, box_constraints, solve_transcription
from falcon_plan.planning.problem import PlanProblem

START = np.array([0.0, 0.0, 0.1])
MOVE = np.array([0.03, 0.02, 0.04])
VMAX, AMAX = 0.5, 10.0


def test_toppra_straight_line() -> None:
    path = toppra.SplineInterpolator([0.0, 1.0], np.vstack([START, START + MOVE]), bc_type="natural")
    cons = [constraint.JointVelocityConstraint(np.tile([-VMAX, VMAX], (3, 1))),
            constraint.JointAccelerationConstraint(np.tile([-AMAX, AMAX], (3, 1)))]
    instance = algo.TOPPRA(cons, path, gridpoints=np.linspace(0, 1, 401), solver_wrapper="seidel",
                           parametrizer="ParametrizeConstAccel")
    assert instance.compute_trajectory().duration == pytest.approx(0.13, abs=2e-4)


@pytest.mark.parametrize("jerk, expected", [(None, 0.13), (500.0, 0.15)])
def test_ruckig(jerk: float | None, expected: float) -> None:
    inp = ruckig.InputParameter(3)
    inp.current_position, inp.target_position = list(START), list(START + MOVE)
    inp.max_velocity, inp.max_acceleration = [VMAX] * 3, [AMAX] * 3
    if jerk is not None:
        inp.max_jerk = [jerk] * 3
    traj = ruckig.Trajectory(3)
    assert ruckig.Ruckig(3).calculate(inp, traj) in (ruckig.Result.Working, ruckig.Result.Finished)
    assert traj.duration == pytest.approx(expected, abs=1e-6)


def test_planner_transcription() -> None:
    # N = 26: h = 5 ms puts the switching times (50 and 80 ms) on nodes, so the
    # piecewise-constant acceleration represents the optimum exactly
    n = 26
    problem = PlanProblem(tuple(START), tuple(START + MOVE))
    t0 = 0.3
    s = np.linspace(0, 1, n + 1)[:, None]
    guess = NodeMotion(t0, START + s * MOVE, np.tile(MOVE / t0, (n + 1, 1)), np.zeros((n, 3)))
    bound = np.array([VMAX] * 3 + [AMAX] * 3)
    result = solve_transcription(box_constraints(), problem, MinTimeSettings(n, hessian="exact", profile="constant"),
                                 row_lower=-bound, row_upper=bound, eff=np.zeros(1), guess=guess)
    assert result.success, result.solver_status
    assert result.duration_s == pytest.approx(0.13, abs=1e-5)
