"""Time-varying LQR tracking of a planned motion, designed from the model (the default
controller of the executor; :class:`falcon_plan.control.Controller` with ``kind="lqr"``).

Everything is in encoder space, per leg: the counts n [counts] and their rate dn/dt
[counts/s]; the reference is the plan's counts ref_k on the loop's grid t_k = k / rate.

Design, once per reference (:func:`design`), from the reference counts and the model only
(so that a replay regenerates exactly the gains that ran):

1. **Feed-forward** u_ff,k: the model's inverse dynamics of the reference over the period the
   command will act on, ``delay`` samples ahead (:func:`model_feedforward`; the same formula
   as the PD's feed-forward, with a fractional lead read by linear interpolation).
2. **Linearisation** at every sample of a motion (the reference state and the feed-forward
   acting then): s = (n, dn/dt), ds/dt = A(t) s + B(t) Tc
   (:meth:`FalconModel.count_linearisation`, from the CasADi model; without the friction that
   switches with the leg speed's sign, :meth:`~falcon_plan.model.effects.Effects.for_linear_design`:
   its smoothed sign's slope at rest is not damping), **discretised** at the
   loop period T by matrix exponentials with the command delay d = m + f samples (m whole,
   0 <= f < 1) in the state: a command acts from d periods after it is issued, so over one
   period the motors see u_{k-m-1} for f T and then u_{k-m}; the ceil(d) commands in flight
   are 3 ceil(d) extra states (the delay line).
3. **Finite-horizon Riccati pass** backwards over each motion (plus :data:`HORIZON_MARGIN_S`
   on both sides) from the infinite-horizon solution (DARE) of the hold that follows; at holds
   the stationary DARE gains of the hold's pose. Weights by Bryson's rule: position error
   ``position_counts`` [counts], count-rate error ``velocity_counts_s`` [counts/s], feedback
   command ``feedback_units`` [command units] (by default the plan's feedback reserve, 150:
   the feedback that the expected errors call for stays within what the plan left free).
4. **Observer**: a stationary Kalman filter (gain :func:`observer_gain`) of the deviation
   from the reference, (delta n, delta dn/dt) plus a constant disturbance at the command
   input (per leg, command units), predicted with the same time-varying discrete model and
   the commands in flight (known exactly), corrected with the counts read. The disturbance
   estimate is cancelled in the command (integral action: a payload, friction or a push at
   the grip is rejected without a steady error). No velocity filter: the observer's count
   rate has no filter lag.

Per tick (:class:`LqrTracker.update`, one matrix-vector product precomputed per sample; the
arithmetic is one compiled C call, :func:`compiled_tick`, about 6 us a tick; the tests check
it against a separate numpy statement of the law)::

    xi_k  = [observer prediction (9), delay line (3 ceil(d))],  y_k = n_k - ref_k
    [du; xi_{k+1}'] = G_k [xi_k; y_k]
    Tc_k = clamp(round(u_ff,k + du), +-limit),   xi_{k+1} = xi_{k+1}' + E_k (Tc_k - u_ff,k)

(the second term records the command actually sent, rounded and clamped, in the delay line
and the prediction).

Saturation: the planner keeps ``feedback_reserve`` command units below its bound
(:class:`~falcon_plan.planning.problem.CommandLimits`, default 150 below 2500), the Bryson
weight on the command is that reserve, so the feedback for errors of the stated size fits in
it; the command sent is clamped to the device's speed-dependent limit L(w) at the reference's
leg speeds (2500 at rest, up to 4096 in motion: what the motors would give anyway; the lowest
over the periods it may act in, a loop delay up to :data:`LATE_ACTING_TICKS` longer than
designed for included) and at the
motor speeds the observer predicts for the periods it may act in, the late ones included
(:data:`SPEED_PERIODS`; its count-rate error carried on under the commands in flight: a device
braking hard, or behind its reference, will be slower than the reference then), and the
observer is told the clamped value. Before the motion (the
approach from a measured state and the hold) the executor keeps the command within the
static limit whatever the speed (:meth:`LqrTracker.within_static_until`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.saturation import SaturationModel, speed_limit
from falcon_plan.timing import give_way

if TYPE_CHECKING:
    from falcon_plan.compiled import BufferedFunction
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.effects import Effects

DEFAULT_POSITION_COUNTS = 1.5
"""Bryson's rule: the position error the design tolerates [counts] (about the resolution: one
encoder count plus the rounding of the reading)."""
DEFAULT_VELOCITY_COUNTS_S = 300.0
"""Bryson's rule: the count-rate error tolerated [counts/s]."""
DEFAULT_FEEDBACK_UNITS = 150.0
"""Bryson's rule: the feedback command [command units]: the planner's default feedback
reserve (``CommandLimits.feedback_reserve``)."""
MEASUREMENT_NOISE_COUNTS = 1.0
"""Observer: standard deviation of a reading [counts] (whole counts, plus what the model misses
between readings)."""
ACCELERATION_NOISE_COUNTS_S2 = 5.0e3
"""Observer: standard deviation of the unmodelled count acceleration per leg [counts/s^2]."""
DISTURBANCE_NOISE_UNITS_S = 2.0e3
"""Observer: random-walk rate of the input disturbance [command units / sqrt(s)]."""
HORIZON_MARGIN_S = 0.1
"""The time-varying gains cover each motion plus this much before and after [s]; elsewhere the
reference holds still and the gains are the hold's stationary ones."""
LIMIT_MARGIN_UNITS = 20.0
LIMIT_MARGIN_COUNTS_S = 400.0
"""The clamp at the predicted motor speed takes the device's limit at this much less speed
[counts/s], and both clamps (it and the one at the reference's speeds) keep this far below the
limit [command units]: the observer's count rate is uncertain by
tens of counts/s (measured without them: up to 43 units over the device's limit while braking
on a device-limit plan), and by more where a leg reverses on a device with friction the model
does not know (the friction flips sign faster than the observer's disturbance estimate
follows): with 150 counts/s, the simulated device with hidden Coulomb friction (0.01 N.m) and
payload (40 g) clipped commands up to 1.04x its limit just after a leg passed through rest
(benchmarks/bench_tracking.py --only sim,sim+hidden; 1.05x on a fast plan of via_two_points);
with 400 at most 1.0x there. The margin costs tracking where a device-limit plan uses the limit
at speed (the clamp bites sooner): the device-limit move of tests/planning/test_device_limit.py
tracks at 0.29 mm RMS with 400, 0.32 mm with 450; the constant-limit problems are unchanged
(sim median 0.031 mm)."""
LATE_ACTING_TICKS = 2
"""The clamp at the reference's speeds also covers this many periods after the design's delay:
the loop delay of threaded USB I/O is about 4 periods against the model's 2, so a command may
act that much later, when a leg reversing or braking is slower (measured on the emulated Falcon
through threaded USB without it: up to 1.05x the device's limit where a leg passes through rest)."""
SPEED_PERIODS = 2 + LATE_ACTING_TICKS
"""The clamp at the predicted motor speed takes the lowest limit over this many periods from the
command delay's whole samples on: the two a command acts in, and the :data:`LATE_ACTING_TICKS`
after them in which it may act instead (a device braking hard is slower then: measured on the
emulated Falcon through threaded USB with only the two, up to 1.14x the device's limit while a
leg braked towards rest, at 0.4 rad/s less per period)."""
STILL_COUNTS = 1e-9
"""The reference holds still between two samples closer than this [counts]."""
LATE_READING_TICKS = 8
"""A reading read for a tick up to this many ticks before the next one the tracker expects (a
late status: the host stalled while it was on its way) corrects the observer at its own tick
(:meth:`LqrTracker.update`, ``read_for``); an older one is not used."""
STALE_INNOVATION_COUNTS = 12.0
"""A fresh reading whose innovation (its counts less the observer's prediction for the tick it
was taken as) exceeds this on some leg [counts] (the observer's usual innovation is a count or
two, a few with effects the model lacks) is checked against the predictions of the
:data:`LATE_READING_TICKS` ticks before: if one of them explains it within
:data:`STALE_MATCH_COUNTS`, and three times better, the reading is that tick's, delayed on its
way (:meth:`LqrTracker.update`). Measured on the emulated Falcon with a CPU-stress process: no
status came for 2.5 ms, then one about two periods old arrived and was dated by its arrival;
taken as the current tick's it was 54 counts behind at speed, and the law sent -4076 on every
leg for two ticks (0.51 mm RMS on that run, 0.03 mm usually). A device that really stopped
(held by a hand or an obstacle) looks the same for at most that many ticks, then is followed."""
STALE_MATCH_COUNTS = 4.0
"""How close an earlier tick's prediction must be to a delayed reading's counts [counts] (the
quantisation and the observer's usual error) for the reading to be taken as that tick's."""
AHEAD_INNOVATION_COUNTS = 6.0
"""A fresh reading whose innovation exceeds this on some leg [counts] and that the observer's
prediction for the tick after explains within :data:`STALE_MATCH_COUNTS`, three times better,
is a status a frame newer than the loop's delay (threaded I/O handed one over after a late
hand-over): it is left out, the observer predicting through the tick without it, never two
ticks in a row (a device really ahead is followed). Taken as the expected tick's at 18 counts a
tick it swung the commands by 3300 units (measured in the closed loop on the simulated plant)."""


