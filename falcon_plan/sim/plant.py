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
   substeps, all in ONE CasADi Function per period (:mod:`falcon_plan.sim.equations`), compiled to C
   (:mod:`falcon_plan.compiled`).
   Mechanical end stops (:data:`~falcon_plan.sim.equations.END_STOP_MARGIN_RAD` beyond the leg-angle limits) catch a
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
  band, k is the cable stiffness (or :data:`~falcon_plan.sim.equations.BACKLASH_CONTACT_STIFFNESS_NM_RAD` if the cable is
  rigid but slack), c = 2 zeta sqrt(k J_m) with zeta = :data:`~falcon_plan.sim.equations.CABLE_DAMPING_RATIO` (a cable
  has some structural damping; without it the 300 Hz cable mode would ring forever). The
  motor obeys J_m dw_m/dt = tau_m - tau_c with tau_m = -N gain Tc (Ks - s Kd N w_m); friction
  stays at the leg pivots. Encoders read q_m.

The parts, one job each: :mod:`falcon_plan.sim.equations` (right-hand side, RK4 period,
parameter vector), :mod:`falcon_plan.sim.firmware` (delay line, command hold),
:mod:`falcon_plan.sim.batch` (many periods per compiled call) and this module (the plant's
state and its per-period and batched API).

Accuracy: see ``tests/sim/test_plant_accuracy.py`` (RK4 against scipy's DOP853 at rtol 1e-10
over 1 s of the PD step experiment).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from falcon_plan.compiled import BufferedFunction
from falcon_plan.control import EncoderPD, PDRun
from falcon_plan.errors import InvalidParameterError, WorkspaceError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import forward_kinematics
from falcon_plan.model.saturation import SATURATION_RELEASE_SPEED_RAD_S
from falcon_plan.sim.batch import buffered_plant_function, run_chunks
from falcon_plan.sim.equations import (BUILDING, PLANT_PARAMETERS, SUBSTEPS_COMPLIANT, SUBSTEPS_RIGID, PlantFunctions,
                                       PlantLayout, friction_substeps, plant_encoder, plant_functions, plant_parameters)
from falcon_plan.sim.firmware import Firmware


