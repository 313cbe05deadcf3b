"""An independent, plain-numpy reference of the Falcon's rigid-body dynamics (for checks only).

Written from ``shared/MODEL-CONVENTIONS.md`` without calling :mod:`falcon_plan.model.symbolic`
or :mod:`falcon_plan.model.kinematics`: its own inverse kinematics (circle intersection in the
leg plane instead of the atan2/acos formula), its own body positions, and a *numeric*
Lagrangian:

- body Jacobians dx_k/dp by 4th-order central differences of the body coordinates;
- M(p) = sum_k w_k J_k^T J_k, i.e. the Hessian in v of T = 1/2 sum_k w_k |J_k v|^2;
- h(p, v) = (dM/dt) v - 1/2 d(v^T M v)/dp, both derivatives by central differences in p
  (a different formula from the main model's sum_k w_k J_k^T (dJ_k/dt) v);
- g(p) = dV/dp by central differences of V(p) = -sum_k m_k gvec . x_k.

Units: SI, base frame (x right, y up, z toward the user). Everything is vectorised over the
finite-difference stencil, so one call evaluates all the perturbed points in one batch.
"""
from __future__ import annotations

import numpy as np

from falcon_plan.model.params import FalconParams

GRAVITY = np.array([0.0, -9.81, 0.0])
"""Gravity vector [m/s^2] (MODEL-CONVENTIONS "Frame")."""

_D1 = (np.array([-2.0, -1.0, 1.0, 2.0]), np.array([1.0, -8.0, 8.0, -1.0]) / 12.0)
"""4th-order central first-derivative stencil: offsets and weights (divide by the step)."""


def _legs(params: FalconParams) -> tuple[np.ndarray, np.ndarray]:
    phi = np.radians(np.asarray(params.leg_azimuth_deg, dtype=float))
    e_r = np.stack([np.cos(phi), np.sin(phi), np.zeros(3)], -1)
    e_t = np.stack([-np.sin(phi), np.cos(phi), np.zeros(3)], -1)
    return e_r, e_t


def body_coordinates(p: np.ndarray, params: FalconParams) -> list[tuple[np.ndarray, float, float]]:
    """Every energy term of the nominal model at points p [m], shape (..., 3).

    Returns (coordinate (..., k), kinetic weight [kg or kg.m^2], gravity mass [kg]) triples:
    points (k = 3) carry mass, angles and the bar direction (k = 1 or 3) carry an inertia.
    Potential energy is only given up to constants (pivot offsets).
    """
    e_r, e_t = _legs(params)
    e_z = np.array([0.0, 0.0, 1.0])
    a, b = params.a_m, params.b_m
    out: list[tuple[np.ndarray, float, float]] = []
    m_joint = params.shin_joint_mass_kg
    for i in range(3):
        # tangential: b cos th3 = p.e_t - (s - f)
        cos3 = (p @ e_t[i] - (params.s_m - params.f_m)) / b
        sin3 = np.sqrt(1.0 - cos3 ** 2)
        shin = params.d_m + params.e_m + b * sin3
        # the effector joint in the leg plane, relative to the pivot: (u, w)
        u = p @ e_r[i] - (params.r_m - params.c_m)
        w = p[..., 2]
        dist = np.hypot(u, w)
        # knee = intersection of circle(0, a) and circle((u, w), shin), knee-outward branch
        along = (a * a - shin * shin + dist * dist) / (2.0 * dist)
        half = np.sqrt(a * a - along * along)
        knee_u = (along * u + half * w) / dist
        knee_w = (along * w - half * u) / dist
        th1 = np.arctan2(knee_w, knee_u)
        th2 = np.arctan2(w - knee_w, u - knee_u)
        c1, s1 = np.cos(th1)[..., None], np.sin(th1)[..., None]
        u2 = np.cos(th2)[..., None] * e_r[i] + np.sin(th2)[..., None] * e_z
        u_bar = sin3[..., None] * u2 + cos3[..., None] * e_t[i]
        knee = a * (c1 * e_r[i] + s1 * e_z)          # pivot at the origin of this leg
        cx, cy = params.leg_com_m
        leg_com = cx * (c1 * e_r[i] + s1 * e_z) + cy * (-s1 * e_r[i] + c1 * e_z)
        bar_com = knee + params.d_m * u2 + params.shin_bar_com_m * u_bar
        leg_inertia = (params.leg_izz_kgm2 + params.leg_mass_kg * (cx * cx + cy * cy)
                       + params.motor_inertia_kgm2 * params.drive_ratio ** 2)
        out += [
            (th1[..., None], leg_inertia, 0.0),
            (leg_com, 0.0, params.leg_mass_kg),
            (knee, m_joint, m_joint),
            (th2[..., None], 2.0 * params.shin_joint_inertia_kgm2, 0.0),  # both joints spin at dth2/dt
            (bar_com, 2.0 * params.shin_bar_mass_kg, 2.0 * params.shin_bar_mass_kg),
            (u_bar, 2.0 * params.shin_bar_inertia_kgm2, 0.0),
            (p, m_joint, m_joint),                                        # effector-side joint
        ]
    out.append((p, params.effector_mass_kg, params.effector_mass_kg))
    return out


def theta1(p: np.ndarray, params: FalconParams) -> np.ndarray:
    """Leg angles theta1 [rad] of points p [m], shape (..., 3), from the reference kinematics."""
    terms = body_coordinates(np.asarray(p, float), params)
    return np.concatenate([terms[7 * i][0] for i in range(3)], axis=-1)


