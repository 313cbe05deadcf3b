"""CasADi expressions of the Falcon's closed-chain rigid-body dynamics.

The only CasADi code of :mod:`falcon_plan.model`. Coordinates are the end-effector point
p [m] and its velocity v = dp/dt [m/s] (base frame). Every body's motion is written through
the inverse kinematics (MODEL-CONVENTIONS "How each body moves"):

- leg: rotation about its pivot, inertia Izz + m |cm|^2 + Im N^2 (reflected motor);
- knee-side shin joint: point mass at the knee B, spinning at dtheta2/dt about its hinge;
- shin bars (2 per leg): on the parallelogram's centre line from C = B + d u2 along the bar
  direction u_b, centre of mass 56.35 mm from C; rotational energy from the transverse
  inertia and |du_b/dt| (no spin about the bar's own axis);
- effector-side shin joint: point mass at the effector joint, spinning at dtheta2/dt;
- end effector (plus an optional payload): point mass at p.

With T = 1/2 v^T M(p) v and V(p), Lagrange's equations give

    M(p) a + h(p, v) + g(p) = J(p)^T tau,

where J = dtheta1/dp and tau are the torques at the three leg pivots (theta1 sense). M is
assembled body by body as sum m J_k^T J_k (points) + I G_k^T G_k (rotations), and h as
sum m J_k^T (dJ_k/dt v) (+ the same for rotations), computed with forward-mode AD
(``jtimes``); it equals dM/dt v - 1/2 d(v^T M v)/dp, which a test checks.

Motor model (MODEL-CONVENTIONS "Encoders, motors, commands"): leg torque
tau_i = -N Tc_i (Ks - Kd N dtheta1_i/dt), scaled by the motor-gain effect and with the Kd
sign effect; friction torques (:mod:`falcon_plan.model.effects`) add at the pivots.

Every function takes the smooth-effect vector ``eff`` (``Effects.smooth_vector()``) as its
last input, so the planner and the identification can treat effects symbolically.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np

from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.effects import (LEG_COULOMB_FIELDS, LEG_GAIN_FIELDS, Effects,
                                      SMOOTH_EFFECT_FIELDS)
from falcon_plan.model.kinematics import leg_equations, leg_frames
from falcon_plan.model.params import GRAVITY_M_S2, FalconParams
from falcon_plan.model.workspace import (DEFAULT_LIMITS, WorkspaceLimits, bar_determinant,
                                         workspace_constraint_values)

CASADI_OPS = SimpleNamespace(sin=ca.sin, cos=ca.cos, sqrt=ca.sqrt, atan2=ca.atan2, acos=ca.acos)
N_EFFECTS = len(SMOOTH_EFFECT_FIELDS)


def _effect(eff: ca.SX, name: str) -> ca.SX:
    return eff[SMOOTH_EFFECT_FIELDS.index(name)]


def _per_leg(eff: ca.SX, names: tuple[str, str, str]) -> ca.SX:
    """The three per-leg entries ``names`` of ``eff`` as a 3x1 vector (leg order)."""
    return ca.vertcat(*[_effect(eff, n) for n in names])


@dataclass(frozen=True)
class LegKinematicsSX:
    """Symbolic leg angles of point p, each a 3x1 SX (leg index): ``theta1`` the leg angle,
    ``theta2`` the angle of the knee-to-effector line (from the same axis) and ``theta3`` the
    parallelogram angle [rad]; ``cos`` and ``sin``, (3, 3) each: their cosines and sines
    (row: leg; column: theta1, theta2, theta3), found algebraically
    (:func:`~falcon_plan.model.kinematics.leg_equations`), without the angles themselves."""

    theta1: ca.SX
    theta2: ca.SX
    theta3: ca.SX
    cos: ca.SX
    sin: ca.SX


def leg_angles_sx(p: ca.SX, params: FalconParams) -> LegKinematicsSX:
    """theta1, theta2, theta3 [rad] of the three legs as SX of ``p`` (3x1) [m, base frame],
    with the geometry of ``params``."""
    e_r, e_t = leg_frames(params)
    th1, th2, th3, cosines, sines = [], [], [], [], []
    for i in range(3):
        p_r = e_r[i, 0] * p[0] + e_r[i, 1] * p[1]
        p_t = e_t[i, 0] * p[0] + e_t[i, 1] * p[1]
        eq = leg_equations(p_r, p_t, p[2], params, CASADI_OPS)
        th1.append(eq["theta1"])
        th2.append(eq["theta2"])
        th3.append(eq["theta3"])
        cosines.append(ca.horzcat(eq["cos_theta1"], eq["cos_theta2"], eq["cos_theta3"]))
        sines.append(ca.horzcat(eq["sin_theta1"], eq["sin_theta2"], eq["sin_theta3"]))
    return LegKinematicsSX(ca.vertcat(*th1), ca.vertcat(*th2), ca.vertcat(*th3), ca.vertcat(*cosines),
                           ca.vertcat(*sines))


def gravity_vector(eff: ca.SX, gravity_m_s2: float = GRAVITY_M_S2) -> ca.SX:
    """Gravity [m/s^2]: (0, -gravity_m_s2, 0) rotated by the tilt about x, then about z (the
    tilt entries of the smooth-effect vector ``eff``)."""
    tx, tz = _effect(eff, "gravity_tilt_x_rad"), _effect(eff, "gravity_tilt_z_rad")
    g0 = ca.vertcat(0.0, -gravity_m_s2, 0.0)
    rx = ca.vertcat(ca.horzcat(1, 0, 0), ca.horzcat(0, ca.cos(tx), -ca.sin(tx)),
                    ca.horzcat(0, ca.sin(tx), ca.cos(tx)))
    rz = ca.vertcat(ca.horzcat(ca.cos(tz), -ca.sin(tz), 0), ca.horzcat(ca.sin(tz), ca.cos(tz), 0),
                    ca.horzcat(0, 0, 1))
    return rz @ (rx @ g0)


@dataclass(frozen=True)
class _Body:
    """One term of the energies: coordinate ``x`` (a point 3x1, an angle, or the bars' unit
    direction u_b, whose rate's norm is their transverse angular speed); kinetic energy
    1/2 ``kinetic_weight`` |dx/dt|^2 (a mass or an inertia); potential energy
    -``gravity_mass`` g.x (points only)."""

    x: ca.SX
    kinetic_weight: float | ca.SX
    gravity_mass: float | ca.SX


def _bodies(p: ca.SX, eff: ca.SX, params: FalconParams) -> list[_Body]:
    e_r, e_t = leg_frames(params)
    e_z = ca.DM([0.0, 0.0, 1.0])
    legs = leg_angles_sx(p, params)
    a, d = params.a_m, params.d_m
    cx, cy = params.leg_com_m
    m_joint, m_bars = params.shin_joint_mass_kg, 2.0 * params.shin_bar_mass_kg
    # link-mass effect: the leg body's mass and own inertia scale, the reflected motor's do not
    link = _effect(eff, "link_mass_scale")
    motor = params.motor_inertia_kgm2 * params.drive_ratio ** 2
    leg_inertia = (params.leg_inertia_about_pivot_kgm2 - motor) * link + motor
    bodies: list[_Body] = []
    for i in range(3):
        er, et = ca.DM(e_r[i]), ca.DM(e_t[i])
        pivot = params.r_m * er + params.s_m * et
        (c1, c2, c3), (s1, s2, s3) = ([legs.cos[i, j] for j in range(3)], [legs.sin[i, j] for j in range(3)])
        along = c1 * er + s1 * e_z          # leg x axis: pivot -> knee
        across = -s1 * er + c1 * e_z        # leg y axis: the way the knee moves as theta1 grows
        knee = pivot + a * along
        u2 = c2 * er + s2 * e_z
        u_bar = s3 * u2 + c3 * et
        bar_com = knee + d * u2 + params.shin_bar_com_m * u_bar
        bodies += [
            # leg: rotation about its pivot (reflected motor included); weight at its CoM
            _Body(legs.theta1[i], leg_inertia, 0.0),
            _Body(pivot + cx * along + cy * across, 0.0, params.leg_mass_kg * link),
            # knee-side shin joint: point mass at the knee, spinning with theta2
            _Body(knee, m_joint, m_joint),
            _Body(legs.theta2[i], params.shin_joint_inertia_kgm2, 0.0),
            # the two shin bars: centre-of-mass translation and transverse rotation
            _Body(bar_com, m_bars, m_bars),
            _Body(u_bar, 2.0 * params.shin_bar_inertia_kgm2, 0.0),
            # effector-side shin joint: point mass moving with p, spinning with theta2
            _Body(p, m_joint, m_joint),
            _Body(legs.theta2[i], params.shin_joint_inertia_kgm2, 0.0),
        ]
    m_eff = params.effector_mass_kg + _effect(eff, "payload_kg")
    bodies.append(_Body(p, m_eff, m_eff))
    return bodies


def friction_torque(w: ca.SX, eff: ca.SX) -> ca.SX:
    """Friction torques at the leg pivots [N.m, theta1 sense] at leg speeds ``w`` [rad/s]
    (3x1), ``eff`` the smooth-effect vector: -(viscous w + (coulomb + coulomb_leg_i + stribeck
    exp(-(w / v_s)^2)) tanh(w / w_s)). The one place the friction law is written."""
    smooth_sign = ca.tanh(w / _effect(eff, "friction_smoothing_rad_s"))
    stribeck = _effect(eff, "stribeck_Nm") * ca.exp(-(w / _effect(eff, "stribeck_velocity_rad_s")) ** 2)
    coulomb = _effect(eff, "coulomb_Nm") + _per_leg(eff, LEG_COULOMB_FIELDS)
    return -(_effect(eff, "viscous_Nms") * w + (coulomb + stribeck) * smooth_sign)


def motor_torque_per_command(speed_rad_s: ca.SX, eff: ca.SX, params: FalconParams) -> ca.SX:
    """d tau / d Tc [N.m at the leg per command unit] of the motor model at a motor speed
    ``speed_rad_s`` expressed at the leg (theta1 rate for a rigid drive) [rad/s], 3x1:
    -N gain_i (Ks - s Kd N speed_i), gain_i = motor_gain * motor_gain_leg_i, with the Kd-sign
    effect s; ``eff`` is the smooth-effect vector and ``params`` gives N, Ks and Kd. The one
    place the motor law is written."""
    n = params.drive_ratio
    gain = _effect(eff, "motor_gain") * _per_leg(eff, LEG_GAIN_FIELDS)
    return -n * gain * (params.ks_Nm - _effect(eff, "kd_sign") * params.kd_Nms * n * speed_rad_s)


_motor_law_cache: dict[FalconParams, ca.Function] = {}


def torque_per_command(speed_rad_s: Any, effects: Effects, params: FalconParams) -> np.ndarray:
    """:func:`motor_torque_per_command` evaluated in numpy: d tau / d Tc [N.m per command
    unit] per leg, shape (..., 3), at leg speeds ``speed_rad_s`` [rad/s] (..., 3) (a scalar
    applies to every leg), with the motor gains and Kd sign of ``effects`` and the motor
    constants of ``params``. For the numeric users (toppra's constraint, characterisation)."""
    if params not in _motor_law_cache:
        w, eff = ca.SX.sym("w", 3), ca.SX.sym("eff", N_EFFECTS)
        _motor_law_cache[params] = ca.Function("torque_per_command", [w, eff],
                                               [motor_torque_per_command(w, eff, params)])
    speed = np.broadcast_to(np.asarray(speed_rad_s, dtype=float), np.broadcast_shapes(np.shape(speed_rad_s), (3,)))
    flat = speed.reshape(-1, 3)
    out = np.asarray(_motor_law_cache[params].map(flat.shape[0])(flat.T, effects.smooth_vector()))
    return out.T.reshape(speed.shape)


@dataclass(frozen=True)
class DynamicsExpressions:
    """SX expressions of the dynamics, in symbols ``p``, ``v``, ``a`` (3x1 each) and ``eff``.

    Attributes
    ----------
    p, v, a : end-effector position [m], velocity [m/s] and acceleration [m/s^2] (base
        frame); eff : the smooth-effect vector (:data:`N_EFFECTS` entries).
    theta1, theta2, theta3 : the legs' angles [rad], 3x1 each (as :class:`LegKinematicsSX`).
    theta1_dot : the legs' angular velocities J v [rad/s] (3x1).
    jacobian, mass_matrix, bias, generalized_force, gravity, friction_torque,
    torque_per_command, workspace_margins : as described at each field.
    kinetic_energy, potential_energy : T and V [J] (V up to a constant).
    """

    p: ca.SX
    v: ca.SX
    a: ca.SX
    eff: ca.SX
    theta1: ca.SX
    theta2: ca.SX
    theta3: ca.SX
    jacobian: ca.SX
    """J = dtheta1/dp (3x3) [rad/m]."""
    theta1_dot: ca.SX
    mass_matrix: ca.SX
    """M(p) (3x3) [kg]."""
    bias: ca.SX
    """h(p, v): Coriolis and centrifugal terms (3x1) [N]."""
    generalized_force: ca.SX
    """M(p) a + h(p, v) + g(p) (3x1) [N], computed by virtual power (sum over the bodies of
    J_b^T times the body's inertial and gravity load, one reverse-mode sweep): the same
    quantity in about 2.4x fewer operations than assembling M (the inverse dynamics uses it)."""
    gravity: ca.SX
    """g(p) = dV/dp (3x1) [N]."""
    kinetic_energy: ca.SX
    potential_energy: ca.SX
    friction_torque: ca.SX
    """Friction torques at the pivots (3x1) [N.m], theta1 sense."""
    torque_per_command: ca.SX
    """d tau_i / d Tc_i (3x1) [N.m per command unit]: -N gain (Ks - s Kd N theta1_dot)."""
    workspace_margins: ca.SX
    """Workspace constraint values (>= 0 inside), rows as workspace.CONSTRAINT_NAMES x legs."""


def _checked_gravity(gravity_m_s2: float) -> float:
    """The gravity magnitude as a float, or InvalidParameterError naming what is allowed."""
    if isinstance(gravity_m_s2, bool) or not isinstance(gravity_m_s2, (int, float)) \
            or not math.isfinite(gravity_m_s2) or gravity_m_s2 < 0:
        raise InvalidParameterError(f"gravity_m_s2 must be a finite number >= 0 [m/s^2], got {gravity_m_s2!r}")
    return float(gravity_m_s2)


def build_expressions(params: FalconParams, limits: WorkspaceLimits = DEFAULT_LIMITS,
                      gravity_m_s2: float = GRAVITY_M_S2) -> DynamicsExpressions:
    """Build every expression of the dynamics symbolically (SX), for the parameter set
    ``params`` and the workspace ``limits`` (of the margins).

    ``gravity_m_s2`` is the magnitude of gravity [m/s^2] (default 9.81, along -y before the
    tilt effects). It is a builder argument, not an effect: 0 gives the gravity-free model
    that the verification tests use (energy conservation of the kinetic energy alone).
    """
    gravity_m_s2 = _checked_gravity(gravity_m_s2)
    p, v, a = ca.SX.sym("p", 3), ca.SX.sym("v", 3), ca.SX.sym("a", 3)
    eff = ca.SX.sym("eff", N_EFFECTS)
    legs = leg_angles_sx(p, params)
    jac = ca.jacobian(legs.theta1, p)
    theta1_dot = jac @ v
    gvec = gravity_vector(eff, gravity_m_s2)

    mass = ca.SX.zeros(3, 3)
    bias = ca.SX.zeros(3, 1)
    kinetic = ca.SX(0.0)
    potential = ca.SX(0.0)
    coords, loads = [], []
    for body in _bodies(p, eff, params):
        load = ca.SX.zeros(body.x.shape)
        if not (isinstance(body.kinetic_weight, float) and body.kinetic_weight == 0.0):
            jb = ca.jacobian(body.x, p)
            xdot = ca.jtimes(body.x, p, v)   # one forward sweep (as J_b v); its own sweep along v
            # then gives dJ_b/dt v with a quarter fewer operations than differentiating J_b v
            mass += body.kinetic_weight * (jb.T @ jb)
            bias += body.kinetic_weight * (jb.T @ ca.jtimes(xdot, p, v))
            kinetic += 0.5 * body.kinetic_weight * ca.sumsqr(xdot)
            load += body.kinetic_weight * (ca.jtimes(xdot, p, v) + jb @ a)
        if not (isinstance(body.gravity_mass, float) and body.gravity_mass == 0.0):
            potential += -body.gravity_mass * ca.dot(gvec, body.x)
            load -= body.gravity_mass * gvec
        coords.append(body.x)
        loads.append(load)
    gravity = ca.gradient(potential, p)
    # virtual power: sum_b J_b^T (w_b xddot_b - m_b g), one reverse sweep over every body
    generalized = ca.jtimes(ca.vertcat(*coords), p, ca.vertcat(*loads), True)

    w = theta1_dot
    friction = friction_torque(w, eff)
    torque_per_command = motor_torque_per_command(w, eff, params)

    dets = bar_determinant([legs.theta2[i] for i in range(3)], [legs.theta3[i] for i in range(3)],
                           params, CASADI_OPS)
    margins = workspace_constraint_values(legs.theta1, legs.theta2, legs.theta3,
                                          ca.fabs(dets), limits, CASADI_OPS)
    return DynamicsExpressions(
        p=p, v=v, a=a, eff=eff, theta1=legs.theta1, theta2=legs.theta2, theta3=legs.theta3,
        jacobian=jac, theta1_dot=theta1_dot, mass_matrix=mass, bias=bias, generalized_force=generalized,
        gravity=gravity,
        kinetic_energy=kinetic, potential_energy=potential, friction_torque=friction,
        torque_per_command=torque_per_command, workspace_margins=ca.vertcat(*margins))


@dataclass(frozen=True)
class DynamicsFunctions:
    """Compiled (SX) CasADi Functions of the dynamics; all take ``eff`` last.

    - ``leg_angles(p, eff) -> (theta1, theta2, theta3)`` [rad]
    - ``jacobian(p, eff) -> J`` [rad/m]
    - ``mass_matrix(p, eff) -> M`` [kg]
    - ``bias(p, v, eff) -> h`` [N]; ``gravity(p, eff) -> g`` [N]
    - ``energy(p, v, eff) -> (T, V)`` [J]
    - ``leg_torques(p, v, a, eff) -> tau`` [N.m]: pivot torques the motion needs, total
    - ``inverse_dynamics(p, v, a, eff) -> Tc`` [command units, real-valued]: the commands
      that produce the motion through the motor model, friction included
    - ``forward_dynamics(p, v, Tc, eff) -> a`` [m/s^2]
    - ``forward_dynamics_torque(p, v, tau_motor, eff) -> a``: from motor torques at the pivots
      (friction added inside), for plants that model the drive themselves
    - ``workspace_margins(p, eff) -> m`` (>= 0 inside)
    - ``count_linearisation(p, v, Tc, eff) -> (27,)``: the dynamics linearised in encoder
      space, s = (n, dn/dt) [counts, counts/s] with n = counts_per_rad theta1: ds/dt =
      [[0, I], [A21, A22]] s + [[0], [B2]] Tc, returned as the column-major entries of A21
      [1/s^2], A22 [1/s] and B2 [counts/s^2 per command unit] (the tracking controller's
      design model, :mod:`falcon_plan.lqr`)

    ``expressions`` holds the SX expressions they were built from.
    """

    leg_angles: ca.Function
    jacobian: ca.Function
    mass_matrix: ca.Function
    bias: ca.Function
    gravity: ca.Function
    energy: ca.Function
    leg_torques: ca.Function
    inverse_dynamics: ca.Function
    forward_dynamics: ca.Function
    forward_dynamics_torque: ca.Function
    workspace_margins: ca.Function
    count_linearisation: ca.Function
    expressions: DynamicsExpressions


def solve_mass(mass: ca.SX, rhs: ca.SX) -> ca.SX:
    """M^-1 rhs for the symmetric positive definite 3x3 mass matrix ``mass`` by its adjugate
    over its determinant (closed form: about 260 fewer operations in the forward dynamics than
    CasADi's general symbolic solve, the same values to rounding; a test checks M x = rhs)."""
    m00, m01, m02, m11, m12, m22 = mass[0, 0], mass[0, 1], mass[0, 2], mass[1, 1], mass[1, 2], mass[2, 2]
    c00, c01, c02 = m11 * m22 - m12 * m12, m02 * m12 - m01 * m22, m01 * m12 - m02 * m11
    c11, c12, c22 = m00 * m22 - m02 * m02, m01 * m02 - m00 * m12, m00 * m11 - m01 * m01
    adjugate = ca.vertcat(ca.horzcat(c00, c01, c02), ca.horzcat(c01, c11, c12), ca.horzcat(c02, c12, c22))
    return (adjugate @ rhs) / (m00 * c00 + m01 * c01 + m02 * c02)


def _count_linearisation(ex: DynamicsExpressions, tc: ca.SX, params: FalconParams) -> ca.SX:
    """The entries of A21, A22, B2 of the encoder-space linearisation (see
    :class:`DynamicsFunctions`). With n = c theta1(p) (c counts per radian) and dn/dt = c J v,
    the counts' acceleration is g(p, v, Tc) = c (J a + d(J v)/dp v); through p(n) and
    v(n, dn/dt) = (c J)^-1 dn/dt the chain rule gives dp/dn = (c J)^-1 and, at constant dn/dt,
    dv/dn = -J^-1 d(J v)/dp dp/dn."""
    p, v, jac = ex.p, ex.v, ex.jacobian
    rhs = jac.T @ (ex.torque_per_command * tc + ex.friction_torque) - ex.bias - ex.gravity
    accel = solve_mass(ex.mass_matrix, rhs)
    c = params.counts_per_rad
    counts_accel = c * (jac @ accel + ca.jtimes(ex.theta1_dot, p, v))
    dp_dn = ca.inv(c * jac)
    dv_dn = -ca.solve(jac, ca.jacobian(ex.theta1_dot, p)) @ dp_dn
    g_p, g_v = ca.jacobian(counts_accel, p), ca.jacobian(counts_accel, v)
    a21 = g_p @ dp_dn + g_v @ dv_dn
    a22 = g_v @ dp_dn
    b2 = ca.jacobian(counts_accel, tc)
    return ca.vertcat(ca.vec(a21), ca.vec(a22), ca.vec(b2))


_function_cache: dict[tuple[FalconParams, WorkspaceLimits, float], DynamicsFunctions] = {}


def dynamics_functions(params: FalconParams, limits: WorkspaceLimits = DEFAULT_LIMITS,
                       gravity_m_s2: float = GRAVITY_M_S2) -> DynamicsFunctions:
    """Build (once per parameter set ``params``, ``limits`` and gravity magnitude [m/s^2],
    then cached) the dynamics Functions; see :func:`build_expressions` for ``gravity_m_s2``."""
    key = (params, limits, _checked_gravity(gravity_m_s2))
    if key in _function_cache:
        return _function_cache[key]
    ex = build_expressions(params, limits, gravity_m_s2)
    p, v, a, eff = ex.p, ex.v, ex.a, ex.eff
    tc = ca.SX.sym("tc", 3)
    tau_m = ca.SX.sym("tau_motor", 3)
    jt = ex.jacobian.T
    tau_total = ca.solve(jt, ex.generalized_force)
    command = (tau_total - ex.friction_torque) / ex.torque_per_command
    rhs_cmd = jt @ (ex.torque_per_command * tc + ex.friction_torque) - ex.bias - ex.gravity
    rhs_tau = jt @ (tau_m + ex.friction_torque) - ex.bias - ex.gravity
    fns = DynamicsFunctions(
        leg_angles=ca.Function("leg_angles", [p, eff], [ex.theta1, ex.theta2, ex.theta3],
                               ["p", "eff"], ["theta1", "theta2", "theta3"]),
        jacobian=ca.Function("jacobian", [p, eff], [ex.jacobian], ["p", "eff"], ["J"]),
        mass_matrix=ca.Function("mass_matrix", [p, eff], [ex.mass_matrix], ["p", "eff"], ["M"]),
        bias=ca.Function("bias", [p, v, eff], [ex.bias], ["p", "v", "eff"], ["h"]),
        gravity=ca.Function("gravity", [p, eff], [ex.gravity], ["p", "eff"], ["g"]),
        energy=ca.Function("energy", [p, v, eff], [ex.kinetic_energy, ex.potential_energy],
                           ["p", "v", "eff"], ["T", "V"]),
        leg_torques=ca.Function("leg_torques", [p, v, a, eff], [tau_total], ["p", "v", "a", "eff"], ["tau"]),
        inverse_dynamics=ca.Function("inverse_dynamics", [p, v, a, eff], [command],
                                     ["p", "v", "a", "eff"], ["tc"]),
        forward_dynamics=ca.Function("forward_dynamics", [p, v, tc, eff],
                                     [solve_mass(ex.mass_matrix, rhs_cmd)], ["p", "v", "tc", "eff"], ["a"]),
        forward_dynamics_torque=ca.Function("forward_dynamics_torque", [p, v, tau_m, eff],
                                            [solve_mass(ex.mass_matrix, rhs_tau)],
                                            ["p", "v", "tau_motor", "eff"], ["a"]),
        workspace_margins=ca.Function("workspace_margins", [p, eff], [ex.workspace_margins],
                                      ["p", "eff"], ["margins"]),
        count_linearisation=ca.Function("count_linearisation", [p, v, tc, eff],
                                        [_count_linearisation(ex, tc, params)], ["p", "v", "tc", "eff"], ["abc"]),
        expressions=ex,
    )
    _function_cache[key] = fns
    return fns


__all__ = ["DynamicsExpressions", "DynamicsFunctions", "build_expressions", "dynamics_functions",
           "solve_mass", "leg_angles_sx", "motor_torque_per_command", "friction_torque", "gravity_vector", "torque_per_command", "CASADI_OPS", "N_EFFECTS"]