# --- feed-forward ------------------------------------------------------------------------------

def model_feedforward(ref_counts: np.ndarray, model: FalconModel, effects: Effects, rate_hz: float,
                      lead_samples: float, positions_m: np.ndarray | None = None) -> np.ndarray:
    """Commands (K, 3) [command units] of the model's inverse dynamics for the reference
    counts ``ref_counts`` (K, 3) over the period [k + lead, k + lead + 1] that a command issued at
    k acts on: positions are the forward kinematics of the reference (read from ``effects``'
    home angle, :meth:`Effects.encoder_params`), the state at the period's midpoint, the velocity
    its mean and the acceleration the centred second difference around it. ``model`` gives
    the parameter set, ``effects`` the model's effects; ``rate_hz`` the loop rate [Hz];
    ``lead_samples`` >= 0, fractional leads read the positions by linear interpolation
    (whole leads read samples exactly). Samples beyond either end hold the end.
    ``positions_m`` (K, 3) [m]: the reference's points if already known (their forward
    kinematics is then not recomputed)."""
    from falcon_plan.model.kinematics import counts_to_position

    k_total = ref_counts.shape[0]
    p = (counts_to_position(ref_counts, effects.encoder_params(model.params)).reshape(k_total, 3)
         if positions_m is None else np.asarray(positions_m, dtype=float))
    grid = np.arange(k_total, dtype=float)

    def at(j: np.ndarray) -> np.ndarray:
        j = np.clip(j, 0.0, k_total - 1.0)
        if float(lead_samples).is_integer():
            return p[j.astype(int)]
        return np.stack([np.interp(j, grid, p[:, i]) for i in range(3)], axis=1)

    j = grid + lead_samples
    p_prev, p0, p1, p2 = at(j - 1), at(j), at(j + 1), at(j + 2)
    return np.asarray(model.with_effects(effects).inverse_dynamics(
        0.5 * (p0 + p1), (p1 - p0) * rate_hz, 0.5 * (p2 - p1 - p0 + p_prev) * rate_hz * rate_hz),
        dtype=float).reshape(k_total, 3)


# --- the discrete design model ------------------------------------------------------------------

@dataclass(frozen=True)
class DelayModel:
    """The command delay d = ``whole`` + ``fraction`` samples (0 <= fraction < 1) and the delay
    line it needs: ``line`` = ceil(d) commands in flight."""

    whole: int
    fraction: float

    @classmethod
    def of(cls, delay_samples: float) -> "DelayModel":
        """From the delay ``delay_samples`` [samples], a finite number >= 0."""
        if not (math.isfinite(delay_samples) and delay_samples >= 0):
            raise InvalidParameterError(f"the command delay must be a finite number >= 0 [samples], got {delay_samples!r}")
        whole = int(math.floor(delay_samples + 1e-12))
        fraction = max(0.0, float(delay_samples) - whole)
        if fraction < 1e-9:
            fraction = 0.0
        return cls(whole, fraction)

    @property
    def line(self) -> int:
        """Commands in flight (3 states each)."""
        return self.whole + (1 if self.fraction > 0 else 0)


EXP_TERMS = 14
"""Taylor terms of the matrix exponentials (Horner's scheme, after scaling to a norm <= 1/2:
the truncation error is below 1e-16 relative)."""


def _expm(x: np.ndarray) -> np.ndarray:
    """exp(X) for a batch of square matrices X (K, n, n): scaling and squaring around a Taylor
    series in batched matrix products (scipy's Pade ``expm`` loops over the batch in LAPACK
    calls, ~100 times slower here; tests compare the two)."""
    norm = float(np.abs(x).sum(axis=-1).max()) if x.size else 0.0
    squarings = max(0, int(math.ceil(math.log2(norm / 0.5)))) if norm > 0.5 else 0
    x = x / 2.0 ** squarings
    eye = np.eye(x.shape[-1])
    e = eye + x / EXP_TERMS
    for i in range(EXP_TERMS - 1, 0, -1):
        e = eye + (x @ e) / i
    for _ in range(squarings):
        e = e @ e
    return e