def _stencil_derivative(fun, p: np.ndarray, direction: np.ndarray, step: float) -> np.ndarray:
    """d/ds fun(p + s direction) at s = 0, 4th-order central differences; fun maps (..., 3)
    points to (..., k) values and is called once on the whole stencil."""
    offsets, weights = _D1
    pts = p[None, ...] + (offsets * step)[:, None] * direction[None, ...]
    vals = fun(pts)
    return np.tensordot(weights, vals, axes=1) / step


def body_jacobians(p: np.ndarray, params: FalconParams, step_m: float = 1e-4) -> list[tuple[np.ndarray, float, float]]:
    """(dx_k/dp (k, 3), kinetic weight, gravity mass) of every term at one point p [m]."""
    p = np.asarray(p, float)
    offsets, weights = _D1
    # stencil over the 3 axes: shape (4 offsets, 3 axes, 3)
    pts = p + (offsets * step_m)[:, None, None] * np.eye(3)[None]
    terms = body_coordinates(pts, params)
    result = []
    for x, kin, grav in terms:
        jac = np.tensordot(weights, x, axes=1) / step_m      # (3 axes, k)
        result.append((jac.T, kin, grav))
    return result


def mass_matrix(p: np.ndarray, params: FalconParams) -> np.ndarray:
    """M(p) [kg], (3, 3): the Hessian in v of T = 1/2 sum w |J_k v|^2 (exact for a quadratic)."""
    mass = np.zeros((3, 3))
    for jac, kin, _ in body_jacobians(p, params):
        if kin:
            mass += kin * jac.T @ jac
    return mass


def kinetic_energy(p: np.ndarray, v: np.ndarray, params: FalconParams) -> float:
    """T(p, v) [J]."""
    v = np.asarray(v, float)
    return 0.5 * float(v @ mass_matrix(p, params) @ v)


def potential_energy(p: np.ndarray, params: FalconParams, gravity: np.ndarray = GRAVITY) -> np.ndarray:
    """V(p) [J] up to a constant, for points p [m] of shape (..., 3)."""
    total = 0.0
    for x, _, grav in body_coordinates(np.asarray(p, float), params):
        if grav:
            total = total - grav * (x @ gravity)
    return total


def gravity_term(p: np.ndarray, params: FalconParams, gravity: np.ndarray = GRAVITY,
                 step_m: float = 1e-4) -> np.ndarray:
    """g(p) = dV/dp [N], (3,), by central differences."""
    p = np.asarray(p, float)
    return np.array([_stencil_derivative(lambda q: potential_energy(q, params, gravity), p, e, step_m)
                     for e in np.eye(3)])


def bias_term(p: np.ndarray, v: np.ndarray, params: FalconParams, step_m: float = 1e-4) -> np.ndarray:
    """h(p, v) = (dM/dt) v - 1/2 d(v^T M v)/dp [N], (3,), outer derivatives by central
    differences of :func:`mass_matrix` (which is itself a finite-difference quantity)."""
    p, v = np.asarray(p, float), np.asarray(v, float)
    offsets, weights = _D1
    speed = float(np.linalg.norm(v))
    if speed == 0.0:
        return np.zeros(3)
    direction = v / speed
    dm_dt = sum(wt * mass_matrix(p + off * step_m * direction, params)
                for off, wt in zip(offsets, weights)) / step_m * speed
    grad = np.array([sum(wt * (v @ mass_matrix(p + off * step_m * e, params) @ v)
                         for off, wt in zip(offsets, weights)) / step_m for e in np.eye(3)])
    return dm_dt @ v - 0.5 * grad


def jacobian(p: np.ndarray, params: FalconParams, step_m: float = 1e-4) -> np.ndarray:
    """dtheta1/dp [rad/m], (3 legs, 3 xyz), by central differences of the reference IK."""
    return np.stack([_stencil_derivative(lambda q: theta1(q, params), np.asarray(p, float), e, step_m)
                     for e in np.eye(3)], axis=-1)


def inverse_dynamics(p: np.ndarray, v: np.ndarray, a: np.ndarray, params: FalconParams) -> np.ndarray:
    """Commands Tc (real) for acceleration a [m/s^2] at (p [m], v [m/s]), nominal model:
    tau = J^-T (M a + h + g), Tc = tau / (-N (Ks - Kd N theta1_dot))."""
    jac = jacobian(p, params)
    generalized = mass_matrix(p, params) @ a + bias_term(p, v, params) + gravity_term(p, params)
    tau = np.linalg.solve(jac.T, generalized)
    n = params.drive_ratio
    w = jac @ v
    return tau / (-n * (params.ks_Nm - params.kd_Nms * n * w))


def lumped_params(params: FalconParams) -> FalconParams:
    """A variant whose only mass is the end effector (every other mass and inertia ~0; the
    leg mass must stay > 0, so it is 1e-15 kg)."""
    return params.replace(leg_mass_kg=1e-15, leg_izz_kgm2=0.0, motor_inertia_kgm2=0.0,
                          shin_bar_mass_kg=0.0, shin_bar_inertia_kgm2=0.0,
                          shin_joint_mass_kg=0.0, shin_joint_inertia_kgm2=0.0,
                          name=params.name + "-lumped")


__all__ = ["body_coordinates", "theta1", "mass_matrix", "kinetic_energy", "potential_energy",
           "gravity_term", "bias_term", "jacobian", "inverse_dynamics", "lumped_params",
           "GRAVITY"]
