"""The planner's fallback: a feasible, slower motion from ruckig in leg-angle space, returned
at once when the optimiser fails or runs out of time, and also a reference that the plan
report compares the optimal plan against (:mod:`falcon_plan.planning.crosscheck`).

How: :func:`safe_joint_limits` bounds the pivot torques over the box of leg angles between
start and goal (from the model's inverse dynamics written in leg-angle space) and derives
leg-angle velocity and acceleration limits under which every command stays within tc_max;
:func:`ruckig_reference` gives those limits to ruckig (jerk-limited, rest or given end
velocities) and maps its leg-angle motion back to the workspace through forward kinematics.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np
import ruckig

from falcon_plan.errors import CrosscheckError, KinematicsError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import forward_kinematics, inverse_kinematics, jacobian
from falcon_plan.model.symbolic import torque_per_command
from falcon_plan.model.workspace import check_workspace
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.trajectory import Trajectory


@dataclass(frozen=True)
class JointLimits:
    """Leg-angle limits under which every command stays within tc_max (see
    :func:`safe_joint_limits`): |theta1_dot| <= ``velocity_rad_s`` [rad/s], |theta1_ddot| <=
    ``acceleration_rad_s2`` [rad/s^2] (every leg), ``jerk_rad_s3`` [rad/s^3] for ruckig's
    smoothness only; ``worst_command``: the largest bound on |Tc| at the sampled points with
    these limits [command units]; ``samples``: how many points of the leg-angle box the bound
    was taken at."""

    velocity_rad_s: float
    acceleration_rad_s2: float
    jerk_rad_s3: float
    worst_command: float
    """Largest bound on |Tc| at the sampled points with these limits [command units]."""
    samples: int


_joint_torque_cache: dict[tuple[Any, ...], ca.Function] = {}


def _joint_space_torques(model: FalconModel) -> ca.Function:
    """SX Function (p, theta1_dot, theta1_ddot, eff) -> pivot torques tau [N.m]: the model's
    ``leg_torques`` at v = J^-1 theta1_dot, a = J^-1 (theta1_ddot - (dJ/dt) v), built once per
    (params, limits)."""
    key = (model.params, model.limits)
    if key not in _joint_torque_cache:
        fns = model.functions
        ex = fns.expressions
        p, eff = ex.p, ex.eff
        thd, thdd = ca.SX.sym("thd", 3), ca.SX.sym("thdd", 3)
        v_free = ca.SX.sym("v", 3)                    # v held constant while differentiating J
        jdot_v = ca.substitute(ca.jtimes(ex.jacobian @ v_free, p, v_free), v_free, ca.solve(ex.jacobian, thd))
        v = ca.solve(ex.jacobian, thd)
        a = ca.solve(ex.jacobian, thdd - jdot_v)
        tau = ca.cse(fns.leg_torques(p, v, a, eff))
        _joint_torque_cache[key] = ca.Function("joint_space_torques", [p, thd, thdd, eff], [tau])
    return _joint_torque_cache[key]


def joint_space_terms(model: FalconModel, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At ``points`` (n, 3) [m], for ``model``'s dynamics, with tau_j = sum_i M_ji thdd_i +
    thd^T Q_j thd + G_j:
    |G| (3, n), sum_i |M_ji| (3, n) and sum_ik |Q_jik| (3, n), from 10 evaluations of the
    torques per point (zero; unit accelerations; unit speeds and pairs of them, by
    polarisation: the speed terms are exactly quadratic)."""
    eye = np.eye(3)
    pairs = [(0, 1), (0, 2), (1, 2)]
    thd = [np.zeros(3)] + [np.zeros(3)] * 3 + list(eye) + [eye[i] + eye[k] for i, k in pairs]
    thdd = [np.zeros(3)] + list(eye) + [np.zeros(3)] * 6
    n, m = len(points), len(thd)
    fn = _joint_space_torques(model).map(n * m)
    tau = np.asarray(fn(np.repeat(points, m, axis=0).T, np.tile(np.array(thd), (n, 1)).T,
                        np.tile(np.array(thdd), (n, 1)).T, np.repeat(model.effect_vector[:, None], n * m, 1)))
    tau = tau.reshape(3, n, m)                        # (leg j, point, case)
    g = tau[:, :, 0]
    m_abs = np.abs(tau[:, :, 1:4] - g[..., None]).sum(axis=2)
    q_diag = tau[:, :, 4:7] - g[..., None]
    q_off = [(tau[:, :, 7 + c] - g - q_diag[:, :, i] - q_diag[:, :, k]) / 2 for c, (i, k) in enumerate(pairs)]
    q_abs = np.abs(q_diag).sum(axis=2) + 2 * sum(np.abs(q) for q in q_off)
    return np.abs(g), m_abs, q_abs


