"""The output of a switching-time plan: its motion at nodes (:func:`sample`) and as a
:class:`~falcon_plan.trajectory.Trajectory` (:func:`trajectory`).

The solve integrated with a few RK4 steps per phase; the output grid is finer
(:data:`OUTPUT_STEP_S`; under the device's limit the solve's steps split where a leg's limit
changes, as finely as the limit's curvature there needs, :func:`output_splits`), and the event times are corrected on it first, so that its last node
lands on the goal.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.saturation import SaturationModel
from falcon_plan.planning.bound import leg_motion, sampled_speed
from falcon_plan.planning.integration import StepPlan
from falcon_plan.planning.pattern import SWITCH_RAMP_S
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.planning.shooting import Shooting, SwitchingResult
from falcon_plan.planning.transcription import NodeMotion, nodes_to_trajectory, payload_model
from falcon_plan.trajectory import Trajectory


OUTPUT_STEP_S = 4e-3
"""Longest interval of the returned trajectory [s] (its acceleration is piecewise linear
between nodes; the command between them leaves the bound by < 0.3 % at this spacing on the
benchmark problems, < 0.1 % at 2 ms, which doubles the nodes and the dense re-check's cost)."""
DEVICE_OUTPUT_STEP_S = 2.5e-4
"""Shortest interval a device-limit plan's output splits a solve step into where a leg's limit
is changing (between its value at rest and the full range) [s]: the command follows L(w_s), a
cubic in the speed, which a linear acceleration between nodes 4 ms apart missed by 11-16 %
(on the dense re-check of the benchmark problems); how finely is :func:`output_splits`'
choice; elsewhere :data:`OUTPUT_STEP_S`."""
DEVICE_CURVATURE_TOLERANCE = 10.0
"""How far [command units] a linear acceleration between a device-limit plan's output nodes may
stray from the limit's curve where it changes, by the curvature bound of :func:`output_splits`
(0.4 % of the static 2500). On the 37 benchmark problems the output had 5053 nodes in all
instead of 8625 with every such step split into :data:`DEVICE_OUTPUT_STEP_S`, and the worst
dense re-check of each plan was the same (up to 1.0087, at command ramps; between such nodes
at most 1.0034); with 20 units it reached 1.0065 there, with 1 ms intervals 1.0100."""


def sample(model: FalconModel, problem: PlanProblem, plan: SwitchingResult,
           step_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The motion of a solved ``plan`` at nodes at most ``step_s`` [s] (default
    :data:`OUTPUT_STEP_S`; under the device's limit the solve's own steps, split where the
    limit changes, see below) apart, with a node at both
    ends of every command ramp: (t (n,), p (n, 3), v (n, 3), a (n, 3)) [s, m, m/s, m/s^2];
    a from the forward dynamics with the command at each node (``model`` with the problem's
    payload added). The last node is the goal state itself (the integration put it within
    the solve's tolerance of it)."""
    model = payload_model(model, problem)
    step_s = OUTPUT_STEP_S if step_s is None else step_s
    phases = plan.pattern.phases(plan.duration_s)
    counts = [max(1, math.ceil((d - (SWITCH_RAMP_S if j and phases.ramp[j - 1] else 0.0)) / step_s))
              for j, d in enumerate(phases.durations)]
    # The solve integrated with a few steps per phase; integrated on this finer grid its
    # events land the motion a few um off the goal, and a trajectory that jumps there would
    # give the executor's finite-difference feed-forward a spike. So the event times are
    # corrected on this grid first.
    z = np.append(plan.pattern.times_s, plan.duration_s)
    if plan.rule.kind == "constant":
        grid = Shooting(model, problem, plan.pattern, plan.rule, counts, plan.reversals)
        t, states, a, steps = _nodes(model, problem, grid, *grid.landed(z, plan.jacobian))
        return t, states[:, :3], states[:, 3:], a
    # Under the device's limit: the solve's own steps (at most DEVICE_STEP_S), and where a
    # leg's limit is between its value at rest and the full range (it changes within a few
    # ms there) split as its curvature needs (output_splits)
    grid = Shooting(model, problem, plan.pattern, plan.rule, list(plan.counts), plan.reversals)
    _, states, a, steps = _nodes(model, problem, grid, z)
    split = output_splits(model, plan.rule.saturation, states, a, steps.h)
    fractions = [np.repeat(steps.share[steps.phase == j] / split[steps.phase == j], split[steps.phase == j])
                 for j in range(plan.pattern.n_phases)]
    grid = Shooting(model, problem, plan.pattern, plan.rule, counts, grid=fractions)
    t, states, a, steps = _nodes(model, problem, grid, *grid.landed(z, plan.jacobian))
    return t, states[:, :3], states[:, 3:], a


def output_splits(model: FalconModel, saturation: SaturationModel, states: np.ndarray, a: np.ndarray,
                  h: np.ndarray) -> np.ndarray:
    """Into how many output intervals each solve step of a device-limit plan is split, (n,):
    one where no leg's limit (``saturation``) is between its value at rest and the full range
    at either end of the step; elsewhere enough that a linear acceleration between the nodes
    follows L(w_s) within :data:`DEVICE_CURVATURE_TOLERANCE` (L's second time derivative is
    at most 6 (full - static) / w_r^2 (dw/dt)^2 there, the smoothstep's, and a straight line
    over an interval d is off a curve by at most its second derivative times d^2 / 8; dw/dt
    taken at the step's ends), at most ``ceil(h / DEVICE_OUTPUT_STEP_S)``. ``states`` (n + 1, 6)
    [m, m/s] and ``a`` (n + 1, 3) [m/s^2] at the ends of the steps of lengths ``h`` (n,) [s]
    of ``model``'s motion."""
    w, rate = leg_motion(model, states[:, :3], states[:, 3:], a)
    limit = saturation.limit(sampled_speed(w, rate))
    band = (limit > saturation.static + 1e-6) & (limit < saturation.full - 1e-6)       # (n + 1, 3)
    per_rate2 = 6.0 * (saturation.full - saturation.static) / saturation.release_speed_rad_s ** 2
    curvature = per_rate2 * np.where(band, rate * rate, 0.0)                             # [units/s^2]
    step_curvature = np.maximum(curvature[:-1], curvature[1:]).max(axis=1)
    longest = np.sqrt(8.0 * DEVICE_CURVATURE_TOLERANCE / np.maximum(step_curvature, 1e-300))
    moving = np.any(band[:-1] | band[1:], axis=1)
    return np.where(moving, np.ceil(h / np.maximum(longest, DEVICE_OUTPUT_STEP_S)), 1).astype(int)


def _nodes(model: FalconModel, problem: PlanProblem, grid: "Shooting", z: np.ndarray,
           states: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, StepPlan]:
    """The nodes of ``grid``'s run of ``z`` (its ``states`` when already run): times (n,)
    [s], states (n, 6) (the via points and the goal set exactly) and accelerations (n, 3)
    [m/s^2] with the command at each node, and the steps."""
    phases, steps = grid.plan(z)
    if states is None:
        states = grid.stepper.run(grid.x0, grid.eff, grid.rule.level, steps.h, steps.u0, steps.u1)
    for e, k in enumerate(phases.via):  # the via points and the goal themselves (within ~1e-10 m)
        if k >= 0:
            states[steps.ends[e], :3] = problem.via_m[k]
    states[-1] = np.concatenate([problem.goal_m, problem.goal_velocity_m_s])
    t = np.concatenate([[0.0], np.cumsum(steps.h)])
    t[-1] = z[-1]
    # the command at each node: its step's start command; the last node, the last step's end
    signs = np.vstack([np.asarray(steps.u0), np.asarray(steps.u1[-1])[None, :]])
    commands = grid.stepper.commands(states, signs, grid.eff, grid.rule.level)
    return t, states, np.asarray(model.forward_dynamics(states[:, :3], states[:, 3:], commands)), steps


def trajectory(model: FalconModel, problem: PlanProblem, plan: SwitchingResult, *,
               meta: dict[str, Any] | None = None, step_s: float | None = None) -> Trajectory:
    """The solved ``plan`` as a :class:`Trajectory` (linear acceleration between the nodes of
    :func:`sample`, at most ``step_s`` [s] apart as there, commands from ``model``'s inverse
    dynamics with the problem's payload), carrying ``meta`` and the switching summary."""
    t, p, v, a = sample(model, problem, plan, step_s)
    motion = NodeMotion(float(t[-1]), p, v, a, np.diff(t))
    return nodes_to_trajectory(model, problem, motion, source="casadi",
                               meta={**(meta or {}), "n_intervals": len(t) - 1, "profile": "linear",
                                     "switching": plan.to_dict()})


__all__ = ["sample", "trajectory", "output_splits", "OUTPUT_STEP_S", "DEVICE_OUTPUT_STEP_S",
           "DEVICE_CURVATURE_TOLERANCE"]
