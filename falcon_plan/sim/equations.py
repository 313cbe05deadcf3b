"""The simulated plant's equations as CasADi Functions: the right-hand side of the drive and
leg dynamics (rigid or with the cable model, end stops, the saturation rule) and one control
period integrated by classical RK4, plus the runtime parameter vector they take.

What the equations mean (timing, saturation, effects, the cable) is described in
:mod:`falcon_plan.sim.plant`; the batched loops over many periods are in
:mod:`falcon_plan.sim.batch`.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from falcon_plan.model.effects import COULOMB_SMOOTHING_RAD_S, LEG_COULOMB_FIELDS, SMOOTH_EFFECT_FIELDS, Effects
from falcon_plan.model.params import FalconParams
from falcon_plan.model.saturation import saturate
from falcon_plan.model.symbolic import (N_EFFECTS, DynamicsFunctions, dynamics_functions,
                                        motor_torque_per_command)
from falcon_plan.model.workspace import WorkspaceLimits

BACKLASH_CONTACT_STIFFNESS_NM_RAD = 2000.0
"""Stiffness of the slack-taken-up contact when backlash is on but the cable is rigid [N.m/rad]
(about a 0.5 mm steel cable's stiffness at the 56 mm leg radius)."""
CABLE_DAMPING_RATIO = 0.1
"""Damping ratio of the cable mode (motor inertia on the cable spring)."""
SUBSTEPS_RIGID = 1
"""RK4 steps per control period, rigid drive (the slowest mode is ~50 rad/s; see accuracy)."""
SUBSTEPS_COMPLIANT = 6
"""RK4 steps per control period with the cable model (its mode reaches ~2000 rad/s)."""
FRICTION_STEP_PHASE = 4.0
"""Largest h * lambda per RK4 substep for the smoothed friction sign, where lambda [1/s] is its
slope at zero speed, (largest leg friction torque) / (friction_smoothing_rad_s * leg inertia),
h the substep [s]. Above RK4's linear limit (2.78) the tanh saturates, so the speed only
chatters inside its band (a stuck leg stays stuck); measured on the second generator's
stick-slip logs (Coulomb 0.008 N.m, per-leg up to 0.014 N.m, smoothing 0.005-0.001 rad/s, 800 Hz), up
to 4 per substep the held-out replay matched a 12-substep integration to within the sub-count
chaos (0.2 counts RMS), 7.4 left 0.34 counts."""
FRICTION_SUBSTEP_CHOICES = (1, 2, 4)
"""Substep counts :func:`friction_substeps` picks from (each is a compiled plant layout, whose
first use in a process costs 0.3-1 s). (3 was tried for speed, where 4 is now picked: on the
busy-host Stribeck log the replays' chaos, and with it the open-world floor, fell from 0.66 to
0.56 counts, the held-out error after correction rose from 0.81 to 0.92 counts, and the case
was flagged.)"""
END_STOP_MARGIN_RAD = math.radians(5.0)
"""The legs' mechanical end stops sit this far beyond the workspace's leg-angle limits. The
paper gives no stop angles; the real device rests on its stops when no force is applied, so
the plant needs them (without them an unheld device falls out of reach in ~0.2 s)."""
END_STOP_STIFFNESS_NM_RAD = 50.0
"""Contact stiffness of an end stop at the leg pivot [N.m/rad]: 1 deg of penetration takes
0.87 N.m, several times the gravity torque on a leg; its mode (~160 rad/s with the leg's
inertia) stays well inside RK4's accuracy at one step per 800 Hz period."""
END_STOP_DAMPING_RATIO = 0.7
"""Damping ratio of the stop contact (a soft, non-bouncing stop)."""

PLANT_PARAMETERS = ("dt_s", "saturation_static", "command_limit", "release_speed_rad_s",
                    "stiffness_Nm_rad", "damping_Nms_rad", "half_backlash_rad",
                    "stop_low_rad", "stop_high_rad", "stop_stiffness_Nm_rad", "stop_damping_Nms_rad",
                    "force_x_N", "force_y_N", "force_z_N")
"""Order of the plant parameter vector ``pp`` (runtime inputs of the compiled functions); the
last three are an external force at the grip [N, base frame] (a push, for disturbance tests;
zero by default)."""


def plant_parameters(layout: PlantLayout, effects: Effects, *, dt_s: float, saturation: bool,
                     release_speed_rad_s: float, external_force_N: tuple[float, float, float] = (0.0, 0.0, 0.0)
                     ) -> np.ndarray:
    """The runtime parameter vector ``pp`` (order :data:`PLANT_PARAMETERS`) of a plant.

    ``layout``: parameter set and workspace limits (the end stops sit
    :data:`END_STOP_MARGIN_RAD` beyond its leg-angle limits); ``effects``: the simulated
    device's effects (cable stiffness, backlash); ``dt_s``: control period [s];
    ``saturation``: apply the static saturation rule (else only the command limit);
    ``release_speed_rad_s``: motor speed [rad/s, leg units] above which the full command
    limit is available; ``external_force_N``: a constant force at the grip [N, base frame]."""
    params, limits = layout.params, layout.limits
    stiffness = effects.cable_stiffness_Nm_rad
    if not math.isfinite(stiffness):
        stiffness = BACKLASH_CONTACT_STIFFNESS_NM_RAD
    motor_inertia = params.motor_inertia_kgm2 * params.drive_ratio ** 2
    values = {
        "dt_s": dt_s,
        "saturation_static": float(params.command_saturation if saturation else params.command_limit),
        "command_limit": float(params.command_limit),
        "release_speed_rad_s": float(release_speed_rad_s),
        "stiffness_Nm_rad": stiffness,
        "damping_Nms_rad": 2.0 * CABLE_DAMPING_RATIO * math.sqrt(stiffness * motor_inertia),
        "half_backlash_rad": 0.5 * effects.backlash_rad,
        "stop_low_rad": limits.theta1_min_rad - END_STOP_MARGIN_RAD,
        "stop_high_rad": limits.theta1_max_rad + END_STOP_MARGIN_RAD,
        "stop_stiffness_Nm_rad": END_STOP_STIFFNESS_NM_RAD,
        "stop_damping_Nms_rad": 2.0 * END_STOP_DAMPING_RATIO * math.sqrt(
            END_STOP_STIFFNESS_NM_RAD * params.leg_inertia_about_pivot_kgm2),
        "force_x_N": float(external_force_N[0]),
        "force_y_N": float(external_force_N[1]),
        "force_z_N": float(external_force_N[2]),
    }
    return np.array([values[name] for name in PLANT_PARAMETERS])


def friction_substeps(effects: Effects, params: FalconParams, rate_hz: float) -> int:
    """RK4 substeps per control period that keep the smoothed friction sign of ``effects``
    stable and accurate at ``rate_hz`` [Hz]: the smallest of :data:`FRICTION_SUBSTEP_CHOICES`
    with at most :data:`FRICTION_STEP_PHASE` per substep (the largest if none). The leg inertia
    is a lower bound (leg body about its pivot plus the reflected motor, no closed-chain
    share), so the count errs on the safe side. :data:`SUBSTEPS_RIGID` with no friction or a
    smoothing at or above the default (the plant's behaviour there is unchanged).
    ``params`` the parameter set (inertias)."""
    if effects.friction_smoothing_rad_s >= COULOMB_SMOOTHING_RAD_S:
        return SUBSTEPS_RIGID
    legs = np.array([getattr(effects, f) for f in LEG_COULOMB_FIELDS])
    torque = effects.coulomb_Nm + effects.stribeck_Nm + float(legs.max())
    inertia = params.leg_inertia_about_pivot_kgm2 + params.motor_inertia_kgm2 * params.drive_ratio ** 2
    slope = torque / (effects.friction_smoothing_rad_s * inertia)
    needed = slope / (rate_hz * FRICTION_STEP_PHASE)
    return next((n for n in FRICTION_SUBSTEP_CHOICES if n >= needed), max(FRICTION_SUBSTEP_CHOICES))


@dataclass(frozen=True)
class PlantLayout:
    """Everything the compiled code depends on (effect values and timing are runtime inputs):
    the device's parameter set ``params``, its workspace ``limits`` (where the end stops
    sit), ``compliant`` (the cable model's extra motor states) and ``substeps`` (RK4 steps
    per control period)."""

    params: FalconParams
    limits: WorkspaceLimits
    compliant: bool
    substeps: int

    @property
    def n_states(self) -> int:
        """p, v (6) for a rigid drive; p, v, q_m, w_m (12) with the cable model."""
        return 12 if self.compliant else 6


def _pp(pp: ca.SX, name: str) -> ca.SX:
    return pp[PLANT_PARAMETERS.index(name)]


def _saturate(tc: ca.SX, speed: ca.SX, pp: ca.SX) -> ca.SX:
    """The command acting on the motors: clipped to +-L(|speed|) (module docstring, step 2)."""
    return saturate(tc, speed, _pp(pp, "saturation_static"), _pp(pp, "command_limit"),
                    _pp(pp, "release_speed_rad_s"))


def _end_stop_torque(theta1: ca.SX, w_leg: ca.SX, pp: ca.SX) -> ca.SX:
    """Torque of the mechanical end stops on each leg [N.m] (theta1 sense): a one-sided
    spring-damper beyond [stop_low, stop_high] that pushes back and never pulls."""
    k, c = _pp(pp, "stop_stiffness_Nm_rad"), _pp(pp, "stop_damping_Nms_rad")
    over = theta1 - _pp(pp, "stop_high_rad")
    under = _pp(pp, "stop_low_rad") - theta1
    push_down = ca.if_else(over > 0, ca.fmax(k * over + c * w_leg, 0.0), 0.0)
    push_up = ca.if_else(under > 0, ca.fmax(k * under - c * w_leg, 0.0), 0.0)
    return push_up - push_down


class _Symbolic:
    """The SX pieces of one layout: the right-hand side, one RK4 period and the encoder map."""

    def __init__(self, layout: PlantLayout) -> None:
        self.layout = layout
        params = layout.params
        leg_params = params.replace(motor_inertia_kgm2=0.0) if layout.compliant else params
        self.fns: DynamicsFunctions = dynamics_functions(leg_params, layout.limits)
        self.motor_inertia = params.motor_inertia_kgm2 * params.drive_ratio ** 2

    def rhs(self, x: ca.SX, tc: ca.SX, eff: ca.SX, pp: ca.SX) -> ca.SX:
        """dx/dt with the motor command tc (after saturation) held."""
        fns, p, v = self.fns, x[0:3], x[3:6]
        theta1 = fns.leg_angles(p, eff)[0]
        w_leg = fns.jacobian(p, eff) @ v
        tau_stop = _end_stop_torque(theta1, w_leg, pp)
        # an external force F at the grip acts at the pivots as J^-T F
        force = ca.vertcat(_pp(pp, "force_x_N"), _pp(pp, "force_y_N"), _pp(pp, "force_z_N"))
        tau_stop = tau_stop + ca.solve(fns.jacobian(p, eff).T, force)
        if not self.layout.compliant:
            tau_motor = motor_torque_per_command(w_leg, eff, self.layout.params) * tc
            return ca.vertcat(v, fns.forward_dynamics_torque(p, v, tau_motor + tau_stop, eff))
        params = self.layout.params
        qm, wm = x[6:9], x[9:12]
        delta = qm - theta1
        half = _pp(pp, "half_backlash_rad")
        taken_up = ca.fabs(delta) >= half
        stretch = delta - ca.fmin(ca.fmax(delta, -half), half)
        tau_cable = ca.if_else(taken_up, _pp(pp, "stiffness_Nm_rad") * stretch
                               + _pp(pp, "damping_Nms_rad") * (wm - w_leg), 0.0)
        # the motor law at the motor's own speed (the cable lets it differ from theta1 rate)
        tau_motor = motor_torque_per_command(wm, eff, params) * tc
        accel = fns.forward_dynamics_torque(p, v, tau_cable + tau_stop, eff)
        return ca.vertcat(v, accel, wm, (tau_motor - tau_cable) / self.motor_inertia)

    def encoder(self, x: ca.SX, eff: ca.SX) -> tuple[ca.SX, ca.SX]:
        """(fractional encoder counts of the motor angle, leg angles theta1 [rad]); the counts
        start at the true home angle, theta_home + the encoder-offset effect."""
        params = self.layout.params
        theta1 = self.fns.leg_angles(x[0:3], eff)[0]
        motor = x[6:9] if self.layout.compliant else theta1
        home = params.theta_home_rad + eff[SMOOTH_EFFECT_FIELDS.index("encoder_offset_rad")]
        return (motor - home) * params.counts_per_rad, theta1

    def motor_speed(self, x: ca.SX, eff: ca.SX) -> ca.SX:
        """Motor speeds in leg units [rad/s] (theta1 rate for a rigid drive)."""
        if self.layout.compliant:
            return x[9:12]
        return self.fns.jacobian(x[0:3], eff) @ x[3:6]

    def period(self, x: ca.SX, tc: ca.SX, eff: ca.SX, pp: ca.SX) -> tuple[ca.SX, ca.SX]:
        """(state after one control period [dt_s], motor command): the saturation limit is
        set from the motor speed at the start of the period (the firmware samples it), then
        RK4 with ``substeps`` steps under that command held."""
        tc = _saturate(tc, self.motor_speed(x, eff), pp)
        h = _pp(pp, "dt_s") / self.layout.substeps
        for _ in range(self.layout.substeps):
            k1 = self.rhs(x, tc, eff, pp)
            k2 = self.rhs(x + 0.5 * h * k1, tc, eff, pp)
            k3 = self.rhs(x + 0.5 * h * k2, tc, eff, pp)
            k4 = self.rhs(x + h * k3, tc, eff, pp)
            x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return x, tc


@dataclass(frozen=True)
class PlantFunctions:
    """CasADi Functions of one layout (all take ``eff`` and ``pp`` as inputs).

    - ``rhs(x, tc, eff, pp) -> dx`` (the ODE, for references such as solve_ivp)
    - ``encoder(x, eff) -> (enc, theta1)``: fractional counts of the motor angle, leg angles
    - ``motor_command(x, tc, eff, pp) -> tc_motor``: the acting command after saturation
    - ``period(x, tc, eff, pp) -> (x_next, enc, theta1, tc_motor)``: one control period;
      tc_motor is the command after the saturation rule, held over the period
    """

    layout: PlantLayout
    rhs: ca.Function
    encoder: ca.Function
    motor_command: ca.Function
    period: ca.Function


BUILDING = threading.RLock()
"""Held while a plant's Functions are built or loaded (CasADi's symbolic graphs are not
built safely from two threads; the discrepancy workflow replays side by side)."""


@lru_cache(maxsize=None)
def plant_encoder(layout: PlantLayout) -> ca.Function:
    """The encoder map of ``layout``'s plant, (x, eff) -> (fractional counts, leg angles
    theta1 [rad]): all a plant needs besides its compiled Functions, built without the period
    (whose unrolled RK4 substeps take most of :func:`plant_functions`' time)."""
    sym = _Symbolic(layout)
    x, eff = ca.SX.sym("x", layout.n_states), ca.SX.sym("eff", N_EFFECTS)
    enc, theta = sym.encoder(x, eff)
    return ca.Function("plant_encoder", [x, eff], [enc, theta], ["x", "eff"], ["enc", "theta1"])


@lru_cache(maxsize=None)
def plant_functions(layout: PlantLayout, merged: bool = True) -> PlantFunctions:
    """Build (once per layout) the plant's CasADi Functions; with ``merged`` False the period's
    common subexpressions are left unmerged (same values; ~0.15 s less to build: what names
    and keys a compiled library the first time it is built)."""
    sym = _Symbolic(layout)
    n = layout.n_states
    x, tc = ca.SX.sym("x", n), ca.SX.sym("tc", 3)
    eff, pp = ca.SX.sym("eff", N_EFFECTS), ca.SX.sym("pp", len(PLANT_PARAMETERS))
    x_next, tc_motor = sym.period(x, tc, eff, pp)
    enc_next, theta_next = sym.encoder(x_next, eff)
    # cse merges the dynamics evaluated in the four stages (halves the operation count).
    outs = ca.cse([x_next, enc_next, theta_next, tc_motor]) if merged else [x_next, enc_next, theta_next, tc_motor]
    return PlantFunctions(
        layout=layout,
        rhs=ca.Function("plant_rhs", [x, tc, eff, pp], [sym.rhs(x, tc, eff, pp)],
                        ["x", "tc", "eff", "pp"], ["dx"]),
        encoder=plant_encoder(layout),
        motor_command=ca.Function("plant_motor_command", [x, tc, eff, pp],
                                  [_saturate(tc, sym.motor_speed(x, eff), pp)],
                                  ["x", "tc", "eff", "pp"], ["tc_motor"]),
        period=ca.Function(f"falcon_plant_period_{'c' if layout.compliant else 'r'}",
                           [x, tc, eff, pp], outs, ["x", "tc", "eff", "pp"],
                           ["x_next", "enc", "theta1", "tc_motor"]),
    )