def _augmented_exp(a: np.ndarray, b: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """(exp(A tau), int_0^tau exp(A s) ds B) for batches A (K, 6, 6), B (K, 6, 3)."""
    k, n, m = b.shape
    big = np.zeros((k, n + m, n + m))
    big[:, :n, :n], big[:, :n, n:] = a * tau, b * tau
    e = _expm(big)
    return e[:, :n, :n], e[:, :n, n:]


def discretise(a21: np.ndarray, a22: np.ndarray, b2: np.ndarray, period_s: float,
               delay: DelayModel) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The continuous encoder-space model (``a21``, ``a22``, ``b2``: A21, A22, B2, each (K, 3, 3);
    see :meth:`FalconModel.count_linearisation`) over one period ``period_s`` [s] with the command
    delay ``delay``: returns Phi (K, 6, 6) and the input matrices {j: (K, 6, 3)} of the
    commands u_{k-j} that act during period k (their sum is the zero-order-hold input matrix):
    x_{k+1} = Phi x_k + sum_j B_j u_{k-j}."""
    k = a21.shape[0]
    a = np.zeros((k, 6, 6))
    a[:, 0:3, 3:6] = np.eye(3)
    a[:, 3:6, 0:3], a[:, 3:6, 3:6] = a21, a22
    b = np.zeros((k, 6, 3))
    b[:, 3:6, :] = b2
    phi, gamma = _augmented_exp(a, b, period_s)
    if delay.fraction == 0.0:
        return phi, {delay.whole: gamma}
    late = (1.0 - delay.fraction) * period_s
    phi_late, gamma_late = _augmented_exp(a, b, late)
    _, gamma_early = _augmented_exp(a, b, delay.fraction * period_s)
    return phi, {delay.whole: gamma_late, delay.whole + 1: phi_late @ gamma_early}


def lqr_system(phi: np.ndarray, inputs: dict[int, np.ndarray], delay: DelayModel) -> tuple[np.ndarray, np.ndarray]:
    """The LQR's discrete system with the delay line, z = [x (6), u_{k-L}, ..., u_{k-1}]
    (L = ``delay.line``): (A_z (K, nz, nz), B_z (K, nz, 3)) from :func:`discretise`'s Phi
    ``phi`` and input matrices ``inputs``."""
    k_total, line = phi.shape[0], delay.line
    nz = 6 + 3 * line
    a = np.zeros((k_total, nz, nz))
    b = np.zeros((k_total, nz, 3))
    a[:, :6, :6] = phi
    for j, mat in inputs.items():
        if j == 0:
            b[:, :6, :] += mat
        else:
            col = 6 + 3 * (line - j)
            a[:, :6, col:col + 3] += mat
    for i in range(line - 1):  # the line shifts by one command per period
        a[:, 6 + 3 * i:9 + 3 * i, 9 + 3 * i:12 + 3 * i] = np.eye(3)
    if line:
        b[:, nz - 3:, :] = np.eye(3)
    return a, b


DARE_TOLERANCE = 1e-12
"""Relative change at which the doubling iteration of :func:`_dare` stops."""


def _dare(a: np.ndarray, b: np.ndarray, q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The stabilising solution X of the discrete algebraic Riccati equation
    X = A'XA - A'XB (R + B'XB)^-1 B'XA + Q, by the structure-preserving doubling algorithm
    (quadratic convergence; plain matrix products and solves: scipy's Schur-based solver
    spends most of its time in threaded BLAS calls, which stall on a busy machine; the tests
    compare the two)."""
    n = a.shape[0]
    eye = np.eye(n)
    ak, gk, hk = a.copy(), b @ np.linalg.solve(r, b.T), q.copy()
    for _ in range(100):
        w = eye + gk @ hk
        wa = np.linalg.solve(w, ak)
        wg = np.linalg.solve(w, gk)
        h_next = hk + ak.T @ hk @ wa
        gk = gk + ak @ wg @ ak.T
        ak = ak @ wa
        if np.abs(h_next - hk).max() <= DARE_TOLERANCE * max(1.0, np.abs(h_next).max()):
            return 0.5 * (h_next + h_next.T)
        hk = h_next
    raise InvalidParameterError("the Riccati equation of the LQR design did not converge (an uncontrollable model?)")


def _lqr_gain(a: np.ndarray, b: np.ndarray, p_next: np.ndarray, r: np.ndarray) -> np.ndarray:
    """K = (R + B' P B)^-1 B' P A (u = -K z)."""
    bp = b.T @ p_next
    return np.linalg.solve(r + bp @ b, bp @ a)


def observer_gain(phi: np.ndarray, gamma: np.ndarray, rate_hz: float) -> np.ndarray:
    """The stationary Kalman gain L (9, 3) of the observer state (delta n, delta dn/dt,
    input disturbance) for the one-period model ``phi`` (6, 6), zero-order-hold input matrix
    ``gamma`` (6, 3), loop rate ``rate_hz`` [Hz]; the correction is chi += L (y - delta n).
    Noise: :data:`MEASUREMENT_NOISE_COUNTS`, :data:`ACCELERATION_NOISE_COUNTS_S2`,
    :data:`DISTURBANCE_NOISE_UNITS_S`."""
    period = 1.0 / rate_hz
    f = np.zeros((9, 9))
    f[:6, :6], f[:6, 6:] = phi, gamma
    f[6:, 6:] = np.eye(3)
    c = np.zeros((3, 9))
    c[:, :3] = np.eye(3)
    w = np.zeros((9, 9))
    acc = (ACCELERATION_NOISE_COUNTS_S2 * period) ** 2 / period  # white acceleration, per period
    w[0:3, 0:3] = np.eye(3) * acc * period ** 2 / 3.0
    w[0:3, 3:6] = w[3:6, 0:3] = np.eye(3) * acc * period / 2.0
    w[3:6, 3:6] = np.eye(3) * acc
    w[6:, 6:] = np.eye(3) * DISTURBANCE_NOISE_UNITS_S ** 2 * period
    v = np.eye(3) * MEASUREMENT_NOISE_COUNTS ** 2
    p = _dare(f.T, c.T, w, v)
    return p @ c.T @ np.linalg.inv(c @ p @ c.T + v)


# --- the schedule ---------------------------------------------------------------------------

@dataclass(frozen=True)
class LqrWeights:
    """Bryson's rule: the largest position error ``position_counts`` [counts], count-rate error
    ``velocity_counts_s`` [counts/s] and feedback command ``feedback_units`` [command units]
    wanted; each weight is one over its square."""

    position_counts: float = DEFAULT_POSITION_COUNTS
    velocity_counts_s: float = DEFAULT_VELOCITY_COUNTS_S
    feedback_units: float = DEFAULT_FEEDBACK_UNITS

    def __post_init__(self) -> None:
        for name in ("position_counts", "velocity_counts_s", "feedback_units"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidParameterError(f"LQR weight {name} must be a number > 0, got {value!r}")

    def matrices(self, line: int) -> tuple[np.ndarray, np.ndarray]:
        """(Q (6 + 3 line, same), R (3, 3)); the delay line is not weighted."""
        q = np.zeros((6 + 3 * line, 6 + 3 * line))
        q[0:3, 0:3] = np.eye(3) / self.position_counts ** 2
        q[3:6, 3:6] = np.eye(3) / self.velocity_counts_s ** 2
        return q, np.eye(3) / self.feedback_units ** 2


@dataclass(frozen=True)
class GainSchedule:
    """The LQR along one reference (made by :func:`design`).

    Attributes
    ----------
    rate_hz : loop rate [Hz]; delay_samples : the command delay designed for [samples].
    ref_counts : (K, 3) the reference [counts]; feedforward : (K, 3) u_ff [command units].
    gains : (G, 3, 6 + 3 L) the LQR gains K (u = -K z) on z = (delta n, delta dn/dt,
        commands in flight oldest first), one per distinct design (holds share theirs).
    index : (K,) int: the gains (and tick matrices) of each sample.
    tick : (G, 3 + nx, nx + 3) the per-tick matrices G_k (module docstring), nx = 9 + 3 L.
    record : (G, nx, 3) E_k: how the command sent enters the next observer state.
    observer : (9, 3) the Kalman gain L.
    systems : ((G, nz, nz), (G, nz, 3)) the discrete design model (A_z, B_z) of each gain.
    command_limits : (K, 3) the device's speed-dependent limit L(w) [command units] at the
        reference's leg speeds over the period each command acts on (the lowest from its start
        to :data:`LATE_ACTING_TICKS` periods after its end) (:mod:`falcon_plan.model.saturation`):
        the tracker clamps to it, and to the limit at the estimated speed (below), so the
        observer knows what the motors got.
    acting_rate : (K, P, 3) the reference's count rate at the start of the P =
        :data:`SPEED_PERIODS` periods each command may act in (the command delay's whole
        samples on, one more, and the late ones) [counts/s]: plus the observer's predicted
        count-rate error then (``speed_rows``), the motor speeds the device's limit will be set
        from.
    saturation : the device's saturation rule (:class:`~falcon_plan.model.saturation.SaturationModel`).
    counts_per_rad : encoder counts per radian of leg angle.
    speed_rows : (G, 3 P, nx + 3) the observer's predicted count-rate error at those P times
        from [observer state; reading error] (the commands in flight known, no feedback after
        them): the device brakes or speeds up under the commands in flight before this one acts.
    """

    rate_hz: float
    delay_samples: float
    ref_counts: np.ndarray
    feedforward: np.ndarray
    gains: np.ndarray
    index: np.ndarray
    tick: np.ndarray
    record: np.ndarray
    observer: np.ndarray
    systems: tuple[np.ndarray, np.ndarray]
    command_limits: np.ndarray
    acting_rate: np.ndarray
    saturation: SaturationModel
    counts_per_rad: float
    speed_rows: np.ndarray

    @property
    def samples(self) -> int:
        """K, the reference's samples."""
        return int(self.index.shape[0])

    def closed_loop_radius(self) -> np.ndarray:
        """(G,) the spectral radius of A_z - B_z K of each gain (< 1: stable)."""
        az, bz = self.systems
        return np.array([max(abs(np.linalg.eigvals(a - b @ k))) for a, b, k in zip(az, bz, self.gains)])

    def gains_at(self) -> np.ndarray:
        """(K, 3, 6 + 3 L): the gain matrix K_k of every sample."""
        return self.gains[self.index]


def _moving(ref: np.ndarray) -> np.ndarray:
    """(K,) True where the reference moves into or out of sample k."""
    step = np.any(np.abs(np.diff(ref, axis=0)) > STILL_COUNTS, axis=1)
    moving = np.zeros(ref.shape[0], dtype=bool)
    moving[1:] |= step
    moving[:-1] |= step
    return moving


def _runs(mask: np.ndarray) -> list[tuple[int, int, bool]]:
    """Contiguous runs (start, stop, value) of a boolean array."""
    edges = np.flatnonzero(np.diff(mask.astype(np.int8))) + 1
    bounds = np.concatenate([[0], edges, [mask.size]])
    return [(int(a), int(b), bool(mask[a])) for a, b in zip(bounds[:-1], bounds[1:])]


def design(ref_counts: Any, model: FalconModel, effects: Effects, rate_hz: float, delay_samples: float,
           weights: LqrWeights = LqrWeights()) -> GainSchedule:
    """The gain schedule along ``ref_counts`` (K, 3) [counts, from ``effects``' home angle] at
    ``rate_hz`` [Hz] with the command delay ``delay_samples`` [samples, may be fractional],
    designed on ``model``'s parameter set with ``effects`` (the controller's model) and
    ``weights``. Deterministic: the same inputs give the same schedule."""
    from falcon_plan.model.kinematics import counts_to_position

    ref = np.asarray(ref_counts, dtype=float)
    if ref.ndim != 2 or ref.shape[1] != 3 or ref.shape[0] == 0 or not np.isfinite(ref).all():
        raise InvalidParameterError(f"ref_counts must be finite with shape (K, 3), K >= 1, got {ref.shape}")
    delay = DelayModel.of(float(delay_samples))
    k_total, period = ref.shape[0], 1.0 / rate_hz
    ff = model_feedforward(ref, model, effects, rate_hz, float(delay_samples))
    q, r = weights.matrices(delay.line)
    design_model = model.with_effects(effects.for_linear_design())

    # where the time-varying gains apply: every motion widened by the margin
    margin = int(round(HORIZON_MARGIN_S * rate_hz))
    moving = _moving(ref)
    varying = moving.copy()
    for start, stop, value in _runs(moving):
        if value:
            varying[max(0, start - margin):min(k_total, stop + margin)] = True
    # the linearisation points: the stationary part once per hold, every sample of a motion
    points = np.flatnonzero(varying)
    holds = [(a, b) for a, b, v in _runs(varying) if not v]
    rows = np.concatenate([points, np.array([a for a, _ in holds], dtype=int)]).astype(int)
    p = counts_to_position(ref, effects.encoder_params(model.params)).reshape(k_total, 3)
    grid = np.arange(k_total)
    v = (p[np.minimum(grid + 1, k_total - 1)] - p[np.maximum(grid - 1, 0)]) * (0.5 * rate_hz)
    v[~moving] = 0.0
    acting = ff[np.clip(grid - int(round(delay_samples)), 0, k_total - 1)]
    a21, a22, b2 = design_model.count_linearisation(p[rows], v[rows], acting[rows])
    phi, inputs = discretise(a21, a22, b2, period, delay)
    az, bz = lqr_system(phi, inputs, delay)
    gamma = sum(inputs.values())
    row_of = {int(k): i for i, k in enumerate(rows)}

    index = np.zeros(k_total, dtype=int)
    gains: list[np.ndarray] = []
    source_row: list[int] = []  # the design (row of az, bz) each gain came from
    hold_p: dict[int, np.ndarray] = {}
    for a, b in holds:  # stationary LQR at each hold
        i = row_of[a]
        hold_p[a] = _dare(az[i], bz[i], q, r)
        index[a:b] = len(gains)
        gains.append(_lqr_gain(az[i], bz[i], hold_p[a], r))
        source_row.append(i)
    for start, stop, value in _runs(varying):  # finite-horizon Riccati pass over each motion
        if not value:
            continue
        p_next = hold_p.get(stop)
        if p_next is None:
            last = row_of[stop - 1]
            p_next = _dare(az[last], bz[last], q, r)
        for k in range(stop - 1, start - 1, -1):
            give_way()
            i = row_of[k]
            gain = _lqr_gain(az[i], bz[i], p_next, r)
            p_next = q + az[i].T @ p_next @ (az[i] - bz[i] @ gain)
            p_next = 0.5 * (p_next + p_next.T)
            index[k] = len(gains)
            gains.append(gain)
            source_row.append(i)
    gain_arr, src = np.array(gains), np.array(source_row)
    observer = observer_gain(phi[row_of[0]], gamma[row_of[0]], rate_hz)
    tick, record, speed_rows = _tick_matrices(gain_arr, phi[src], {j: m[src] for j, m in inputs.items()}, delay,
                                              observer)
    return GainSchedule(float(rate_hz), float(delay_samples), ref, ff, gain_arr, index, tick, record,
                        observer, (az[src], bz[src]), *_command_limits(ref, model, rate_hz, delay_samples), speed_rows)


def _command_limits(ref: np.ndarray, model: FalconModel, rate_hz: float,
                    delay_samples: float) -> tuple[np.ndarray, np.ndarray, SaturationModel, float]:
    """The device's limit along ``ref`` (K, 3) [counts]: (K, 3) the lowest L(w) [command units]
    from the start of the period each command acts on to :data:`LATE_ACTING_TICKS` periods after
    its end, (K, P, 3) the reference's signed count rate at the start of the
    :data:`SPEED_PERIODS` periods it may act in [counts/s], the saturation rule and the counts
    per radian (GainSchedule's fields after ``systems``)."""
    k_total = ref.shape[0]
    grid = np.arange(k_total)
    signed_rate = (ref[np.minimum(grid + 1, k_total - 1)] - ref[np.maximum(grid - 1, 0)]) * (0.5 * rate_hz)
    leg_speed = np.abs(signed_rate) / model.params.counts_per_rad
    acting_at = grid + int(math.floor(delay_samples))
    rule = SaturationModel.of(model.params)
    fraction = float(delay_samples) - math.floor(delay_samples)
    last = 1 + (fraction > 0) + LATE_ACTING_TICKS
    at = lambda j: np.minimum(acting_at + j, k_total - 1)  # noqa: E731  (acting_at >= 0)
    limit = rule.limit(leg_speed)                          # elementwise: once, then shifted
    limits = np.min([limit[at(j)] for j in range(last + 1)], axis=0)
    acting_rate = np.stack([signed_rate[at(j)] for j in range(SPEED_PERIODS)], axis=1)
    return np.ascontiguousarray(limits), np.ascontiguousarray(acting_rate), rule, float(model.params.counts_per_rad)


def hold_design(ref_counts: np.ndarray, feedforward: np.ndarray, model: FalconModel, effects: Effects,
                rate_hz: float, delay_samples: float, weights: LqrWeights, observer: np.ndarray) -> GainSchedule:
    """A schedule with ONE gain for all of ``ref_counts`` (K, 3) [counts]: the stationary (DARE)
    gain of the hold at its last sample, where it comes to rest, with its ``feedforward`` (K, 3)
    [command units] and the ``observer`` gain (9, 3) of the schedule it continues (so the
    observer's estimate carries over); ``model``, ``effects``, ``rate_hz``, ``delay_samples`` and
    ``weights`` as for :func:`design`. One linearisation and one DARE (about a millisecond):
    the gains of a short motion that ends at rest, e.g. a brake
    (:mod:`falcon_plan.execution.braking`); :func:`design` is the full design."""
    from falcon_plan.model.kinematics import counts_to_position

    ref = np.ascontiguousarray(ref_counts, dtype=float)
    delay = DelayModel.of(float(delay_samples))
    q, r = weights.matrices(delay.line)
    p_end = counts_to_position(ref[-1:], effects.encoder_params(model.params)).reshape(1, 3)
    design_model = model.with_effects(effects.for_linear_design())
    a21, a22, b2 = design_model.count_linearisation(p_end, np.zeros((1, 3)), feedforward[-1:])
    phi, inputs = discretise(a21, a22, b2, 1.0 / rate_hz, delay)
    az, bz = lqr_system(phi, inputs, delay)
    gain = _lqr_gain(az[0], bz[0], _dare(az[0], bz[0], q, r), r)[None]
    tick, record, speed_rows = _tick_matrices(gain, phi, inputs, delay, observer)
    return GainSchedule(float(rate_hz), float(delay_samples), ref, np.ascontiguousarray(feedforward, dtype=float),
                        gain, np.zeros(ref.shape[0], dtype=int), tick, record, observer, (az, bz),
                        *_command_limits(ref, model, rate_hz, delay_samples), speed_rows)


def carried_design(schedule: GainSchedule, sample: int, ref_counts: np.ndarray, feedforward: np.ndarray,
                   model: FalconModel) -> GainSchedule:
    """A schedule with ONE gain for all of ``ref_counts`` (K, 3) [counts] with its
    ``feedforward`` (K, 3) [command units]: the gain ``schedule`` uses at its ``sample``, with
    its observer and tick matrices (no design at all: microseconds plus the device limit along
    the reference, from ``model``). For a tail that must start at once (the loop's brake,
    :func:`falcon_plan.execution.braking.quick_brake`) until a designed one takes over."""
    g = int(schedule.index[min(max(sample, 0), schedule.samples - 1)])
    ref = np.ascontiguousarray(ref_counts, dtype=float)
    az, bz = schedule.systems
    return GainSchedule(schedule.rate_hz, schedule.delay_samples, ref, np.ascontiguousarray(feedforward, dtype=float),
                        schedule.gains[g:g + 1], np.zeros(ref.shape[0], dtype=int), schedule.tick[g:g + 1],
                        schedule.record[g:g + 1], schedule.observer, (az[g:g + 1], bz[g:g + 1]),
                        *_command_limits(ref, model, schedule.rate_hz, schedule.delay_samples),
                        schedule.speed_rows[g:g + 1])


def _tick_matrices(gains: np.ndarray, phi: np.ndarray, inputs: dict[int, np.ndarray], delay: DelayModel,
                   observer: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The per-tick matrices (G_k, E_k) of the module docstring for every gain, from its
    design's Phi, input matrices and the observer gain, and the rows predicting the count-rate
    error when the command starts acting (``GainSchedule.speed_rows``)."""
    n_g, line = gains.shape[0], delay.line
    nx = 9 + 3 * line
    # correction: chi = chi_pred + L (y - delta n_pred); the delay line is kept
    w = np.eye(nx)
    w[:9, :3] -= observer
    v = np.zeros((nx, 3))
    v[:9] = observer
    # control: du = -K [delta s; line + d] - d
    z = np.zeros((6 + 3 * line, nx))
    z[:6, :6] = np.eye(6)
    for i in range(line):
        z[6 + 3 * i:9 + 3 * i, 9 + 3 * i:12 + 3 * i] = np.eye(3)
        z[6 + 3 * i:9 + 3 * i, 6:9] = np.eye(3)
    sd = np.zeros((3, nx))
    sd[:, 6:9] = np.eye(3)
    h = -gains @ z - sd                                   # (G, 3, nx)
    # prediction: delta s' = Phi delta s + sum_j B_j (u_{k-j} + d), d' = d, line shifts
    f = np.zeros((n_g, nx, nx))
    e = np.zeros((n_g, nx, 3))
    f[:, :6, :6] = phi
    f[:, :6, 6:9] = sum(inputs.values())
    f[:, 6:9, 6:9] = np.eye(3)
    for j, mat in inputs.items():
        if j == 0:
            e[:, :6, :] += mat
        else:
            col = 9 + 3 * (line - j)
            f[:, :6, col:col + 3] += mat
    for i in range(line - 1):
        f[:, 9 + 3 * i:12 + 3 * i, 12 + 3 * i:15 + 3 * i] = np.eye(3)
    if line:
        e[:, nx - 3:, :] = np.eye(3)
    wv = np.concatenate([w, v], axis=1)                   # (nx, nx + 3)
    tick = np.concatenate([h @ wv, f @ wv], axis=1)       # (G, 3 + nx, nx + 3)
    # the corrected state carried delay.whole and SPEED_PERIODS - 1 more periods on, the
    # commands after those in flight at their feed-forward (deviation 0): its count-rate rows
    ahead = np.broadcast_to(np.eye(nx), f.shape).copy()
    for _ in range(delay.whole):
        ahead = f @ ahead
    rows = []
    for _ in range(SPEED_PERIODS):
        rows.append(ahead[:, 3:6])
        ahead = f @ ahead
    speed = np.concatenate(rows, axis=1) @ wv                                    # (G, 3 P, nx + 3)
    return np.ascontiguousarray(tick), np.ascontiguousarray(e), np.ascontiguousarray(speed)


# --- the per-tick law ------------------------------------------------------------------------

_tick_cache: dict[tuple[int, int], Any] = {}
_tick_library: dict[tuple[int, int], Any] = {}     # the compiled library (None: no compiler)


def compiled_tick(nx: int, periods: int = SPEED_PERIODS, compile: bool = True) -> "BufferedFunction":
    """The arithmetic of one period of the law (:meth:`LqrTracker._tick` without its
    bookkeeping; the one definition of it) as a CasADi Function on in-place buffers, for an
    observer-and-delay-line state of ``nx`` and ``periods`` speed periods: compiled C (built
    once per machine, loaded once per process) unless ``compile`` is False or there is no
    compiler, then the CasADi virtual machine (the same results, ~100x slower). A new
    :class:`~falcon_plan.compiled.BufferedFunction` per call, so trackers never share buffers.

    Inputs, each laid out as the schedule stores it (row-major, read column-major as the
    transpose, so the tracker feeds the schedule's own memory): G_k^T (nx+3, 3+nx), the
    speed rows^T (nx+3, 3 P), E_k^T (3, nx), [xi; y] (nx+3), the reference's count rates at
    the P periods (3 P) [counts/s], the clamp along the reference (3), u_ff (3) [command
    units], the held command (3) and whether it is used (1), and (static, full) of the
    device's limit less :data:`LIMIT_MARGIN_UNITS` [command units], its release speed [rad/s],
    radians per count and :data:`LIMIT_MARGIN_COUNTS_S` [counts/s]. Outputs: the command sent
    (3) [command units], the next observer-and-delay-line state (nx), and the count rates
    predicted for the P periods the command may act in (3 P) [counts/s], which set the clamp."""
    key = (int(nx), int(periods))
    if key not in _tick_cache:
        import casadi as ca

        n = nx + 3
        gt, st, et = ca.SX.sym("gt", n, n), ca.SX.sym("st", n, 3 * periods), ca.SX.sym("et", 3, nx)
        buf, acting = ca.SX.sym("buf", n), ca.SX.sym("acting", 3 * periods)
        along, uff, held, use_held = ca.SX.sym("along", 3), ca.SX.sym("uff", 3), ca.SX.sym("held", 3), ca.SX.sym("use_held")
        rule = ca.SX.sym("rule", 5)       # static, full, release speed, rad per count, margin
        out = ca.mtimes(gt.T, buf)
        # the limit at the motor speeds predicted for when the command acts (reference + the
        # observer's count-rate error carried on under the commands in flight)
        rates = acting + ca.mtimes(st.T, buf)
        speed = ca.fmax(ca.fabs(rates) - rule[4], 0.0)
        limits = speed_limit(speed * rule[3], rule[0], rule[1], rule[2])
        lim = along
        for j in range(periods):
            lim = ca.fmin(lim, limits[3 * j:3 * j + 3])
        law = ca.fmin(ca.fmax(ca.floor(uff + out[:3] + 0.5), -lim), lim)
        tc = ca.if_else(use_held, held, law)
        nxt = out[3:] + ca.mtimes(et.T, tc - uff)
        _tick_cache[key] = ca.Function(f"falcon_lqr_tick_{nx}_{periods}",
                                       [gt, st, et, buf, acting, along, uff, held, use_held, rule], [tc, nxt, rates])
    fn = _tick_cache[key]
    from falcon_plan.compiled import BufferedFunction, build_library

    if compile and key not in _tick_library:
        _tick_library[key] = build_library(fn)
    return BufferedFunction(fn, _tick_library[key] if compile else None, hold_gil=True)   # a few us a call


class LqrTracker:
    """The LQR's per-tick state and law along the :class:`GainSchedule` ``schedule`` (module
    docstring).

    :meth:`start` once with the first counts read (the device had zero force before: the
    commands in flight are zero), then :meth:`update` every tick k = 0, 1, ... with the counts
    read. The commands are clamped to ``limit`` [command units] and to the device's
    speed-dependent limit along the reference (``GainSchedule.command_limits``). Each period's
    arithmetic is one call of :func:`compiled_tick` fed the schedule's own memory: compiled C,
    unless ``compiled`` is False or there is no compiler (then the same Function uncompiled)."""

    def __init__(self, schedule: GainSchedule, limit: float, compiled: bool = True) -> None:
        self.s = schedule
        self.limit = float(limit)
        self.offset = 0              # the tick of the schedule's sample 0 (moved by splice)
        self.limits = self._below(schedule.command_limits)
        rule = schedule.saturation
        # the device's L(w) with the margins: the same rule (speed_limit), lowered by LIMIT_MARGIN_UNITS
        self._margined = (rule.static - LIMIT_MARGIN_UNITS, rule.full - LIMIT_MARGIN_UNITS, rule.release_speed_rad_s)
        self._per_count = 1.0 / schedule.counts_per_rad
        delay = DelayModel.of(schedule.delay_samples)
        self.line = delay.line
        self._acts_next_tick = delay.whole == 0   # a command sent now moves the next tick's counts
        self.nx = 9 + 3 * self.line
        self.tick_function = compiled_tick(self.nx, compile=compiled)
        """The law's Function on its buffers (:func:`compiled_tick`)."""
        self._buf = self.tick_function.inputs[3]           # [xi; y]
        self.tick_function.inputs[9][:] = (*self._margined, self._per_count, LIMIT_MARGIN_COUNTS_S)
        self._bind()
        self.xi = np.zeros(self.nx)
        self.last_tc = np.zeros(3)
        self.k_next = 0
        self.started = False
        self.redated = 0
        """Fresh readings taken as an earlier tick's (delayed on their way: :data:`STALE_INNOVATION_COUNTS`)."""
        self.ahead = 0
        """Fresh readings left out as a tick newer than expected (:data:`AHEAD_INNOVATION_COUNTS`)."""
        self._ahead_at = -2          # the tick whose reading was last left out as newer
        # the last LATE_READING_TICKS ticks: the observer state before each one's correction and
        # the command the device had in it (sent, or held through a missed tick), by tick % size
        self._past_tick = np.full(LATE_READING_TICKS, -1, dtype=np.int64)
        self._past_xi = np.zeros((LATE_READING_TICKS, self.nx))
        self._past_tc = np.zeros((LATE_READING_TICKS, 3))

    def _below(self, command_limits: np.ndarray) -> np.ndarray:
        """The clamp along a schedule: its device limits ``command_limits`` (K, 3) less
        :data:`LIMIT_MARGIN_UNITS`, and within the tracker's ``limit`` [command units]."""
        return np.ascontiguousarray(np.minimum(command_limits - LIMIT_MARGIN_UNITS, self.limit), dtype=float)

    def _bind(self) -> None:
        """Where the law reads the schedule's arrays: (address, bytes per index) of
        the tick matrices, speed rows and E_k (per gain), and of the reference's count rates,
        the clamp and the feed-forward (per sample); the arrays are kept alive here."""
        s = self.s
        self._bound = [np.ascontiguousarray(a, dtype=float) for a in
                       (s.tick, s.speed_rows, s.record, s.acting_rate, self.limits, s.feedforward)]
        self._addresses = [(a.ctypes.data, a.strides[0]) for a in self._bound]

    def within_static_until(self, sample: int) -> None:
        """Clamp the commands of the schedule's samples before ``sample`` to the device's static
        limit less :data:`LIMIT_MARGIN_UNITS` whatever the speed: the approach from a measured
        state and the hold before the motion (a device falling after homing is braked from
        readings a few periods old, before the observer has converged, so its speed is known
        worst then; the gentle approach needs no headroom above the static limit)."""
        end = min(max(int(sample), 0), self.limits.shape[0])
        self.limits[:end] = np.minimum(self.limits[:end], self.s.saturation.static - LIMIT_MARGIN_UNITS)

    def start(self, counts: Any, issued_before: Any = None) -> None:
        """Set the observer at the first reading ``counts`` (3,) [counts], at rest, with the
        commands in flight ``issued_before`` (3,) [command units] (default zero force)."""
        self.xi[:] = 0.0
        self.xi[:3] = np.asarray(counts, dtype=float) - self.s.ref_counts[0]
        before = np.zeros(3) if issued_before is None else np.asarray(issued_before, dtype=float)
        for i in range(self.line):
            self.xi[9 + 3 * i:12 + 3 * i] = before - self.s.feedforward[0]
        self.last_tc = before.copy()
        self.k_next = 0
        self._past_tick[:] = -1
        self._ahead_at = -2
        self.started = True

    def update(self, k: int, counts: Any, slots: int = 1, fresh: bool = True,
               read_for: int | None = None) -> np.ndarray:
        """The commands (3,) [whole command units, float] for tick k from the ``counts`` (3,)
        read for tick ``read_for`` (None: the next tick the tracker expects; the reference and
        gains beyond the schedule's end hold the last sample; ``slots`` is not needed: the
        observer counts ticks). When ticks were missed (k beyond the next expected one, whose
        deadline passed before its command was sent), the reading corrects the observer at the
        tick it was read for, the device holds the last command through the missed ticks, and
        the command for k comes from the prediction. A reading read for an earlier tick (it
        arrived late: threaded I/O returned it when no newer status came in time, after a host
        stall) corrects the observer at that tick, which then predicts again through the
        commands the device had since (up to :data:`LATE_READING_TICKS` back; an older one is
        not used): taken as the expected tick's, a reading two periods old at speed is a
        tracking error of tens of counts to the observer, and the command swings by thousands.
        ``fresh`` False: no new reading came since the last one (threaded I/O returns the
        newest status again when none arrived in time): the observer predicts without a
        correction (a repeated reading is not a device that stopped)."""
        if not self.started:
            self.start(counts)
        if fresh and (read_for is None or read_for >= self.k_next):
            measured = np.asarray(counts, dtype=float)
            innovation = 0.0 if self.k_next == 0 else \
                float(np.abs(measured - self.s.ref_counts[self._sample(self.k_next)] - self.xi[:3]).max())
            if self._a_tick_ahead(measured, innovation):
                fresh = False
            else:
                read_for = self._delayed_tick(measured, innovation, read_for)
        if fresh and read_for is not None and read_for < self.k_next:
            if read_for >= 0 and k >= self.k_next:
                self._correct_past(read_for, np.asarray(counts, dtype=float))
            fresh = False                   # used at its own tick, or too old to use
        y = np.asarray(counts, dtype=float) - self.s.ref_counts[self._sample(self.k_next)] if fresh else None
        if k > self.k_next:
            self._tick(self.k_next, y, self.last_tc)
            for j in range(self.k_next + 1, k):
                self._tick(j, None, self.last_tc)
            y = None
        elif k < self.k_next and fresh:
            y = np.asarray(counts, dtype=float) - self.s.ref_counts[self._sample(k)]
        self.k_next = k + 1
        return self._tick(k, y, None)

    def _delayed_tick(self, counts: np.ndarray, innovation: float, read_for: int | None) -> int | None:
        """The earlier tick whose prediction explains a fresh ``counts`` (3,) [counts] that
        the next expected tick's does not (its ``innovation`` [counts], the most on a leg, above
        :data:`STALE_INNOVATION_COUNTS`): a status delayed on its way; else ``read_for``
        unchanged."""
        k = self.k_next
        if innovation <= STALE_INNOVATION_COUNTS or k == 0:
            return read_for
        best, best_error = read_for, STALE_MATCH_COUNTS
        for tick in range(k - 1, max(k - LATE_READING_TICKS, 0) - 1, -1):
            slot = tick % LATE_READING_TICKS
            if self._past_tick[slot] != tick:
                break
            error = np.abs(counts - self.s.ref_counts[self._sample(tick)] - self._past_xi[slot, :3]).max()
            if error <= best_error and 3.0 * error <= innovation:
                best, best_error = tick, error
        if best != read_for:
            self.redated += 1
        return best

    def _a_tick_ahead(self, counts: np.ndarray, innovation: float) -> bool:
        """Whether a fresh ``counts`` (3,) [counts], ``innovation`` [counts] (the most on a leg)
        from the expected tick's prediction, is the tick after's (:data:`AHEAD_INNOVATION_COUNTS`;
        not two ticks in a row; only with a command delay of a sample or more, so that the next
        tick's counts do not depend on the command about to be sent): the observer's prediction
        for that tick, without a correction now, explains it and the expected tick's does not."""
        k = self.k_next
        if k == 0 or self._acts_next_tick or self._ahead_at == k - 1 or innovation <= AHEAD_INNOVATION_COUNTS:
            return False
        g = int(self.s.index[self._sample(k)])
        nx = self.nx
        # the count rows of the prediction with no innovation (y = the predicted counts)
        predicted = self.s.tick[g][3:6, :nx] @ self.xi + self.s.tick[g][3:6, nx:] @ self.xi[:3]
        error = np.abs(counts - self.s.ref_counts[self._sample(k + 1)] - predicted).max()
        if error <= STALE_MATCH_COUNTS and 3.0 * error <= innovation:
            self.ahead += 1
            self._ahead_at = k
            return True
        return False

    def _correct_past(self, tick: int, counts: np.ndarray) -> None:
        """Correct the observer with ``counts`` read for the past ``tick`` and predict again up
        to the next expected tick through the commands the device had; nothing if ``tick`` is
        no longer remembered."""
        slots = np.arange(tick, self.k_next) % LATE_READING_TICKS
        if self.k_next - tick > LATE_READING_TICKS or \
                np.any(self._past_tick[slots] != np.arange(tick, self.k_next)):
            return
        self.xi[:] = self._past_xi[slots[0]]
        y = counts - self.s.ref_counts[self._sample(tick)]
        for j, slot in zip(range(tick, self.k_next), slots):
            self._tick(j, y if j == tick else None, self._past_tc[slot].copy())

    def _tick(self, k: int, y: np.ndarray | None, held: np.ndarray | None) -> np.ndarray:
        """One period of the law at tick k: correct with the reading's error ``y`` (3,) [counts]
        (None: no reading), then send the law's command, or the ``held`` one (the device kept
        it), and predict; returns the command sent."""
        slot = k % LATE_READING_TICKS
        self._past_tick[slot] = k
        self._past_xi[slot] = self.xi
        k = self._sample(k)
        g = int(self.s.index[k])
        buf, nx = self._buf, self.nx
        buf[:nx] = self.xi
        buf[nx:] = self.xi[:3] if y is None else y      # no reading: no innovation
        tc = self._law(k, g, held)
        self._past_tc[slot] = tc
        self.last_tc = tc
        return tc

    def _law(self, k: int, g: int, held: np.ndarray | None) -> np.ndarray:
        """The law's arithmetic at sample k (gains g) on [xi; y] in ``_buf``, one call of
        :func:`compiled_tick`: the command sent (the law's, clamped; or ``held``); the observer
        state predicted into ``xi``."""
        f = self.tick_function
        (tick, t_step), (rows, r_step), (record, e_step), (acting, a_step), (along, l_step), (ff, f_step) = \
            self._addresses
        f.feed(0, tick + g * t_step)
        f.feed(1, rows + g * r_step)
        f.feed(2, record + g * e_step)
        f.feed(4, acting + k * a_step)
        f.feed(5, along + k * l_step)
        f.feed(6, ff + k * f_step)
        if held is None:
            f.inputs[8][0] = 0.0
        else:
            f.inputs[7][:] = held
            f.inputs[8][0] = 1.0
        f()
        self.xi[:] = f.outputs[1]
        return f.outputs[0].copy()

    @property
    def predicted_rates(self) -> np.ndarray:
        """The count rates (SPEED_PERIODS, 3) [counts/s] the last command's clamp was set from:
        the motor speeds predicted for the periods it may act in."""
        return self.tick_function.outputs[2].reshape(SPEED_PERIODS, 3)

    def _sample(self, k: int) -> int:
        """The schedule's sample of tick k (the ends held)."""
        return min(max(k - self.offset, 0), self.s.samples - 1)

    def splice(self, tick: int, tail: GainSchedule) -> None:
        """Follow ``tail`` from ``tick`` on (its sample 0 at that tick), e.g. a brake
        (:func:`hold_design`). The observer's state (the deviation from the reference and the
        commands in flight) carries over unchanged, so the tail must continue the reference in
        position and rate at ``tick`` and share the observer and the command delay."""
        if tail.delay_samples != self.s.delay_samples or tail.gains.shape[1:] != self.s.gains.shape[1:]:
            raise InvalidParameterError("a spliced schedule must have the running one's command delay")
        self.s, self.offset = tail, int(tick)
        self.limits = self._below(tail.command_limits)
        self._bind()
        self._past_tick[:] = -1     # a late reading is not carried back across the splice

    def state(self) -> tuple[np.ndarray, np.ndarray, int]:
        """A copy of the observer state, the last command and the next tick (for
        :meth:`restore`)."""
        return self.xi.copy(), self.last_tc.copy(), self.k_next

    def restore(self, state: tuple[np.ndarray, np.ndarray, int]) -> None:
        """Go back to a :meth:`state`."""
        self.xi[:] = state[0]
        self.last_tc = state[1].copy()
        self.k_next = state[2]


__all__ = ["GainSchedule", "LqrTracker", "compiled_tick", "LqrWeights", "DelayModel", "carried_design", "design", "discretise", "hold_design", "lqr_system",
           "model_feedforward", "observer_gain"]
