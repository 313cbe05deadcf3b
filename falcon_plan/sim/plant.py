"""SimPlant: the simulated Falcon, one control period per call.

What happens in one period (rate 800 Hz by default, the paper's simulation; 1 kHz selectable):

1. **Command path.** The command issued now (rounded half up to an integer and clamped to
   +-4096) enters a delay line of ``2 + Effects.extra_delay_samples`` periods (the paper's
   2-sample delay). The command leaving the line reaches the firmware, which holds it until
   a newer one arrives; ``step(None)`` issues nothing, and once no command has arrived for
   ``params.command_hold_s`` (100 ms) the firmware drops the force to zero. Precisely: a
   command that starts acting in period j acts in periods j .. j + H - 1, H = round(0.1 rate),
   unless replaced.
2. **Static saturation** (MODEL-CONVENTIONS "Saturation"; the paper: To stopped growing past
   |Tc| = 2500 in static tests, the limit lifted in motion): the command acting on the motor
   is clipped to +-L(w), the speed-dependent limit defined once in
   :mod:`falcon_plan.model.saturation` (2500 at rest rising smoothly to 4096 above 2 rad/s
   of motor speed in leg units; the planner's ``limit="device"`` uses the same rule). The
   limit is set once per period from the speed at its start (the firmware samples the speed; it
   also keeps the integrand smooth, so RK4 keeps its order). ``saturation=False`` keeps
   only +-4096.
3. **Dynamics.** The model's CasADi equations (:mod:`falcon_plan.model.symbolic`) with its
   smooth-effect vector (friction, payload, motor gain, gravity tilt, Kd sign) and the
   command held constant over the period, integrated by classical RK4 with a fixed number of
   substeps, all in ONE CasADi Function per period, compiled to C (:mod:`.codegen`).
   Mechanical end stops (:data:`END_STOP_MARGIN_RAD` beyond the leg-angle limits) catch a
   leg that is not held, as on the real device.
4. **Encoders** are on the motors: they read the motor angle (equal to theta1 for a rigid
   cable) as whole counts, rounded half up, at the end of the period.

Plant-only effects (:class:`~falcon_plan.model.effects.Effects`):

- ``extra_delay_samples``: a longer delay line.
- ``cable_stiffness_Nm_rad`` (finite) and/or ``backlash_rad`` (> 0) switch to the *compliant*
  drive: three extra motor states q_m, w_m (motor angle and speed expressed at the leg,
  q_m = motor angle / N). The reflected motor inertia J_m = Im N^2 moves from the legs to the
  motors (the leg-side model is built with Im = 0). The cable transmits
  tau_c = k dz(q_m - theta1) + c (w_m - dtheta1/dt) while the slop is taken up
  (|q_m - theta1| >= backlash / 2) and nothing inside the dead band; dz removes the half
  band, k is the cable stiffness (or :data:`BACKLASH_CONTACT_STIFFNESS_NM_RAD` if the cable is
  rigid but slack), c = 2 zeta sqrt(k J_m) with zeta = :data:`CABLE_DAMPING_RATIO` (a cable
  has some structural damping; without it the 300 Hz cable mode would ring forever). The
  motor obeys J_m dw_m/dt = tau_m - tau_c with tau_m = -N gain Tc (Ks - s Kd N w_m); friction
  stays at the leg pivots. Encoders read q_m.

Accuracy: see ``tests/sim/test_plant_accuracy.py`` (RK4 against scipy's DOP853 at rtol 1e-10
over 1 s of the PD step experiment).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np

from falcon_plan.errors import InvalidParameterError, WorkspaceError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import SMOOTH_EFFECT_FIELDS, Effects
from falcon_plan.model.kinematics import forward_kinematics
from falcon_plan.model.params import FalconParams
from falcon_plan.model.saturation import SATURATION_RELEASE_SPEED_RAD_S, saturate
from falcon_plan.model.symbolic import (N_EFFECTS, DynamicsFunctions, dynamics_functions,
                                        motor_torque_per_command)
from falcon_plan.model.workspace import WorkspaceLimits
from falcon_plan.compiled import BufferedFunction, build_library
from falcon_plan.control import EncoderPD, pd_law

BACKLASH_CONTACT_STIFFNESS_NM_RAD = 2000.0
"""Stiffness of the slack-taken-up contact when backlash is on but the cable is rigid [N.m/rad]
(about a 0.5 mm steel cable's stiffness at the 56 mm leg radius)."""
CABLE_DAMPING_RATIO = 0.1
"""Damping ratio of the cable mode (motor inertia on the cable spring)."""
SUBSTEPS_RIGID = 1
"""RK4 steps per control period, rigid drive (the slowest mode is ~50 rad/s; see accuracy)."""
SUBSTEPS_COMPLIANT = 6
"""RK4 steps per control period with the cable model (its mode reaches ~2000 rad/s)."""
BATCH_CHUNK = 200
"""Periods per call of the compiled batched functions."""

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
                    "stop_low_rad", "stop_high_rad", "stop_stiffness_Nm_rad", "stop_damping_Nms_rad")