def _round_half_up(x: Any) -> Any:
    return np.floor(np.asarray(x, dtype=float) + 0.5)


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
    substeps : RK4 steps per period (default :data:`SUBSTEPS_RIGID` / :data:`SUBSTEPS_COMPLIANT`,
        or more for a friction sharper than the default smoothing: :func:`friction_substeps`).
    release_speed_rad_s : motor speed [rad/s, leg units] above which the saturation rule
        gives the full command limit (:mod:`falcon_plan.model.saturation`).
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
            substeps = max(SUBSTEPS_COMPLIANT if compliant else SUBSTEPS_RIGID,
                           friction_substeps(self.effects, params, self.rate_hz))
        if int(substeps) != substeps or substeps < 1:
            raise InvalidParameterError(f"substeps must be a whole number >= 1, got {substeps}")
        self.layout = PlantLayout(params, self.model.limits, compliant, int(substeps))
        self.delay_samples = params.command_delay_samples + int(self.effects.extra_delay_samples)
        """Periods between issuing a command and its acting (2 + the extra-delay effect)."""
        with BUILDING:
            self._encoder = plant_encoder(self.layout)   # the period and the chunks run compiled
        self._pp = plant_parameters(self.layout, self.effects, dt_s=self.dt_s, saturation=saturation,
                                    release_speed_rad_s=release_speed_rad_s)
        self._eff = self.effects.smooth_vector()
        self._compile = compile
        self._period = self._buffered("period")
        self._period.inputs[2][:] = self._eff
        self._period.inputs[3][:] = self._pp
        self._batch: dict[str, BufferedFunction] = {}
        self.hold_periods = max(1, int(round(params.command_hold_s * self.rate_hz)))
        self.reset()

    def set_external_force(self, force_N: Any) -> None:
        """Push the grip with the constant force ``force_N`` (3,) [N, base frame] from the next
        period on (zero removes it); for disturbance-rejection tests."""
        f = np.asarray(force_N, dtype=float).reshape(-1)
        if f.shape != (3,) or not np.isfinite(f).all():
            raise InvalidParameterError(f"force_N must be 3 finite numbers [N], got {force_N!r}")
        first = PLANT_PARAMETERS.index("force_x_N")
        self._pp[first:first + 3] = f
        self._period.inputs[3][:] = self._pp

    @functools.cached_property
    def functions(self) -> PlantFunctions:
        """This plant's CasADi Functions (:func:`~falcon_plan.sim.equations.plant_functions`,
        unmerged: built on first use, for references and tests; the plant itself runs compiled)."""
        return plant_functions(self.layout, merged=False)

    def _buffered(self, kind: str) -> BufferedFunction:
        d = self.delay_samples if kind == "pd" else 0
        return buffered_plant_function(self.layout, kind, d, compile=self._compile)

    @property
    def compiled(self) -> bool:
        """True when the per-period step runs compiled C."""
        return self._period.compiled

    # --- state -------------------------------------------------------------------------------
    def reset(self, position_m: Any = None, velocity_m_s: Any = (0.0, 0.0, 0.0), *,
              commands: Any = None) -> None:
        """Put the device at rest (or moving with ``velocity_m_s`` [m/s]) at the point
        ``position_m`` [m, base frame] (default: home, counts 0), time 0,
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
        enc, theta1 = self._encoder(x, self._eff)
        theta1 = np.asarray(theta1).ravel()
        if not np.isfinite(theta1).all():
            raise InvalidParameterError(f"position {p.tolist()} m is not reachable")
        if self.layout.compliant:
            jac = np.asarray(self.model.functions.jacobian(p, self._eff))
            x[6:9], x[9:12] = theta1, jac @ v
            enc, theta1 = self._encoder(x, self._eff)
        self._x = self._period.inputs[0]
        self._x[:] = x
        self._set_reading(np.asarray(enc).ravel(), theta1)
        self._k = 0
        self._acting = np.zeros(3)
        self._motor_command = np.zeros(3)
        self._firmware = Firmware(self.delay_samples, self.hold_periods)
        issued = self._issue(commands)
        if issued is not None:
            self._firmware.preload(issued)
            self._acting = issued.copy()

    def _set_reading(self, enc: Any, theta1: Any) -> None:
        self._theta1 = np.array(theta1, dtype=float).ravel()
        self._enc = np.array(enc, dtype=float).ravel()
        self._counts = np.floor(self._enc + 0.5).astype(np.int64)

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
        return self._run_period(self._firmware.push(self._issue(commands)))

    def step_acting(self, acting: Any) -> np.ndarray:
        """Run one control period with ``acting`` (3 finite numbers [command units], e.g. the
        time average of the commands that acted in it) acting on the motors now: the command
        path (delay line, hold) is bypassed, the static saturation still applies. For a
        caller that models the command path itself (e.g. a reference world with its own
        timing; the batched form is :meth:`run_timed_pd`).
        Returns the encoder counts (int64, (3,)) read at the end of the period."""
        acting = np.asarray(acting, dtype=float).reshape(3)
        if not np.isfinite(acting).all():
            raise InvalidParameterError(f"acting commands must be 3 finite numbers, got {acting!r}")
        return self._run_period(acting)

    def _run_period(self, acting: np.ndarray) -> np.ndarray:
        """One period with ``acting`` on the motors; the counts read at its end."""
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

    def run_timed_pd(self, controller: EncoderPD, ticks: Any, ref_counts: Any, feedforward: Any,
                     weights: Any) -> tuple[np.ndarray, np.ndarray]:
        """Batched closed loop whose ticks and command path are given period by period (the
        discrepancy replay's real timing; :func:`~falcon_plan.sim.batch.timed_pd_chunk`):
        ``ticks`` (J, 4) = [1 if a tick runs in the period else 0, the rate its PD scales the
        count difference by [Hz], the share w of the period after the previous boundary at
        which its reading arrived, 1 if that reading is new else 0 (the tick used the previous
        tick's reading again)], ``ref_counts`` [counts] and ``feedforward`` [command
        units] (J, 3) (used in ticked periods), ``weights`` (J, TIMED_LINE): the share of
        the period each of the last commands (newest first) acted in. The plant's own
        command path is bypassed (and left empty); the PD starts from ``controller``'s gains
        at rest, its previous count the counts now. Returns per period the counts read and
        the command computed (meaningful in ticked periods), (J, 3) each."""
        from falcon_plan.sim.batch import TIMED_LINE

        ticks, refs = np.asarray(ticks, dtype=float), np.asarray(ref_counts, dtype=float)
        ffs, ws = np.asarray(feedforward, dtype=float), np.asarray(weights, dtype=float)
        k_total = ticks.shape[0]
        if not (ticks.shape == (k_total, 4) and refs.shape == ffs.shape == (k_total, 3)
                and ws.shape == (k_total, TIMED_LINE)):
            raise InvalidParameterError(f"ticks must be (J, 4), ref_counts and feedforward (J, 3) and weights "
                                        f"(J, {TIMED_LINE}), got {ticks.shape}, {refs.shape}, {ffs.shape}, {ws.shape}")
        if k_total == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        n = self.layout.n_states
        z0 = np.concatenate([self._x, np.zeros(3), self._counts.astype(float), self._enc, np.zeros(3 * TIMED_LINE)])
        gains = np.array([controller.kp, controller.kd, controller.alpha, float(controller.limit)])
        zs, counts, tcs = self._run_chunks("timed_pd", z0, [refs.T, ffs.T, ticks.T, ws.T], [gains])
        self._check_batch(zs[:n], counts)
        enc, theta = self._encoder_at(zs[:n, -1])
        self._firmware = Firmware(self.delay_samples, self.hold_periods)
        self._advance(zs[:n, -1], enc, theta, np.full(3, np.nan), k_total)
        return counts.T.copy(), tcs.T.copy()

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
        enc, theta = self._encoder(x, self._eff)
        return np.asarray(enc).ravel(), np.asarray(theta).ravel()

    def _run_chunks(self, kind: str, z0: np.ndarray, per_step: list[np.ndarray],
                    constants: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`~falcon_plan.sim.batch.run_chunks` of this plant's ``kind`` Function, with
        its effects and parameters."""
        return run_chunks(self._batch_function(kind), z0, per_step, [self._eff, self._pp, *constants])

    def _batch_function(self, kind: str) -> BufferedFunction:
        if kind not in self._batch:
            self._batch[kind] = self._buffered(kind)
        return self._batch[kind]


__all__ = ["SimPlant"]
