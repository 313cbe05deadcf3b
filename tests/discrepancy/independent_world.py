"""A second, independently written Falcon simulator that makes falcon logs for the tests.

It shares nothing with the project's plant (:mod:`falcon_plan.sim.plant`) or its effect code
(:mod:`falcon_plan.model.symbolic`, :mod:`falcon_plan.model.effects`) except the paper's
numbers (:class:`~falcon_plan.model.params.FalconParams`) and the C compiler helper. So the
logs differ from the identification's model *in form*, as a real device's would:

- **Dynamics**: Euler-Lagrange equations taken by automatic differentiation of the energies,
  M = d2T/dv2, M a = Q + dT/dp - (d/dp dT/dv) v - dV/dp, with every body's position written
  here from its own inverse kinematics (the half-angle root of the leg equation); the leg is
  a rigid body (centre-of-mass translation plus rotation about the centre of mass), not an
  inertia about the pivot. A test checks it against the project model at a few points.
- **Integrator**: semi-implicit (symplectic) Euler at about 10 kHz (``substeps`` per control
  period), not RK4 once per period.
- **Friction**: a time-stepping (Moreau) friction impulse per leg solved by projected
  Gauss-Seidel on the legs' coupled inertia, so a leg truly sticks (zero rate, any torque up
  to break-away) and the sign switch is sharp, not a tanh. The Stribeck curve is
  exponential, F(w) = Fc + (Fs - Fc) exp(-|w| / w_s), with a low break-away speed w_s.
- **Drive**: the motor law To = Tc gain_i (Ks + s Kd w_m) per leg, a saturation that rises
  linearly (not as a smoothstep) from 2500 at rest to 4096 at 2 rad/s; with backlash or a
  finite cable stiffness a two-mass drive (motor inertia on its own, a dead band of its own
  contact law). The encoder reads the motor angle from the true home angle.
- **Loop**: its own encoder PD following the log's ``controller`` metadata
  (``pd kp=.. kd=..``, 50 Hz velocity filter), whole-count quantisation, a transport delay of
  2 + extra periods; lost samples (``drop``) are rows missing from the log, and in those
  periods the host sends nothing (the firmware holds the last command).
- **Out of the library**: cogging torque A sin(n N theta1) per leg (``cogging_Nm``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import casadi as ca
import numpy as np
from scipy.optimize import fsolve

from falcon_plan.compiled import build_shared_library
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.params import ACRA2009, FalconParams
from falcon_plan.compiled import BufferedFunction

G = 9.81
COGGING_CYCLES_PER_MOTOR_TURN = 12
PGS_SWEEPS = 8
SUBSTEP_TARGET_HZ = 10_000.0
DRIVE_CONTACT_STIFFNESS = 5000.0
"""Contact stiffness of the slack-free cable in a pure-backlash world [N.m/rad at the leg]."""
DRIVE_DAMPING_RATIO = 0.2

WORLD_FIELDS = ("coulomb0", "coulomb1", "coulomb2", "static0", "static1", "static2", "stribeck_speed",
                "viscous", "payload", "gain0", "gain1", "gain2", "kd_sign", "tilt_x", "tilt_z",
                "link_scale", "cog0", "cog1", "cog2", "stiffness", "damping", "half_backlash", "h",
                "sat_static", "sat_release")


@dataclass(frozen=True)
class World:
    """The true device. Per-leg tuples are in leg order (top, right, left).

    ``coulomb_Nm``: kinetic friction per leg; ``static_Nm``: break-away friction per leg
    (>= coulomb; equal means no Stribeck drop), falling to coulomb over ``stribeck_speed_rad_s``;
    ``gain``: motor-gain factors; ``encoder_offset_rad``: true home minus theta_home;
    ``cable_stiffness_Nm_rad`` (inf = rigid) and ``backlash_rad`` switch on the two-mass drive.
    """

    coulomb_Nm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    static_Nm: tuple[float, float, float] | None = None
    stribeck_speed_rad_s: float = 0.1
    viscous_Nms: float = 0.0
    payload_kg: float = 0.0
    gain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    kd_sign: float = 1.0
    tilt_x_rad: float = 0.0
    tilt_z_rad: float = 0.0
    link_scale: float = 1.0
    extra_delay: int = 0
    encoder_offset_rad: float = 0.0
    backlash_rad: float = 0.0
    cable_stiffness_Nm_rad: float = math.inf
    cogging_Nm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    params: FalconParams = field(default=ACRA2009, compare=False)

    @property
    def two_mass(self) -> bool:
        return self.backlash_rad > 0 or math.isfinite(self.cable_stiffness_Nm_rad)

    def vector(self, h: float) -> np.ndarray:
        """The runtime parameter vector in WORLD_FIELDS order for substep ``h`` [s]."""
        static = self.static_Nm if self.static_Nm is not None else self.coulomb_Nm
        k = self.cable_stiffness_Nm_rad if math.isfinite(self.cable_stiffness_Nm_rad) else DRIVE_CONTACT_STIFFNESS
        jm = self.params.motor_inertia_kgm2 * self.params.drive_ratio ** 2
        values = [*self.coulomb_Nm, *static, self.stribeck_speed_rad_s, self.viscous_Nms,
                  self.payload_kg, *self.gain, self.kd_sign, self.tilt_x_rad, self.tilt_z_rad,
                  self.link_scale, *self.cogging_Nm, k, 2 * DRIVE_DAMPING_RATIO * math.sqrt(k * jm),
                  0.5 * self.backlash_rad, h, float(self.params.command_saturation), 2.0]
        return np.array(values, dtype=float)


def _w(wp: ca.SX, name: str) -> ca.SX:
    return wp[WORLD_FIELDS.index(name)]


def _w3(wp: ca.SX, stem: str) -> ca.SX:
    return ca.vertcat(*[_w(wp, f"{stem}{i}") for i in range(3)])


def _leg_axes(params: FalconParams) -> list[tuple[np.ndarray, np.ndarray]]:
    axes = []
    for deg in params.leg_azimuth_deg:
        phi = math.radians(deg)
        axes.append((np.array([math.cos(phi), math.sin(phi), 0.0]), np.array([-math.sin(phi), math.cos(phi), 0.0])))
    return axes


def leg_angles(p: ca.SX, params: FalconParams) -> tuple[list, list, list]:
    """theta1, theta2, theta3 of each leg from p, by the half-angle root of
    u cos th1 + w sin th1 = K (the root with the knee outward)."""
    a, b = params.a_m, params.b_m
    t1, t2, t3 = [], [], []
    for er, et in _leg_axes(params):
        u = ca.dot(ca.DM(er), p) - (params.r_m - params.c_m)
        t = ca.dot(ca.DM(et), p) - (params.s_m - params.f_m)
        w = p[2]
        th3 = ca.acos(t / b)
        length = params.d_m + params.e_m + b * ca.sin(th3)
        k = (u * u + w * w + a * a - length * length) / (2 * a)
        # tan(th1 / 2) = (w - sqrt(u^2 + w^2 - k^2)) / (u + k), evaluated as the equal
        # (k - u) / (w + sqrt(u^2 + w^2 - k^2)): the first form is 0 / 0 on the surface u = -k,
        # which crosses the workspace (a recording passed within 1e-6 m of it on one leg, and
        # one substep's velocity came out 16 m/s from the cancellation in its derivatives)
        th1 = 2 * ca.atan((k - u) / (w + ca.sqrt(u * u + w * w - k * k)))
        th2 = ca.atan2(w - a * ca.sin(th1), u - a * ca.cos(th1))
        t1.append(th1)
        t2.append(th2)
        t3.append(th3)
    return t1, t2, t3


def _energies(p: ca.SX, v: ca.SX, wp: ca.SX, params: FalconParams, motor_on_leg: bool) -> tuple[ca.SX, ca.SX]:
    """Kinetic and potential energy [J] of the whole mechanism at (p, v)."""
    t1, t2, t3 = leg_angles(p, params)
    ez = ca.DM([0.0, 0.0, 1.0])
    tx, tz = _w(wp, "tilt_x"), _w(wp, "tilt_z")
    g_vec = ca.vertcat(G * ca.sin(tz) * ca.cos(tx), -G * ca.cos(tz) * ca.cos(tx), -G * ca.sin(tx))
    link = _w(wp, "link_scale")
    jm = params.motor_inertia_kgm2 * params.drive_ratio ** 2 if motor_on_leg else 0.0
    cx, cy = params.leg_com_m
    kin, pot = 0, 0

    def rate(x: ca.SX) -> ca.SX:
        return ca.jtimes(x, p, v)

    def point(mass: ca.SX, x: ca.SX) -> None:
        nonlocal kin, pot
        kin += 0.5 * mass * ca.sumsqr(rate(x))
        pot += -mass * ca.dot(g_vec, x)

    for i, (er, et) in enumerate(_leg_axes(params)):
        er_, et_ = ca.DM(er), ca.DM(et)
        pivot = params.r_m * er_ + params.s_m * et_
        along = ca.cos(t1[i]) * er_ + ca.sin(t1[i]) * ez
        across = -ca.sin(t1[i]) * er_ + ca.cos(t1[i]) * ez
        # leg: centre-of-mass translation + rotation about the centre of mass + motor
        point(params.leg_mass_kg * link, pivot + cx * along + cy * across)
        kin += 0.5 * (params.leg_izz_kgm2 * link + jm) * rate(t1[i]) ** 2
        knee = pivot + params.a_m * along
        u2 = ca.cos(t2[i]) * er_ + ca.sin(t2[i]) * ez
        ub = ca.sin(t3[i]) * u2 + ca.cos(t3[i]) * et_
        point(params.shin_joint_mass_kg, knee)
        point(params.shin_joint_mass_kg, p)
        kin += params.shin_joint_inertia_kgm2 * rate(t2[i]) ** 2          # two joints spin with th2
        point(2 * params.shin_bar_mass_kg, knee + params.d_m * u2 + params.shin_bar_com_m * ub)
        kin += params.shin_bar_inertia_kgm2 * ca.sumsqr(rate(ub))        # 2 x 1/2 I |dub/dt|^2
    point(params.effector_mass_kg + _w(wp, "payload"), p)
    return kin, pot


@dataclass(frozen=True)
class _Layout:
    params: FalconParams
    two_mass: bool
    substeps: int


def _lagrange(p: ca.SX, v: ca.SX, wp: ca.SX, params: FalconParams, motor_on_leg: bool):
    """(M, rhs without generalised forces, J = dtheta1/dp, theta1): M a = rhs + J^T tau."""
    kin, pot = _energies(p, v, wp, params, motor_on_leg)
    dtdv = ca.gradient(kin, v)
    mass = ca.jacobian(dtdv, v)
    rhs = ca.gradient(kin, p) - ca.jacobian(dtdv, p) @ v - ca.gradient(pot, p)
    th1 = ca.vertcat(*leg_angles(p, params)[0])
    return mass, rhs, ca.jacobian(th1, p), th1


def accel_function(params: FalconParams = ACRA2009) -> ca.Function:
    """(p, v, tau (leg torques, theta1 sense), wp) -> a, rigid drive, no friction (for tests)."""
    p, v, tau, wp = ca.SX.sym("p", 3), ca.SX.sym("v", 3), ca.SX.sym("tau", 3), ca.SX.sym("wp", len(WORLD_FIELDS))
    mass, rhs, jac, _ = _lagrange(p, v, wp, params, True)
    return ca.Function("world_accel", [p, v, tau, wp], [ca.solve(mass, rhs + jac.T @ tau)])


def _substep(layout: _Layout) -> ca.Function:
    """One semi-implicit Euler step with the friction impulse: (x, tc, wp) -> x_next."""
    params = layout.params
    n_x = 12 if layout.two_mass else 6
    x, tc, wp = ca.SX.sym("x", n_x), ca.SX.sym("tc", 3), ca.SX.sym("wp", len(WORLD_FIELDS))
    p, v = x[0:3], x[3:6]
    h = _w(wp, "h")
    n = params.drive_ratio
    mass, rhs, jac, th1 = _lagrange(p, v, wp, params, not layout.two_mass)
    w = jac @ v
    motor_speed = x[9:12] if layout.two_mass else w
    # saturation rising linearly with the motor speed, then the motor law per leg
    lim = _w(wp, "sat_static") + (4096 - _w(wp, "sat_static")) * ca.fmin(ca.fabs(motor_speed) / _w(wp, "sat_release"), 1)
    tc_act = ca.fmin(ca.fmax(tc, -lim), lim)
    motor = -n * _w3(wp, "gain") * tc_act * (params.ks_Nm - _w(wp, "kd_sign") * params.kd_Nms * n * motor_speed)
    cog = _w3(wp, "cog") * ca.sin(COGGING_CYCLES_PER_MOTOR_TURN * n * th1)
    tau = cog - _w(wp, "viscous") * w
    if layout.two_mass:
        qm, wm = x[6:9], x[9:12]
        gap = qm - th1
        half = _w(wp, "half_backlash")
        beyond = gap - ca.fmin(ca.fmax(gap, -half), half)
        engaged = ca.fabs(gap) > half
        cable = ca.if_else(engaged, _w(wp, "stiffness") * beyond + _w(wp, "damping") * (wm - w), 0)
        tau = tau + cable
        jm = params.motor_inertia_kgm2 * n ** 2
        wm_next = wm + h * (motor - cable) / jm
        qm_next = qm + h * wm_next
    else:
        tau = tau + motor
    minv_jt = ca.solve(mass, jac.T)
    v_free = v + h * ca.solve(mass, rhs + jac.T @ tau)
    # friction impulse per leg: |lambda_i| <= F_i(w_i) h, sticking when possible (PGS)
    coulomb, static = _w3(wp, "coulomb"), _w3(wp, "static")
    limit = h * (coulomb + (static - coulomb) * ca.exp(-ca.fabs(w) / _w(wp, "stribeck_speed")))
    delassus = jac @ minv_jt
    w_free = jac @ v_free
    lam = [ca.SX(0), ca.SX(0), ca.SX(0)]
    for _ in range(PGS_SWEEPS):
        for i in range(3):
            wi = w_free[i] + sum(delassus[i, j] * lam[j] for j in range(3))
            lam[i] = ca.fmin(ca.fmax(lam[i] - wi / delassus[i, i], -limit[i]), limit[i])
    v_next = v_free + minv_jt @ ca.vertcat(*lam)
    p_next = p + h * v_next
    parts = [p_next, v_next] + ([qm_next, wm_next] if layout.two_mass else [])
    return ca.Function("world_substep", [x, tc, wp], [ca.vertcat(*parts)])


@lru_cache(maxsize=None)
def _period(layout: _Layout) -> BufferedFunction:
    """``substeps`` substeps under one held command, compiled: (x, tc, wp) -> (x_next, theta1)."""
    step = _substep(layout)
    x, tc, wp = ca.MX.sym("x", step.size1_in(0)), ca.MX.sym("tc", 3), ca.MX.sym("wp", len(WORLD_FIELDS))
    loop = step.fold(layout.substeps)
    y = loop(x, ca.repmat(tc, 1, layout.substeps), ca.repmat(wp, 1, layout.substeps))
    th = ca.SX.sym("p", 3)
    theta_fn = ca.Function("world_theta", [th], [ca.vertcat(*leg_angles(th, layout.params)[0])])
    name = f"indep_world_{'tm' if layout.two_mass else 'rg'}_{layout.substeps}"
    fn = ca.Function(name, [x, tc, wp], [y, theta_fn(y[0:3])])
    return BufferedFunction(fn, build_shared_library(name, [fn], flags=("-O2",)))


def _start_point(theta1: np.ndarray, params: FalconParams) -> np.ndarray:
    """The point with leg angles theta1 (this module's own inverse kinematics, fsolve)."""
    p = ca.SX.sym("p", 3)
    th = ca.Function("th", [p], [ca.vertcat(*leg_angles(p, params)[0])])
    return fsolve(lambda q: np.asarray(th(q)).ravel() - theta1, np.array([0.0, 0.0, 0.12]), xtol=1e-13)


def simulate_log(world: World, ref_counts: np.ndarray, rate_hz: float = 800.0, *, kp: float = 10.0,
                 kd: float = 0.1, cutoff_hz: float = 50.0, drop: np.ndarray | None = None) -> FalconLog:
    """Run the encoder PD tracking ``ref_counts`` (N, 3) on ``world``; the falcon log.

    The device starts at rest where its counts read ref_counts[0]. ``drop``: indices of
    samples lost on the link (missing rows; no command is sent in those periods)."""
    params = world.params
    substeps = max(1, int(round(SUBSTEP_TARGET_HZ / rate_hz)))
    layout = _Layout(params, world.two_mass, substeps)
    fn = _period(layout)
    fn.inputs[2][:] = world.vector(1.0 / (rate_hz * substeps))
    cpr = params.counts_per_rad
    home = params.theta_home_rad + world.encoder_offset_rad
    theta0 = home + np.asarray(ref_counts[0], float) / cpr
    x = np.zeros(12 if world.two_mass else 6)
    x[0:3] = _start_point(theta0, params)
    if world.two_mass:
        x[6:9] = theta0
    n_rows = ref_counts.shape[0]
    lost = np.zeros(n_rows, dtype=bool)
    if drop is not None:
        lost[np.asarray(drop)] = True
    alpha = 1.0 - math.exp(-2.0 * math.pi * cutoff_hz / rate_hz)
    delay = params.command_delay_samples + world.extra_delay
    queue = [np.zeros(3)] * delay
    held = np.zeros(3)
    counts_now = np.floor((theta0 - home) * cpr + 0.5)
    prev, vel = counts_now.copy(), np.zeros(3)
    enc = np.zeros((n_rows, 3), dtype=np.int64)
    tc = np.zeros((n_rows, 3), dtype=np.int64)
    for k in range(n_rows):
        if not lost[k]:
            vel = vel + alpha * ((counts_now - prev) * rate_hz - vel)
            prev = counts_now
            cmd = np.clip(np.floor(kp * (counts_now - ref_counts[k]) + kd * vel + 0.5), -4096, 4096)
            held = cmd
        enc[k], tc[k] = counts_now, held
        queue.append(held)
        acting = queue.pop(0)
        fn.inputs[0][:] = x
        fn.inputs[1][:] = acting
        fn()
        x = fn.outputs[0].copy()
        if not np.all(np.isfinite(x)):
            raise RuntimeError(f"independent world diverged at sample {k}")
        motor = x[6:9] if world.two_mass else fn.outputs[1]
        counts_now = np.floor((motor - home) * cpr + 0.5)
    t = np.arange(n_rows) / rate_hz
    keep = ~lost
    meta = {"rate_hz": f"{rate_hz:g}", "controller": f"pd kp={kp:g} kd={kd:g}", "params": params.name,
            "source": "tests/discrepancy/independent_world.py"}
    return FalconLog(t[keep], enc[keep], tc[keep], np.asarray(ref_counts, float)[keep], meta)