"""Order of the plant parameter vector ``pp`` (runtime inputs of the compiled functions)."""
PD_PARAMETERS = ("kp", "kd", "alpha", "rate_hz", "limit")


def _round_half_up(x: Any) -> Any:
    return np.floor(np.asarray(x, dtype=float) + 0.5)


# --- the symbolic period ---------------------------------------------------------------------

@dataclass(frozen=True)
class PlantLayout:
    """Everything the compiled code depends on (effect values and timing are runtime inputs)."""

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

    def open_loop_chunk(self) -> ca.Function:
        """``BATCH_CHUNK`` periods under given active commands (mapaccum of ``period``):
        (x0, TC (3, B), eff, pp) -> (X (n, B), ENC (3, B), THETA1 (3, B))."""
        return _open_loop_chunk(self.layout)

    def pd_chunk(self, delay_samples: int) -> ca.Function:
        """``BATCH_CHUNK`` periods of the encoder PD closed loop with a command delay line of
        ``delay_samples`` (see :meth:`SimPlant.run_pd`)."""
        return _pd_chunk(self.layout, delay_samples)


@lru_cache(maxsize=None)
def plant_functions(layout: PlantLayout) -> PlantFunctions:
    """Build (once per layout) the plant's CasADi Functions."""
    sym = _Symbolic(layout)
    n = layout.n_states
    x, tc = ca.SX.sym("x", n), ca.SX.sym("tc", 3)
    eff, pp = ca.SX.sym("eff", N_EFFECTS), ca.SX.sym("pp", len(PLANT_PARAMETERS))
    x_next, tc_motor = sym.period(x, tc, eff, pp)
    enc_next, theta_next = sym.encoder(x_next, eff)
    enc, theta = sym.encoder(x, eff)
    # cse merges the dynamics evaluated in the four stages (halves the operation count).
    outs = ca.cse([x_next, enc_next, theta_next, tc_motor])
    return PlantFunctions(
        layout=layout,
        rhs=ca.Function("plant_rhs", [x, tc, eff, pp], [sym.rhs(x, tc, eff, pp)],
                        ["x", "tc", "eff", "pp"], ["dx"]),
        encoder=ca.Function("plant_encoder", [x, eff], [enc, theta], ["x", "eff"], ["enc", "theta1"]),
        motor_command=ca.Function("plant_motor_command", [x, tc, eff, pp],
                                  [_saturate(tc, sym.motor_speed(x, eff), pp)],
                                  ["x", "tc", "eff", "pp"], ["tc_motor"]),
        period=ca.Function(f"falcon_plant_period_{'c' if layout.compliant else 'r'}",
                           [x, tc, eff, pp], outs, ["x", "tc", "eff", "pp"],
                           ["x_next", "enc", "theta1", "tc_motor"]),
    )