def safe_joint_limits(model: FalconModel, theta_lo: np.ndarray, theta_hi: np.ndarray, tc_max: float,
                      distance_rad: float, *, grid: int = 3, margin: float = 0.15,
                      jerk_time_s: float = 0.005) -> JointLimits:
    """Leg-angle velocity and acceleration limits that keep |Tc| <= ``tc_max`` [command
    units] for ``model``'s dynamics and effects over the box [``theta_lo``, ``theta_hi``]
    [rad] of leg angles (which a rest-to-rest ruckig motion between two corners of the box
    never leaves); ``distance_rad`` is the largest leg-angle distance to travel.

    How: at grid^3 points of the box (forward kinematics), the pivot torques in leg-angle
    space are tau_j = sum_i M_ji theta1_ddot_i + theta1_dot^T Q_j theta1_dot + G_j, so with
    |theta1_dot| <= V, |theta1_ddot| <= A: |tau_j| <= |G_j| + A sum_i |M_ji| + V^2 sum |Q_j| (+ friction
    bound), and |Tc_j| <= that / (N gain Ks (1 - Kd N V / Ks)) (worst sign of the Kd term).
    V is chosen on a grid to minimise the rest-to-rest time over ``distance_rad``, A as the
    largest value the bound allows at every sample, both shrunk by ``margin`` for what lies
    between samples; jerk = A / jerk_time_s. The dense re-check of the result confirms it.
    """
    prm, eff = model.params, model.effects
    axes = [np.linspace(lo, hi, grid) if hi - lo > 1e-9 else np.array([lo]) for lo, hi in zip(theta_lo, theta_hi)]
    thetas = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    try:
        points = forward_kinematics(thetas, prm)
    except KinematicsError as exc:
        raise CrosscheckError(f"the leg-angle box between start and goal leaves the reachable set: {exc}") from exc
    g_abs, m_sum, q_sum = joint_space_terms(model, points)
    friction = eff.coulomb_Nm + eff.stribeck_Nm
    budget = tc_max / (1.0 + margin)

    def per_command(vel: float) -> np.ndarray:
        """|d tau / d Tc| per leg at leg speed vel with the Kd term's worse sign [N.m]."""
        both = np.abs(torque_per_command(np.array([[vel] * 3, [-vel] * 3]), eff, prm))
        return np.min(both, axis=0)[:, None]                      # (3 legs, 1): against (3, n)

    best: tuple[float, float, float] | None = None
    for vel in np.linspace(2.0, 60.0, 117):
        room = budget * per_command(vel) - g_abs - vel**2 * q_sum - friction - eff.viscous_Nms * vel
        acc = float(np.min(room / np.maximum(m_sum, 1e-12)))
        if acc <= 0:
            break
        t = (distance_rad / vel + vel / acc) if distance_rad > vel**2 / acc else 2.0 * math.sqrt(distance_rad / acc)
        if best is None or t < best[0]:
            best = (t, vel, acc)
    if best is None:
        raise CrosscheckError("no leg-angle velocity keeps the commands within tc_max here")
    _, vel, acc = best
    worst = (g_abs + acc * m_sum + vel**2 * q_sum + friction + eff.viscous_Nms * vel) / per_command(vel)
    return JointLimits(vel, acc, acc / jerk_time_s, float(worst.max()), len(points))


@dataclass(frozen=True)
class RuckigResult:
    """The ruckig reference: ``duration_s`` [s], the sampled ``trajectory``, its joint
    ``limits``, whether it stays ``inside_workspace`` (ruckig's Community edition ignores
    position limits), the ``solve_time_s`` [s] it took, and a ``note`` (e.g. via points
    ignored)."""

    duration_s: float
    trajectory: Trajectory
    limits: JointLimits
    inside_workspace: bool
    solve_time_s: float
    note: str = ""


