"""Motion estimated from a falcon log: smoothed position, velocity and acceleration.

The encoder counts of a log are whole numbers, so the motion is estimated with care:
counts -> leg angles -> end-effector points by forward kinematics (a smooth map of the
quantised counts), then one zero-phase low-pass S (4th-order Butterworth run forwards and
backwards, cut-off :data:`DEFAULT_CUTOFF_HZ`) and central differences give the point
p = S(p_raw) [m], velocity v = D S(p_raw) [m/s] and acceleration a = D^2 S(p_raw) [m/s^2].
The logged commands go through the *same* filter S. Because S is linear and time-invariant it
commutes with the differences and (to first order) with the dynamics, so the inverse dynamics
of the filtered motion is compared with equally filtered commands and their difference is
not a filter artefact. (A Savitzky-Golay differentiator was tried first: its derivative and
smoothing kernels have different frequency responses, and on nominal simulated data it left
a 15 command-unit residual where this consistent filter leaves 2-3.)

Lost samples (gaps in ``t``): a gap of at most :data:`BRIDGE_S` is bridged (the device
moved on while the host skipped ticks: its counts are interpolated there and the command it
held is the last one sent, the firmware's zero-order hold), so a log recorded on a busy host
that skips a tick every few tens of milliseconds is still usable. Longer gaps split the log
into runs; samples whose filter window would cross such a gap or an end are marked invalid
(``valid``) and left out of every fit.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.signal import butter, sosfiltfilt

from falcon_plan.errors import InvalidParameterError, LogFormatError
from falcon_plan.falconlog import END_KEY, parse_rate_hz
from falcon_plan.model.kinematics import counts_to_angles, forward_kinematics, jacobian
from falcon_plan.model.params import ACRA2009, FalconParams

if TYPE_CHECKING:
    from falcon_plan.falconlog import FalconLog

LOG = logging.getLogger(__name__)

DEFAULT_CUTOFF_HZ = 20.0
"""Cut-off of the zero-phase low-pass [Hz]: it averages the count quantisation (the residual
noise on nominal simulated data is ~2.7 command units) and keeps the PD loop's closed-loop
band (~8 Hz). Friction is not linear in the velocity, so near reversals the filtered
commands and the friction of the filtered velocity differ; a lower cut-off widens that
zone (at 15 Hz a Stribeck amplitude came out 20 % low, at 20 Hz 14 %)."""
FILTER_ORDER = 4
EDGE_S = 0.05
"""Samples this close [s] to a gap or an end are left out (the filter's edge transient)."""
BRIDGE_S = 0.025
"""Gaps of at most this long [s] are bridged (see the module docstring): the motion over a
gap that short is smooth on the low-pass's time scale (1 / cut-off = 50 ms)."""
MIN_VALID_SAMPLES = 100
"""Identification needs at least this many valid samples (see :func:`estimate_motion`)."""


def require_samples(log: FalconLog, what: str = "the log") -> None:
    """Raise :class:`LogFormatError` when ``log`` (``what`` names it) has fewer than
    :data:`MIN_VALID_SAMPLES` rows: nothing can be identified from it (e.g. a log whose run
    stopped before its first sample has a header and no rows)."""
    n = len(np.asarray(log.t_s))
    if n < MIN_VALID_SAMPLES:
        raise LogFormatError(f"{what} has {n} samples; identification needs at least {MIN_VALID_SAMPLES}")


def warn_if_cut_short(log: FalconLog, what: str = "the log") -> None:
    """Warn (once per call: the workflow calls it once per log) when the run ``log`` (``what``
    names it) records did not complete (its end line, :data:`~falcon_plan.falconlog.END_KEY`): it holds less of
    its excitation than was designed."""
    end = (log.meta or {}).get(END_KEY)
    if end is not None and end != "completed":
        t = np.asarray(log.t_s, float)
        LOG.warning("%s records a run that ended %r after %.2f s: it holds only part of its excitation "
                    "(record it again for the whole)", what, end, float(t[-1] - t[0]))


def log_rate_hz(log: FalconLog, rate_hz: float | None = None) -> float:
    """The log's sample rate [Hz]: the argument if given, else the ``rate_hz`` metadata.

    Raises :class:`LogFormatError` naming the ``--rate`` option when neither is there.
    """
    if rate_hz is not None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidParameterError(f"rate must be a positive number of Hz, got {rate_hz}")
        return float(rate_hz)
    try:
        value = parse_rate_hz(dict(log.meta or {}))
    except LogFormatError as exc:
        raise LogFormatError(f"{exc}; give the control rate with --rate HZ (python: rate_hz=...)") from exc
    if value is None:
        raise LogFormatError("the log has no 'rate_hz' metadata; give the control rate with "
                             "--rate HZ (python: rate_hz=...)")
    return value


def sample_index(t_s: np.ndarray, rate_hz: float) -> np.ndarray:
    """Whole sample numbers k of times ``t_s`` [s] at ``rate_hz`` (t = t0 + k / rate); a lost
    sample shows as a jump of k by more than one. Raises when times are off the grid."""
    k_real = (np.asarray(t_s, float) - float(t_s[0])) * rate_hz
    k = np.rint(k_real).astype(np.int64)
    if np.any(np.abs(k_real - k) > 0.25):
        bad = int(np.argmax(np.abs(k_real - k) > 0.25))
        raise LogFormatError(f"log time t={t_s[bad]:.6f} s (row {bad}) is off the {rate_hz:g} Hz "
                             "sample grid; is the rate right? (--rate HZ)")
    if np.any(np.diff(k) <= 0):
        raise LogFormatError("log times must increase strictly")
    return k


@dataclass(frozen=True)
class MotionEstimate:
    """Smoothed motion of one log, all arrays with time first.

    Attributes
    ----------
    t_s : (N,) sample times [s]; k : (N,) whole sample numbers.
    rate_hz : control rate [Hz].
    counts : (N, 3) logged encoder counts (float).
    theta1_rad, theta1_dot_rad_s : (N, 3) smoothed leg angles [rad] and rates [rad/s].
    position_m, velocity_m_s, acceleration_m_s2 : (N, 3) smoothed end-effector motion.
    commands : (N, 3) logged commands (float); commands_smooth the same, low-passed.
    reference : (N, 3) logged reference counts, or None.
    valid : (N,) True away from gaps and ends (see :data:`EDGE_S`).
    cutoff_hz : cut-off of the low-pass that smoothed the motion [Hz].
    bridge_samples : gaps of at most this many missing samples were bridged (:data:`BRIDGE_S`).
    """

    t_s: np.ndarray
    k: np.ndarray
    rate_hz: float
    counts: np.ndarray
    theta1_rad: np.ndarray
    theta1_dot_rad_s: np.ndarray
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    acceleration_m_s2: np.ndarray
    commands: np.ndarray
    commands_smooth: np.ndarray
    reference: np.ndarray | None
    valid: np.ndarray
    cutoff_hz: float
    bridge_samples: int = 0
    """Gaps of at most this many missing samples were bridged (:data:`BRIDGE_S`): the command
    held through them is the last one logged."""

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t_s.shape[0])

    def shifted_commands(self, delay_samples: float, smooth: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Commands that act at each sample under a transport delay of ``delay_samples``
        (may be fractional: a command held over a control period acts, on average, half a
        sample after the period starts): row i holds the command logged at sample
        k_i - delay, interpolated linearly between samples (``smooth``: from the low-passed
        commands, else the logged ones). Returns (commands (N, 3),
        ok (N,) False where a needed sample is not in the log)."""
        source = self.commands_smooth if smooth else self.commands
        lookup = np.full(int(self.k[-1]) + 1, -1, dtype=np.int64)
        lookup[self.k] = np.arange(self.n)
        if self.bridge_samples:  # a slot in a bridged gap: the firmware held the last command
            slots = np.arange(lookup.size)
            last = np.searchsorted(self.k, slots, side="right") - 1
            held = (last >= 0) & (lookup < 0) & (slots - self.k[np.maximum(last, 0)] <= self.bridge_samples)
            lookup[held] = last[held]
        whole = math.floor(delay_samples)
        frac = float(delay_samples) - whole
        out = np.zeros_like(source)
        ok = np.ones(self.n, dtype=bool)
        for shift, weight in ((whole, 1.0 - frac), (whole + 1, frac)):
            if weight == 0.0:
                continue
            want = self.k - shift
            idx = np.where(want >= 0, lookup[np.clip(want, 0, None)], -1)
            good = idx >= 0
            ok &= good
            out[good] += weight * source[idx[good]]
        out[~ok] = 0.0
        return out, ok


def _runs(k: np.ndarray) -> list[np.ndarray]:
    """Index arrays of the contiguous runs of sample numbers k (gaps split runs)."""
    breaks = np.flatnonzero(np.diff(k) != 1) + 1
    return np.split(np.arange(k.shape[0]), breaks)


def _filter_runs(x: np.ndarray, k: np.ndarray, sos: np.ndarray, h: float, deriv: int) -> np.ndarray:
    """S(x) differentiated ``deriv`` times (central differences), run by run; runs too short
    to filter are left as they are (and marked invalid by the caller)."""
    out = np.array(x, dtype=float)
    for idx in _runs(k):
        if idx.size > 30:
            y = sosfiltfilt(sos, x[idx], axis=0)
            for _ in range(deriv):
                y = np.gradient(y, h, axis=0)
            out[idx] = y
        elif deriv:
            out[idx] = 0.0
    return out


def estimate_motion(log: FalconLog, rate_hz: float | None = None, params: FalconParams = ACRA2009,
                    cutoff_hz: float = DEFAULT_CUTOFF_HZ) -> MotionEstimate:
    """Estimate the motion of a falcon log (see the module docstring).

    ``log`` is a FalconLog (t_s, enc, tc, ref, meta); ``rate_hz`` [Hz] overrides its rate
    metadata; ``params`` the parameter set that turns counts into angles and points;
    ``cutoff_hz`` [Hz] the low-pass cut-off.
    """
    rate = log_rate_hz(log, rate_hz)
    t = np.asarray(log.t_s, float)
    require_samples(log)
    if not 0 < cutoff_hz < 0.4 * rate:
        raise InvalidParameterError(f"cutoff {cutoff_hz} Hz must be in (0, {0.4 * rate:g}) Hz")
    k = sample_index(t, rate)
    sos = butter(FILTER_ORDER, cutoff_hz, btype="low", fs=rate, output="sos")
    h = 1.0 / rate
    counts = np.asarray(log.enc, float)
    commands = np.asarray(log.tc, float)
    # the grid the filters run on: the logged slots and the slots of the gaps short enough to bridge
    grid = _bridged_grid(k, int(math.floor(BRIDGE_S * rate + 1e-9)))
    row = np.searchsorted(k, grid, side="right") - 1          # the last logged row at each slot
    at_rows = np.searchsorted(grid, k)
    theta_grid = np.stack([np.interp(grid, k, counts_to_angles(counts[:, i], params)) for i in range(3)], axis=1)
    p_raw = forward_kinematics(theta_grid, params)
    p = _filter_runs(p_raw, grid, sos, h, 0)[at_rows]
    v = _filter_runs(p_raw, grid, sos, h, 1)[at_rows]
    a = _filter_runs(p_raw, grid, sos, h, 2)[at_rows]
    theta = _filter_runs(theta_grid, grid, sos, h, 0)[at_rows]
    theta_dot = np.einsum("nij,nj->ni", jacobian(p, params), v)
    commands_smooth = _filter_runs(commands[row], grid, sos, h, 0)[at_rows]   # held through a gap
    ref = None if log.ref is None else np.asarray(log.ref, float)
    edge = max(2, int(round(EDGE_S * rate)))
    valid_grid = np.zeros(grid.shape[0], dtype=bool)
    for idx in _runs(grid):
        if idx.size > 2 * edge + 30:
            valid_grid[idx[edge:idx.size - edge]] = True
    return MotionEstimate(t_s=t, k=k, rate_hz=rate, counts=counts, theta1_rad=theta,
                          theta1_dot_rad_s=theta_dot, position_m=p, velocity_m_s=v,
                          acceleration_m_s2=a, commands=commands, commands_smooth=commands_smooth,
                          reference=ref, valid=valid_grid[at_rows], cutoff_hz=cutoff_hz,
                          bridge_samples=int(math.floor(BRIDGE_S * rate + 1e-9)))


def _bridged_grid(k: np.ndarray, bridge: int) -> np.ndarray:
    """The slots ``k`` (increasing) plus every slot inside a gap of at most ``bridge`` missing
    slots."""
    dk = np.diff(k)
    fill = [np.arange(k[i] + 1, k[i + 1]) for i in np.flatnonzero((dk > 1) & (dk - 1 <= bridge))]
    return np.sort(np.concatenate([k, *fill])) if fill else np.asarray(k)


PHASES = ("hold", "reversal", "high_speed", "high_acceleration", "other")
"""Motion phases used to locate a discrepancy (a sample belongs to the first that applies)."""


def motion_phases(motion: MotionEstimate) -> np.ndarray:
    """Phase label per sample and leg of ``motion``, shape (N, 3), values from :data:`PHASES`.

    - hold: |theta1_dot| below 0.05 rad/s (about 80 counts/s) on that leg for 50 ms around;
    - reversal: theta1_dot changes sign within +-20 ms;
    - high_speed: |theta1_dot| in the top 20 % of the log (per leg);
    - high_acceleration: |theta1_ddot| in the top 20 % of the log (per leg);
    - other: the rest.
    """
    w = motion.theta1_dot_rad_s
    n = motion.n
    rate = motion.rate_hz
    acc = np.gradient(w, 1.0 / rate, axis=0)
    labels = np.full((n, 3), "other", dtype=object)
    half_hold = max(1, int(0.025 * rate))
    half_rev = max(1, int(0.02 * rate))
    slow = np.abs(w) < 0.05
    sign = np.sign(w)
    for leg in range(3):
        hold = np.convolve(slow[:, leg].astype(float), np.ones(2 * half_hold + 1), "same") >= 2 * half_hold + 1
        flips = np.flatnonzero(np.diff(sign[:, leg]) != 0)
        rev = np.zeros(n, dtype=bool)
        for f in flips:
            rev[max(0, f - half_rev):f + half_rev + 1] = True
        fast = np.abs(w[:, leg]) >= np.quantile(np.abs(w[:, leg]), 0.8)
        hacc = np.abs(acc[:, leg]) >= np.quantile(np.abs(acc[:, leg]), 0.8)
        lab = labels[:, leg]
        lab[hacc] = "high_acceleration"
        lab[fast] = "high_speed"
        lab[rev & ~hold] = "reversal"
        lab[hold] = "hold"
    return labels