# The batched functions loop over BATCH_CHUNK periods with mapaccum. Their wrappers are MX, so
# the generated C keeps the loop (an SX wrapper would unroll 200 copies of the period).

@lru_cache(maxsize=None)
def _open_loop_chunk(layout: PlantLayout) -> ca.Function:
    fns = plant_functions(layout)
    n, b = layout.n_states, BATCH_CHUNK
    eff, pp = ca.MX.sym("eff", N_EFFECTS), ca.MX.sym("pp", len(PLANT_PARAMETERS))
    x0, tcs = ca.MX.sym("x0", n), ca.MX.sym("tc", 3, b)
    acc = fns.period.mapaccum("plant_open_loop_acc", b, [0], [0])
    xs, enc, theta, _ = acc(x0, tcs, eff, pp)
    return ca.Function(f"falcon_plant_open_loop_{_tag(layout)}", [x0, tcs, eff, pp],
                       [xs, enc, theta], ["x0", "tc", "eff", "pp"], ["x", "enc", "theta1"])


def _tag(layout: PlantLayout) -> str:
    return "c" if layout.compliant else "r"


@lru_cache(maxsize=None)
def _pd_chunk(layout: PlantLayout, d: int) -> ca.Function:
    """One PD period on z = [x, v_filtered, n_prev, delay line (3 d)] with per-step ref and
    ff, looped over BATCH_CHUNK periods."""
    fns = plant_functions(layout)
    n, b = layout.n_states, BATCH_CHUNK
    eff, pp = ca.MX.sym("eff", N_EFFECTS), ca.MX.sym("pp", len(PLANT_PARAMETERS))
    z = ca.SX.sym("z", n + 6 + 3 * d)
    ref, ff = ca.SX.sym("ref", 3), ca.SX.sym("ff", 3)
    eff_s, pp_s = ca.SX.sym("eff", N_EFFECTS), ca.SX.sym("pp", len(PLANT_PARAMETERS))
    gains = ca.SX.sym("gains", len(PD_PARAMETERS))
    x, v, n_prev, line = z[0:n], z[n:n + 3], z[n + 3:n + 6], z[n + 6:]
    enc, _ = fns.encoder(x, eff_s)
    counts = ca.floor(enc + 0.5)
    g = {name: gains[i] for i, name in enumerate(PD_PARAMETERS)}
    tc, v_new = pd_law(counts, n_prev, v, ref, ff, g["kp"], g["kd"], g["alpha"], g["rate_hz"],
                       g["limit"], ops=_CASADI_OPS)
    x_next = fns.period(x, line[0:3], eff_s, pp_s)[0]
    z_next = ca.vertcat(x_next, v_new, counts, line[3:], tc)
    step = ca.Function("plant_pd_period", [z, ref, ff, eff_s, pp_s, gains], [z_next, counts, tc])
    acc = step.mapaccum("plant_pd_acc", b, [0], [0])
    z0 = ca.MX.sym("z0", z.numel())
    refs, ffs = ca.MX.sym("ref", 3, b), ca.MX.sym("ff", 3, b)
    gains_mx = ca.MX.sym("gains", len(PD_PARAMETERS))
    zs, counts_out, tcs_out = acc(z0, refs, ffs, eff, pp, gains_mx)
    return ca.Function(f"falcon_plant_pd_{_tag(layout)}_d{d}", [z0, refs, ffs, eff, pp, gains_mx],
                       [zs, counts_out, tcs_out], ["z0", "ref", "ff", "eff", "pp", "gains"],
                       ["z", "counts", "tc"])


_CASADI_OPS = SimpleNamespace(floor=ca.floor, fmin=ca.fmin, fmax=ca.fmax)