def ruckig_reference(model: FalconModel, problem: PlanProblem, tc_max: float, *,
                     rate_hz: float = 1000.0, jerk_limited: bool = True) -> RuckigResult:
    """A feasible (slower) motion for ``problem`` (start, goal, end velocities): ruckig in
    leg-angle space with :func:`safe_joint_limits` for ``model`` and the command limit
    ``tc_max`` [command units], jerk-limited unless ``jerk_limited`` is False, mapped back
    through forward kinematics and sampled at ``rate_hz`` [Hz]. The planner's instant
    fallback and one of its references.

    Via points are not used (the Community edition sends them to a cloud API): the motion goes
    straight to the goal in leg-angle space; the report says so. Raises CrosscheckError if ruckig
    fails or the motion cannot be mapped back to the workspace.
    """
    t0 = time.perf_counter()
    prm = model.params
    th0 = inverse_kinematics(np.asarray(problem.start_m), prm).theta1
    th1 = inverse_kinematics(np.asarray(problem.goal_m), prm).theta1
    jac0, jac1 = jacobian(np.asarray(problem.start_m), prm), jacobian(np.asarray(problem.goal_m), prm)
    thd0 = jac0 @ np.asarray(problem.start_velocity_m_s)
    thd1 = jac1 @ np.asarray(problem.goal_velocity_m_s)
    pad = np.radians(1.0) + 0.02 * (np.abs(thd0) + np.abs(thd1))
    lo, hi = np.minimum(th0, th1) - pad, np.maximum(th0, th1) + pad
    lo = np.maximum(lo, model.limits.theta1_min_rad)
    hi = np.minimum(hi, model.limits.theta1_max_rad)
    limits = safe_joint_limits(model, lo, hi, tc_max, float(np.max(np.abs(th1 - th0))))
    otg = ruckig.Ruckig(3)
    inp = ruckig.InputParameter(3)
    inp.current_position, inp.current_velocity, inp.current_acceleration = list(th0), list(thd0), [0.0] * 3
    inp.target_position, inp.target_velocity, inp.target_acceleration = list(th1), list(thd1), [0.0] * 3
    inp.max_velocity = [limits.velocity_rad_s] * 3
    inp.max_acceleration = [limits.acceleration_rad_s2] * 3
    if jerk_limited:
        inp.max_jerk = [limits.jerk_rad_s3] * 3
    out = ruckig.Trajectory(3)
    result = otg.calculate(inp, out)
    if result not in (ruckig.Result.Working, ruckig.Result.Finished):
        raise CrosscheckError(f"ruckig failed: {result}")
    duration = float(out.duration)
    n = max(int(math.ceil(duration * rate_hz)), 2)
    t = np.linspace(0.0, duration, n + 1)
    samples = [out.at_time(float(ti)) for ti in t]
    th = np.array([s[0] for s in samples])
    thd = np.array([s[1] for s in samples])
    thdd = np.array([s[2] for s in samples])
    try:
        pos = forward_kinematics(th, prm)
    except KinematicsError as exc:
        raise CrosscheckError(f"ruckig's leg-angle motion leaves the reachable set: {exc}") from exc
    jac = jacobian(pos, prm)
    vel = np.linalg.solve(jac, thd[..., None])[..., 0]
    # Jdot v by a central difference of J along v (step 1e-6 s of motion)
    step = 1e-6
    jdot_v = np.einsum("nij,nj->ni", (jacobian(pos + step * vel, prm) - jacobian(pos - step * vel, prm)) / (2 * step), vel)
    acc = np.linalg.solve(jac, (thdd - jdot_v)[..., None])[..., 0]
    pos[0], pos[-1] = problem.start_m, problem.goal_m
    inside = bool(check_workspace(pos, prm, model.limits).inside.all())
    traj = Trajectory(t, pos, vel, acc, model.inverse_dynamics(pos, vel, acc), prm.name, "ruckig",
                      {"joint_limits": {"velocity_rad_s": limits.velocity_rad_s,
                                        "acceleration_rad_s2": limits.acceleration_rad_s2,
                                        "jerk_rad_s3": limits.jerk_rad_s3}})
    note = "via points ignored (ruckig Community edition)" if problem.via_m else ""
    return RuckigResult(duration, traj, limits, inside, time.perf_counter() - t0, note)


__all__ = ["JointLimits", "joint_space_terms", "safe_joint_limits", "RuckigResult", "ruckig_reference"]
