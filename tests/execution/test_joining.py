"""Joining trajectories (the approach move before a plan, holds between verification moves):
each piece keeps its motion, checked against the pieces themselves."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.approach import JOIN_RAMP_S, concatenate
from falcon_plan.errors import InvalidProblemError
from falcon_plan.planning.api import plan
from falcon_plan.planning.problem import PlanOptions
from falcon_plan.planning.quintic import quintic_trajectory
from falcon_plan.trajectory import Trajectory

A_M, B_M = np.array([0.0, 0.0, 0.12]), np.array([0.02, 0.01, 0.13])


def _hold(at_m: np.ndarray, name: str) -> Trajectory:
    rest = np.zeros((2, 3))
    return Trajectory(np.array([0.0, 0.5]), np.vstack([at_m, at_m]), rest, rest, rest, name, "hold")


def _same_motion(joined: Trajectory, piece: Trajectory, offset_s: float) -> None:
    """Position within 10 nm and velocity within 10 um/s of ``piece`` (shifted by ``offset_s``
    [s] in ``joined``); the acceleration differs only inside the ramps."""
    t = np.linspace(piece.t_s[0], piece.t_s[-1], 2001)[1:-1]
    (p, v, _), (p0, v0, _) = joined.at_time(t + offset_s), piece.at_time(t)
    np.testing.assert_allclose(p, p0, atol=1e-8)
    np.testing.assert_allclose(v, v0, atol=1e-5)


def test_a_plan_then_a_hold_keeps_the_plan_exactly(model) -> None:
    """A minimum-time plan still brakes at full command when it arrives: the joined
    trajectory keeps its linear acceleration to the end and only then ramps to the hold."""
    move = plan(A_M, B_M, PlanOptions.fast(), model).trajectory
    assert move.interpolation == "linear" and np.abs(move.acceleration_m_s2[-1]).max() > 1.0
    joined = concatenate(move, _hold(B_M, move.params_name))
    assert joined.interpolation == "linear"
    _same_motion(joined, move, 0.0)
    p, v, a = joined.at_time(np.array([move.duration_s + JOIN_RAMP_S, move.duration_s + 0.3]))
    np.testing.assert_allclose(p, [B_M, B_M], atol=1e-8)
    np.testing.assert_allclose(v, 0.0, atol=1e-3)
    np.testing.assert_allclose(a[1], 0.0)


def test_an_approach_with_constant_acceleration_before_a_linear_plan(model) -> None:
    """The quintic approach (piecewise-constant acceleration between its 1 kHz samples) before
    a plan (linear): the approach is read as linear with short ramps, the plan unchanged."""
    approach = quintic_trajectory(B_M + np.array([0.0, 0.0, -0.01]), A_M, model, rate_hz=1000.0)
    move = plan(A_M, B_M, PlanOptions.fast(), model).trajectory
    joined = concatenate(approach, move)
    assert joined.interpolation == "linear"
    _same_motion(joined, approach, 0.0)
    _same_motion(joined, move, approach.duration_s + JOIN_RAMP_S)


def test_joining_needs_rest_at_one_point(model) -> None:
    move = plan(A_M, B_M, PlanOptions.fast(), model).trajectory
    with pytest.raises(InvalidProblemError, match="join only at rest"):
        concatenate(move, _hold(A_M, move.params_name))