def _function(layout: PlantLayout, kind: str, delay_samples: int) -> ca.Function:
    if kind == "period":
        return plant_functions(layout).period
    if kind == "open_loop":
        return _open_loop_chunk(layout)
    return _pd_chunk(layout, delay_samples)


@lru_cache(maxsize=None)
def _library(layout: PlantLayout, kind: str, delay_samples: int) -> Path | None:
    """The compiled shared object of a plant function (built once per machine, then found)."""
    return build_library(_function(layout, kind, delay_samples))


# --- the firmware ----------------------------------------------------------------------------

class _Firmware:
    """Delay line + command hold: turns issued commands (or None) into acting commands."""

    def __init__(self, delay: int, hold_periods: int) -> None:
        self.delay, self.hold = delay, hold_periods
        self.queue: deque[np.ndarray | None] = deque([None] * delay)
        self.latched = np.zeros(3)
        self.since = hold_periods  # nothing received yet: no force

    def push(self, issued: np.ndarray | None) -> np.ndarray:
        """Issue a command now (None: nothing); return the command acting in this period."""
        self.queue.append(issued)
        arrived = self.queue.popleft()
        if arrived is not None:
            self.latched, self.since = arrived, 0
        else:
            self.since += 1
        return self.latched if self.since < self.hold else _ZERO3

    def peek(self, i: int) -> np.ndarray:
        """The command that will act i periods from now if only None is issued meanwhile
        (i < delay: already decided by the queue)."""
        latched, since = self.latched, self.since
        for item in list(self.queue)[:i + 1]:
            latched, since = (item, 0) if item is not None else (latched, since + 1)
        return latched if since < self.hold else _ZERO3

    def after_commands(self, issued: np.ndarray, actives: np.ndarray) -> None:
        """State after a batch that issued a command every period (rows of ``issued``), whose
        acting commands were ``actives`` (same shape)."""
        k = issued.shape[0]
        if k == 0:
            return
        if k <= self.delay:
            for row in issued:
                self.push(row.copy())
            return
        self.queue = deque(row.copy() for row in issued[k - self.delay:])
        self.latched, self.since = actives[-1].copy(), 0


_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)


# --- the plant -------------------------------------------------------------------------------

@dataclass(frozen=True)
class PDRun:
    """Result of :meth:`SimPlant.run_pd`: per period k, the counts read at its start and the
    command issued from them (what a falcon log row holds), shapes (K, 3) int64."""

    t_s: np.ndarray
    counts: np.ndarray
    commands: np.ndarray


