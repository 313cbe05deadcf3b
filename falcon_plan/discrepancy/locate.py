"""Locating a discrepancy: where, when, at what frequency and lag the model and a log disagree.

From the inverse-dynamics residual r = Tc(logged, delayed) - ID(measured motion) [command
units] of the nominal and of the corrected model:

- per leg RMS, and per leg and motion phase (hold, reversal, high speed, high acceleration);
- the residual spectrum in frequency bands (and its peak frequency);
- the lag: the RMS of the residual against the assumed extra delay (0..6 samples) and the lag
  of the peak cross-correlation between residual and command rate;
- the windowed open-loop replay error (80 ms windows re-initialised from the measured state).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from falcon_plan.discrepancy.motion import PHASES, MotionEstimate, motion_phases
from falcon_plan.discrepancy.replay import windowed_replay
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import NOMINAL, Effects

BANDS_HZ = ((0.0, 1.0), (1.0, 3.0), (3.0, 8.0), (8.0, 15.0), (15.0, 30.0))
MAX_LAG_SAMPLES = 6


@dataclass
class Localisation:
    """Summaries (JSON via :meth:`to_dict`) and the arrays behind the plots.

    Per leg, in command units unless the name says counts: ``rms_per_leg_nominal`` /
    ``rms_per_leg_corrected`` the inverse-dynamics residual RMS under the nominal / corrected
    model; ``rms_per_phase_nominal`` the nominal RMS per motion phase (None where the phase
    has too few samples); ``band_rms_nominal`` its RMS per frequency band; ``peak_frequency_hz``
    its spectral peak [Hz]; ``rms_vs_extra_delay`` the nominal RMS (all legs) for 0, 1, ...
    extra samples of delay and ``best_extra_delay`` the lowest; ``xcorr_lag_samples`` the lag of
    the largest cross-correlation with the command rate [samples]; and
    ``window_end_rms_counts_nominal`` / ``window_end_rms_counts_corrected`` the windowed
    open-loop replay error at the windows' ends [counts] (NaN when not run).
    """

    rms_per_leg_nominal: list[float]
    rms_per_leg_corrected: list[float]
    rms_per_phase_nominal: dict[str, list[float | None]]
    band_rms_nominal: dict[str, list[float]]
    peak_frequency_hz: list[float]
    rms_vs_extra_delay: list[float]
    best_extra_delay: int
    xcorr_lag_samples: list[int]
    window_end_rms_counts_nominal: list[float]
    window_end_rms_counts_corrected: list[float]
    arrays: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summaries (command units unless the key says counts)."""
        return {k: v for k, v in self.__dict__.items() if k != "arrays"}


def _residual(motion: MotionEstimate, model: FalconModel, delay: float,
              tc: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Residual (N, 3) [command units] and the mask of samples where it is defined; ``tc``
    the model's inverse dynamics of the motion if already computed."""
    cmd, ok = motion.shifted_commands(delay)
    if tc is None:
        tc = model.inverse_dynamics(motion.position_m, motion.velocity_m_s, motion.acceleration_m_s2)
    use = ok & motion.valid
    return np.where(use[:, None], cmd - tc, 0.0), use


def locate(motion: MotionEstimate, model: FalconModel, corrected: Effects,
           nominal_delay: float, windows: bool = True) -> Localisation:
    """Localise the nominal model's residual on ``motion`` and compare with ``corrected``
    (``model``: the parameter set; ``nominal_delay``: the command delay [samples] before any
    fitted extra; ``windows``: also run the windowed open-loop replay)."""
    nominal = model.with_effects(NOMINAL)
    fitted = model.with_effects(corrected)
    tc_nom = nominal.inverse_dynamics(motion.position_m, motion.velocity_m_s, motion.acceleration_m_s2)
    r_nom, use = _residual(motion, nominal, nominal_delay, tc_nom)
    r_cor, use_c = _residual(motion, fitted, nominal_delay + corrected.extra_delay_samples)
    both = use & use_c

    def rms(x: np.ndarray, sel: np.ndarray) -> list[float]:
        return [float(np.sqrt(np.mean(x[sel, i] ** 2))) if sel.any() else float("nan") for i in range(3)]

    phases = motion_phases(motion)
    per_phase: dict[str, list[float | None]] = {}
    for ph in PHASES:
        row: list[float | None] = []
        for leg in range(3):
            sel = use & (phases[:, leg] == ph)
            row.append(float(np.sqrt(np.mean(r_nom[sel, leg] ** 2))) if sel.sum() > 10 else None)
        per_phase[ph] = row

    # spectrum of the nominal residual (valid stretch, Hann window)
    x = r_nom[use] - r_nom[use].mean(axis=0)
    freqs = np.fft.rfftfreq(x.shape[0], 1.0 / motion.rate_hz)
    spec = np.abs(np.fft.rfft(x * np.hanning(x.shape[0])[:, None], axis=0)) ** 2
    total = spec.sum(axis=0) + 1e-300
    band_rms = {}
    overall = np.sqrt(np.mean(x ** 2, axis=0))
    for lo, hi in BANDS_HZ:
        sel = (freqs >= lo) & (freqs < hi)
        band_rms[f"{lo:g}-{hi:g} Hz"] = [float(v) for v in overall * np.sqrt(spec[sel].sum(axis=0) / total)]
    peak = [float(freqs[1:][np.argmax(spec[1:, i])]) for i in range(3)]

    # lag: residual RMS against the assumed delay, and cross-correlation with the command rate
    scan = []
    for extra in range(MAX_LAG_SAMPLES + 1):
        r, u = _residual(motion, nominal, nominal_delay + extra, tc_nom)
        scan.append(float(np.sqrt(np.mean(r[u & use] ** 2))))
    dcmd = np.gradient(motion.commands_smooth, axis=0)
    lags = []
    for leg in range(3):
        a = r_nom[use, leg] - r_nom[use, leg].mean()
        b = dcmd[use, leg] - dcmd[use, leg].mean()
        cc = [float(np.dot(a[max(0, l):len(a) + min(0, l)], b[max(0, -l):len(b) - max(0, l)]))
              for l in range(-MAX_LAG_SAMPLES, MAX_LAG_SAMPLES + 1)]
        lags.append(int(np.argmax(np.abs(cc))) - MAX_LAG_SAMPLES)

    whole = int(round(nominal_delay - 0.5))
    e_nom = e_cor = np.zeros((0, 1, 3))
    if windows:
        _, e_nom = windowed_replay(motion, nominal, whole)
        e_cor = e_nom if corrected == NOMINAL else \
            windowed_replay(motion, fitted, whole + corrected.extra_delay_samples)[1]
    end_rms = lambda e: [float(np.sqrt(np.mean(e[:, -1, i] ** 2))) if e.size else float("nan")
                         for i in range(3)]
    return Localisation(
        rms_per_leg_nominal=rms(r_nom, use), rms_per_leg_corrected=rms(r_cor, both),
        rms_per_phase_nominal=per_phase, band_rms_nominal=band_rms, peak_frequency_hz=peak,
        rms_vs_extra_delay=scan, best_extra_delay=int(np.argmin(scan)), xcorr_lag_samples=lags,
        window_end_rms_counts_nominal=end_rms(e_nom), window_end_rms_counts_corrected=end_rms(e_cor),
        arrays={"theta1_dot": motion.theta1_dot_rad_s, "residual_nominal": r_nom,
                "residual_corrected": r_cor, "use": use, "t": motion.t_s, "theta1": motion.theta1_rad,
                "command": motion.commands_smooth})