class SimPlant:
    """The simulated Falcon (see the module docstring for the timing, saturation and effects).

    Parameters
    ----------
    model : the model whose dynamics and smooth effects are simulated (nominal acra2009 if
        None).
    rate_hz : control rate [Hz], 800 (the paper's simulation) or e.g. 1000.
    effects : effects of the simulated device (default ``model.effects``); the smooth ones
        replace the model's in the dynamics, the plant-only ones are implemented here.
    saturation : apply the static saturation rule (else only the +-4096 clamp).
    seed : accepted for the Device contract; the plant is deterministic (no noise yet).
    compile : compile the per-period Function to C (default); False runs CasADi directly.
    substeps : RK4 steps per period (default :data:`SUBSTEPS_RIGID` / :data:`SUBSTEPS_COMPLIANT`).
    """

    def __init__(self, model: FalconModel | None = None, *, rate_hz: float = 800.0,
                 effects: Effects | None = None, saturation: bool = True, seed: int | None = None,
                 compile: bool = True, substeps: int | None = None,
                 release_speed_rad_s: float = SATURATION_RELEASE_SPEED_RAD_S) -> None:
        self.model = model if model is not None else FalconModel()
        self.effects = effects if effects is not None else self.model.effects
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidParameterError(f"rate_hz must be a positive number [Hz], got {rate_hz}")
        if not release_speed_rad_s > 0:
            raise InvalidParameterError("release_speed_rad_s must be > 0")
        params = self.model.params
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.saturation = saturation
        self.seed = seed
        compliant = self.effects.backlash_rad > 0 or math.isfinite(self.effects.cable_stiffness_Nm_rad)
        if substeps is None:
            substeps = SUBSTEPS_COMPLIANT if compliant else SUBSTEPS_RIGID
        if int(substeps) != substeps or substeps < 1:
            raise InvalidParameterError(f"substeps must be a whole number >= 1, got {substeps}")
        self.layout = PlantLayout(params, self.model.limits, compliant, int(substeps))
        self.delay_samples = params.command_delay_samples + int(self.effects.extra_delay_samples)
        """Periods between issuing a command and its acting (2 + the extra-delay effect)."""
        self.functions = plant_functions(self.layout)
        stiffness = self.effects.cable_stiffness_Nm_rad
        if not math.isfinite(stiffness):
            stiffness = BACKLASH_CONTACT_STIFFNESS_NM_RAD
        motor_inertia = params.motor_inertia_kgm2 * params.drive_ratio ** 2
        values = {
            "dt_s": self.dt_s,
            "saturation_static": float(params.command_saturation if saturation else params.command_limit),
            "command_limit": float(params.command_limit),
            "release_speed_rad_s": float(release_speed_rad_s),
            "stiffness_Nm_rad": stiffness,
            "damping_Nms_rad": 2.0 * CABLE_DAMPING_RATIO * math.sqrt(stiffness * motor_inertia),
            "half_backlash_rad": 0.5 * self.effects.backlash_rad,
            "stop_low_rad": self.model.limits.theta1_min_rad - END_STOP_MARGIN_RAD,
            "stop_high_rad": self.model.limits.theta1_max_rad + END_STOP_MARGIN_RAD,
            "stop_stiffness_Nm_rad": END_STOP_STIFFNESS_NM_RAD,
            "stop_damping_Nms_rad": 2.0 * END_STOP_DAMPING_RATIO * math.sqrt(
                END_STOP_STIFFNESS_NM_RAD * params.leg_inertia_about_pivot_kgm2),
        }
        self._pp = np.array([values[name] for name in PLANT_PARAMETERS])
        self._eff = self.effects.smooth_vector()
        self._compile = compile
        self._period = self._buffered("period")
        self._period.inputs[2][:] = self._eff
        self._period.inputs[3][:] = self._pp
        self._batch: dict[str, BufferedFunction] = {}
        self.hold_periods = max(1, int(round(params.command_hold_s * self.rate_hz)))
        self.reset()

    def _buffered(self, kind: str) -> BufferedFunction:
        d = self.delay_samples if kind == "pd" else 0
        library = _library(self.layout, kind, d) if self._compile else None
        return BufferedFunction(_function(self.layout, kind, d), library=library)

    @property
    def compiled(self) -> bool:
        """True when the per-period step runs compiled C."""
        return self._period.compiled

    # --- state -------------------------------------------------------------------------------
    def reset(self, position_m: Any = None, velocity_m_s: Any = (0.0, 0.0, 0.0), *,
              commands: Any = None) -> None:
        """Put the device at rest (or moving) at a point [m] (default: home, counts 0), time 0,
        the cable (if modelled) relaxed, slop centred. By default no command is pending or
        acting; ``commands`` (3 numbers) means they were issued every period until now (so
        they act from the first period, e.g. the commands that hold a PD's equilibrium)."""
        if position_m is None:
            p = forward_kinematics(np.full(3, self.model.params.theta_home_rad), self.model.params)
        else:
            p = np.asarray(position_m, dtype=float)
        v = np.asarray(velocity_m_s, dtype=float)
        if p.shape != (3,) or v.shape != (3,) or not (np.isfinite(p).all() and np.isfinite(v).all()):
            raise InvalidParameterError(f"position_m and velocity_m_s must be 3 finite numbers [m, m/s], "
                                        f"got {position_m!r}, {velocity_m_s!r}")
        x = np.zeros(self.layout.n_states)
        x[0:3], x[3:6] = p, v
        enc, theta1 = self.functions.encoder(x, self._eff)
        theta1 = np.asarray(theta1).ravel()
        if not np.isfinite(theta1).all():
            raise InvalidParameterError(f"position {p.tolist()} m is not reachable")
        if self.layout.compliant:
            jac = np.asarray(self.model.functions.jacobian(p, self._eff))
            x[6:9], x[9:12] = theta1, jac @ v
            enc, theta1 = self.functions.encoder(x, self._eff)
        self._x = self._period.inputs[0]
        self._x[:] = x
        self._set_reading(np.asarray(enc).ravel(), theta1)
        self._k = 0
        self._acting = np.zeros(3)
        self._motor_command = np.zeros(3)
        self._firmware = _Firmware(self.delay_samples, self.hold_periods)
        issued = self._issue(commands)
        if issued is not None:
            self._firmware.queue = deque(issued.copy() for _ in range(self.delay_samples))
            self._firmware.latched, self._firmware.since = issued, 0
            self._acting = issued.copy()

    def _set_reading(self, enc: Any, theta1: Any) -> None:
        self._theta1 = np.array(theta1, dtype=float).ravel()
        self._counts = np.floor(np.asarray(enc, dtype=float).ravel() + 0.5).astype(np.int64)

    @property
    def time_s(self) -> float:
        """Simulated time [s] since the last reset."""
        return self._k * self.dt_s

    @property
    def position_m(self) -> np.ndarray:
        """True end-effector point [m] (base frame)."""
        return self._x[0:3].copy()

    @property
    def velocity_m_s(self) -> np.ndarray:
        """True end-effector velocity [m/s]."""
        return self._x[3:6].copy()

    @property
    def theta1_rad(self) -> np.ndarray:
        """True leg angles theta1 [rad]."""
        return self._theta1.copy()

    @property
    def motor_angle_rad(self) -> np.ndarray:
        """Motor angles in leg units [rad] (what the encoders see; theta1 for a rigid drive)."""
        return self._x[6:9].copy() if self.layout.compliant else self._theta1.copy()

    @property
    def counts(self) -> np.ndarray:
        """Encoder counts now (int64, (3,)), whole counts rounded half up."""
        return self._counts.copy()

    @property
    def acting_commands(self) -> np.ndarray:
        """The command the firmware applied in the period that just ran (before saturation)."""
        return self._acting.copy()

    @property
    def motor_commands(self) -> np.ndarray:
        """The command that drove the motors in the period that just ran, after the static
        saturation rule (per-step API only; NaN after a batched run)."""
        return self._motor_command.copy()

    # --- stepping ----------------------------------------------------------------------------
    def _issue(self, commands: Any) -> np.ndarray | None:
        """Issued commands: rounded half up, clamped to +-``params.command_limit`` (None stays None)."""
        if commands is None:
            return None
        # plain floats: several times cheaper than numpy for three numbers (the per-step path)
        try:
            c0, c1, c2 = (float(c) for c in commands)
        except (TypeError, ValueError):
            c0 = c1 = c2 = math.nan
        if not math.isfinite(c0 + c1 + c2):
            raise InvalidParameterError(f"commands must be 3 finite numbers or None, got {commands!r}")
        lim = self.model.params.command_limit
        return np.array([min(max(math.floor(c + 0.5), -lim), lim) for c in (c0, c1, c2)], dtype=float)

    def step(self, commands: Any) -> np.ndarray:
        """Run one control period: issue ``commands`` (3 numbers, rounded and clamped to
        +-4096; None = no command this period) and return the encoder counts (int64, (3,)) read
        at the end of the period."""
        acting = self._firmware.push(self._issue(commands))
        period = self._period
        period.inputs[1][:] = acting
        period()
        x_next, enc, theta1, motor = period.outputs
        if not math.isfinite(enc[0] + enc[1] + enc[2] + x_next[3] + x_next[4] + x_next[5]):
            self._left_workspace(self._x)
        self._x[:] = x_next
        self._acting = acting
        self._motor_command = motor.copy()
        self._k += 1
        self._set_reading(enc, theta1)
        return self._counts.copy()

    def run_open_loop(self, commands: Any) -> np.ndarray:
        """Batched :meth:`step`: issue row k of ``commands`` (K, 3) in period k (a row of NaN
        = no command) and return the counts read at the end of every period, (K, 3) int64.
        Same result as K calls of :meth:`step`, in a few compiled calls."""
        rows = np.asarray(commands, dtype=float)
        if rows.ndim != 2 or rows.shape[1] != 3:
            raise InvalidParameterError(f"commands must have shape (K, 3), got {rows.shape}")
        missing = np.isnan(rows).all(axis=1)
        if np.isnan(rows[~missing]).any() or np.isinf(rows).any():
            raise InvalidParameterError("commands rows must be finite, or all NaN for 'no command'")
        if rows.shape[0] == 0:
            return np.zeros((0, 3), dtype=np.int64)
        lim = self.model.params.command_limit
        issued = np.clip(np.floor(rows + 0.5), -lim, lim)
        push = self._firmware.push
        actives = np.array([push(None if missing[k] else issued[k]) for k in range(len(rows))])
        states, enc, theta = self._run_chunks("open_loop", self._x, [actives.T], [])
        self._check_batch(states, enc)
        self._advance(states[:, -1], enc[:, -1], theta[:, -1], actives[-1], len(rows))
        return _round_half_up(enc.T).astype(np.int64)

    def run_pd(self, controller: EncoderPD, ref_counts: Any, feedforward: Any = None) -> PDRun:
        """Batched closed loop, exactly equivalent to::

            for k in range(K):
                tc = controller.update(counts, ref_counts[k], feedforward[k])
                counts = plant.step(tc)

        compiled into C (the PD arithmetic is :func:`~falcon_plan.control.pd_law` in
        both). ``ref_counts`` (K, 3) [counts], ``feedforward`` (K, 3) [command units] or None.
        The controller's filter state is updated. Returns the counts read at the start of
        each period and the commands issued then (what falcon-log rows hold)."""
        refs = np.asarray(ref_counts, dtype=float)
        ffs = np.zeros_like(refs) if feedforward is None else np.asarray(feedforward, dtype=float)
        if refs.ndim != 2 or refs.shape[1] != 3 or ffs.shape != refs.shape:
            raise InvalidParameterError(f"ref_counts and feedforward must have shape (K, 3), got "
                                        f"{refs.shape} and {ffs.shape}")
        if not (np.isfinite(refs).all() and np.isfinite(ffs).all()):
            raise InvalidParameterError("ref_counts and feedforward must be finite")
        if abs(controller.rate_hz - self.rate_hz) > 1e-9 * self.rate_hz:
            raise InvalidParameterError(f"controller rate {controller.rate_hz} Hz differs from the "
                                        f"plant's {self.rate_hz} Hz")
        k_total, d, n = refs.shape[0], self.delay_samples, self.layout.n_states
        t = (self._k + np.arange(k_total)) * self.dt_s
        if k_total == 0:
            return PDRun(t, np.zeros((0, 3), np.int64), np.zeros((0, 3), np.int64))
        # The first d acting commands are already decided by what is queued now.
        pending = np.array([self._firmware.peek(i) for i in range(d)])
        n_prev = self._counts.astype(float) if controller.n_prev is None else controller.n_prev
        z0 = np.concatenate([self._x, controller.velocity_counts_s, n_prev, pending.ravel()])
        gains = np.array([controller.kp, controller.kd, controller.alpha, controller.rate_hz,
                          float(controller.limit)])
        zs, counts, tcs = self._run_chunks("pd", z0, [refs.T, ffs.T], [gains])
        self._check_batch(zs[:n], counts)
        controller.n_prev = counts[:, -1].copy()
        controller.velocity_counts_s = zs[n:n + 3, -1].copy()
        enc, theta = self._encoder_at(zs[:n, -1])
        actives = np.vstack([pending, tcs.T])[:k_total]
        self._firmware.after_commands(tcs.T, actives)
        self._advance(zs[:n, -1], enc, theta, actives[-1], k_total)
        return PDRun(t_s=t, counts=counts.T.astype(np.int64), commands=tcs.T.astype(np.int64))

    def _left_workspace(self, x: np.ndarray) -> None:
        raise WorkspaceError(
            f"the simulated device left the reachable workspace during the period after "
            f"t = {self.time_s:.4f} s (last position {np.round(x[0:3], 5).tolist()} m): the state "
            "is no longer finite (a force far beyond the device's range?); reset() it")

    def _advance(self, x: np.ndarray, enc: np.ndarray, theta1: np.ndarray, acting: np.ndarray,
                 periods: int) -> None:
        self._x[:] = x
        self._k += periods
        self._acting = np.array(acting, dtype=float)
        self._motor_command = np.full(3, np.nan)
        self._set_reading(enc, theta1)

    def _check_batch(self, states: np.ndarray, enc: np.ndarray) -> None:
        bad = ~(np.isfinite(states).all(axis=0) & np.isfinite(enc).all(axis=0))
        if bad.any():
            k = int(np.argmax(bad))
            self._k += k
            self._left_workspace(states[:, k - 1] if k else self._x)

    def _encoder_at(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        enc, theta = self.functions.encoder(x, self._eff)
        return np.asarray(enc).ravel(), np.asarray(theta).ravel()

    def _run_chunks(self, kind: str, z0: np.ndarray, per_step: list[np.ndarray],
                    constants: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Run a chunked compiled function (inputs: z0, per-step arrays (3, K)..., eff, pp,
        constants...) over all K columns; returns its three outputs, each (rows, K)."""
        fn = self._batch_function(kind)
        k_total = per_step[0].shape[1]
        n_step = len(per_step)
        fn.inputs[n_step + 1][:] = self._eff
        fn.inputs[n_step + 2][:] = self._pp
        for j, value in enumerate(constants):
            fn.inputs[n_step + 3 + j][:] = value
        outs: list[list[np.ndarray]] = [[], [], []]
        z = np.array(z0, dtype=float)
        for start in range(0, k_total, BATCH_CHUNK):
            used = min(BATCH_CHUNK, k_total - start)
            fn.inputs[0][:] = z
            for i, arr in enumerate(per_step):
                fn.inputs[1 + i][:, :used] = arr[:, start:start + used]
                fn.inputs[1 + i][:, used:] = arr[:, start + used - 1:start + used]
            fn()
            for j in range(3):
                outs[j].append(fn.outputs[j][:, :used].copy())
            z = fn.outputs[0][:, used - 1].copy()
        return np.hstack(outs[0]), np.hstack(outs[1]), np.hstack(outs[2])

    def _batch_function(self, kind: str) -> BufferedFunction:
        if kind not in self._batch:
            self._batch[kind] = self._buffered(kind)
        return self._batch[kind]


__all__ = ["SimPlant", "PDRun", "PlantLayout", "PlantFunctions", "plant_functions",
           "SATURATION_RELEASE_SPEED_RAD_S", "BACKLASH_CONTACT_STIFFNESS_NM_RAD",
           "CABLE_DAMPING_RATIO", "END_STOP_MARGIN_RAD", "SUBSTEPS_RIGID", "SUBSTEPS_COMPLIANT", "PLANT_PARAMETERS"]
