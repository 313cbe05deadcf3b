"""The smooth effects, the command delay and the encoder offset: evidence and fits on the
inverse-dynamics residual of the training log (greedy selection by BIC with an effective sample
size), and the blocked cross-validation gate that each chosen effect must pass.

The encoder home-angle offset is searched as a scalar: each trial re-reads the counts with
that home angle and refits the rest on the inverse-dynamics residual.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from falcon_plan.discrepancy.identify import (ResidualProblem, SmoothFit, autocorrelation_time,
                                              fit_effect_set, fit_smooth)
from falcon_plan.discrepancy.library import CANDIDATES
from falcon_plan.discrepancy.motion import estimate_motion
from falcon_plan.discrepancy.search import curvature, parabolic_minimum
from falcon_plan.discrepancy.select import Evaluation, Selection, bic, greedy_select
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.effects import SMOOTH_EFFECT_FIELDS

LOG = logging.getLogger(__name__)

ENCODER_SEARCH_RAD = (-0.2, 0.2)
"""Range [rad] searched for the encoder home-angle offset (about +-11 deg)."""
ENCODER_GRID_POINTS = 9
"""The encoder-offset search starts from this many offsets evenly over ENCODER_SEARCH_RAD."""
ENCODER_TOLERANCE_RAD = 2e-4
"""Tolerance [rad] of the encoder-offset search (parabolic steps from the grid)."""
ENCODER_MAX_REFINE = 8
"""At most this many refits refine the encoder offset after its grid."""
CV_FOLDS = 4
"""Contiguous blocks of the blocked cross-validation of the inverse-dynamics fits."""
CV_MIN_GAIN = 0.05
"""An effect must lower the cross-validated residual by at least this fraction."""


class SmoothStage:
    """Evidence and fits of the smooth effects, the delay and the encoder offset on the
    inverse-dynamics residual, and their blocked cross-validation.

    Parameters
    ----------
    log : the training log (re-read with other home angles for the encoder offset).
    rate_hz : its control rate [Hz].
    problem : the inverse-dynamics residual of the log (nominal model, nominal delay).
    names : the candidates of kind smooth, delay or encoder to consider.
    threshold : delta BIC an effect must win to be named.
    """

    def __init__(self, log: FalconLog, rate_hz: float, problem: ResidualProblem, names: list[str],
                 threshold: float) -> None:
        self.log, self.rate_hz = log, rate_hz
        self.problem = problem
        self.names = names
        base = problem.model.effect_vector
        full = fit_effect_set(problem, [CANDIDATES[n] for n in names if CANDIDATES[n].kind != "encoder"], base)
        # Effective sample size from the residual of the fullest model (mostly noise).
        self.tau = autocorrelation_time(full.residual)
        self.base = base
        self.threshold = threshold
        self._done: dict[tuple[str, ...], Evaluation] = {}
        self._problems = problem.home_variants   # shared by every stage on this problem
        self._problems.setdefault(0.0, problem)
        self._consistency: dict[tuple, dict | None] = {}

    def consistency(self, chosen: tuple[str, ...], values: dict[str, float]) -> dict | None:
        """:func:`consistency_check` of ``chosen`` with ``values`` on this stage, computed once
        (the stretched-fit check and the model-form check both ask)."""
        key = (chosen, tuple(sorted(values.items())))
        if key not in self._consistency:
            self._consistency[key] = consistency_check(self, chosen, values)
        return self._consistency[key]

    def problem_at(self, offset_rad: float) -> ResidualProblem:
        """The residual problem of the log read with the home angle moved by ``offset_rad``."""
        key = round(float(offset_rad), 6)
        if key not in self._problems:
            params = self.problem.model.params
            params = params.replace(theta_home_rad=params.theta_home_rad + key)
            motion = estimate_motion(self.log, self.rate_hz, params, self.problem.motion.cutoff_hz)
            self._problems[key] = ResidualProblem(self.problem.model, motion, self.problem.nominal_delay,
                                                  self.problem.stride, self.problem.start_s)
        return self._problems[key]

    def _fit(self, names: tuple[str, ...], start: dict[str, float] | None,
             rows: np.ndarray | None = None, offset: float | None = None) -> tuple[SmoothFit, float, float]:
        """(fit, encoder offset, its std): the smooth/delay fit of ``names``; with
        ``encoder_offset`` among them, a bounded search of the offset (each trial refits the
        rest on the log re-read with that home angle) unless ``offset`` fixes it."""
        inner = [CANDIDATES[n] for n in names if CANDIDATES[n].kind != "encoder"]
        if "encoder_offset" not in names:
            return fit_effect_set(self.problem, inner, self.base, inflation=self.tau, start=start, rows=rows), 0.0, 0.0
        fits: dict[float, SmoothFit] = {}

        def fit_at(d: float) -> SmoothFit:
            key = round(float(d), 9)
            if key not in fits:
                fits[key] = fit_effect_set(self.problem_at(d), inner, self.base, inflation=self.tau,
                                           start=start, rows=rows)
            return fits[key]

        def mean_square(d: float) -> float:
            fit = fit_at(d)
            return fit.rss / max(fit.n, 1)

        if offset is not None:
            return fit_at(offset), offset, 0.0
        grid = np.linspace(*ENCODER_SEARCH_RAD, ENCODER_GRID_POINTS)
        points = {float(d): mean_square(d) for d in grid}
        best, f0 = parabolic_minimum(mean_square, points, *ENCODER_SEARCH_RAD, ENCODER_TOLERANCE_RAD,
                                     ENCODER_MAX_REFINE)
        best = round(best, 6)
        fit = fit_at(best)
        # std of the offset from the curvature of the mean square residual at the minimum
        curv = curvature(points, best)
        std = math.sqrt(2 * f0 * self.tau / (fit.n * curv)) if curv > 0 else math.inf
        return fit, best, std

    def evaluate(self, names: tuple[str, ...]) -> Evaluation:
        """Fit a set of candidates and score it (BIC, inverse-dynamics residual)."""
        # warm start from the best fitted subset with one effect fewer (nonlinear fits)
        parents = [self._done[k] for k in self._done if len(k) == len(names) - 1 and set(k) <= set(names)]
        start = min(parents, key=lambda e: e.rss).values if parents else None
        # a fitted subset that located the encoder offset fixes it for this set (each trial
        # offset re-reads the whole log, too slow to repeat for every set of every round)
        located = [e for e in parents if "encoder_offset_rad" in e.values]
        if "encoder_offset" in names and located:
            fit, offset, _ = self._fit(names, start, offset=located[0].values["encoder_offset_rad"])
            offset_std = located[0].std["encoder_offset_rad"]
        else:
            fit, offset, offset_std = self._fit(names, start)
        values = dict(fit.values)
        std = dict(fit.std)
        if "command_delay" in names:
            values["extra_delay_samples"] = float(fit.extra_delay)
            std["extra_delay_samples"] = 0.0
        if "encoder_offset" in names:
            values["encoder_offset_rad"], std["encoder_offset_rad"] = offset, offset_std
        k = sum(CANDIDATES[n].n_parameters for n in names)
        ev = Evaluation(names, values, std, fit.rss, fit.n, k,
                        bic(fit.rss, fit.n, k, fit.n / self.tau), fit)
        self._done[tuple(sorted(names))] = ev
        return ev

    def cross_validated_rss(self, names: tuple[str, ...]) -> float:
        """Blocked cross-validation: the log's used samples in CV_FOLDS contiguous blocks; each
        block's residual at the parameters fitted on the other blocks, summed [command^2].
        (The delay and the encoder offset stay at their full-data values.)"""
        ev = self._done.get(tuple(sorted(names))) or self.evaluate(names)
        offset = ev.values.get("encoder_offset_rad", 0.0)
        problem = self.problem_at(offset)
        m = problem.rows.size
        folds = np.minimum((np.arange(m) * CV_FOLDS) // m, CV_FOLDS - 1)
        delay = int(ev.values.get("extra_delay_samples", 0))
        inner = tuple(n for n in names if CANDIDATES[n].kind == "smooth")
        params = [p for n in inner for p in CANDIDATES[n].parameters]
        total = 0.0
        for fold in range(CV_FOLDS):
            test = folds == fold
            fit = fit_smooth(problem, params, self.base, delay, ev.values, rows=~test) if params else None
            eff = fit.eff if fit is not None else self.base
            r = problem.residual(eff, delay)[test]
            total += float(np.sum(r ** 2))
        return total

    def select(self) -> Selection:
        """Greedy forward selection with the backward check over the candidates."""
        return greedy_select(self.evaluate, self.names, self.threshold)



def cross_validation_gate(stage: SmoothStage, sel: Selection) -> tuple[list[str], dict[str, float]]:
    """Drop from ``sel`` (the selection of ``stage``, in place) every chosen effect whose removal raises the blocked
    cross-validated residual by less than CV_MIN_GAIN (the weakest first, then re-check).
    Returns the dropped names and each kept effect's gain (fraction of the CV residual
    without it that it removes)."""
    dropped: list[str] = []
    gains: dict[str, float] = {}
    while sel.chosen:
        with_all = stage.cross_validated_rss(sel.chosen)
        gains = {}
        for name in sel.chosen:
            without = stage.cross_validated_rss(tuple(n for n in sel.chosen if n != name))
            gains[name] = (without - with_all) / without if without > 0 else 0.0
        weakest = min(gains, key=lambda n: gains[n])
        if gains[weakest] >= CV_MIN_GAIN:
            break
        LOG.info("cross-validation drops %s (gain %.3f)", weakest, gains[weakest])
        dropped.append(weakest)
        sel.chosen = tuple(n for n in sel.chosen if n != weakest)
        key = tuple(sorted(sel.chosen))
        if key not in sel.evaluations:
            sel.evaluations[key] = stage.evaluate(key)
    return dropped, gains



CONSISTENCY_SPLITS = ("time", "command")
"""How the used samples are halved for the consistency check: the first and second half of
the run (an effect that acts in time, a drift), and the smaller and larger acting commands
(an effect that acts on the command, a dead band)."""
CONSISTENCY_SIGMAS = 4.0
CONSISTENCY_MIN_RELATIVE = 0.3
"""A named effect's parameter is inconsistent when its fits on the two halves of a split
differ by more than this many combined standard deviations AND by more than this fraction of
its full-data value (or of the candidate's typical size, if larger)."""


ROUNDED_FIELDS = ("kd_sign",)
"""Fitted as a continuous factor and rounded (to a sign): its range says nothing of a stretch."""
STRETCH_SHARE = 0.01
"""A fitted value within this share of its range from the range's upper end (or from a
lower end that is not zero, the natural "absent" of a torque or mass) is stretched."""


def consistency_check(stage: SmoothStage, chosen: tuple[str, ...], values: dict[str, float]) -> dict | None:
    """Do the named smooth effects ``chosen`` (fitted ``values``, Effects field -> value) of
    the smooth ``stage`` hold across the data, or did they stretch to cover a shape no candidate has? Each split of
    :data:`CONSISTENCY_SPLITS` halves the used samples; the chosen parameters are refitted on
    each half (the delay and encoder offset at their fitted values). Returns None when every
    parameter agrees (:data:`CONSISTENCY_SIGMAS`, :data:`CONSISTENCY_MIN_RELATIVE`), else the
    worst disagreement: split, parameter, the two values and their standard deviations, and
    the split's words for where it sits."""
    inner = [n for n in chosen if CANDIDATES[n].kind == "smooth"]
    params = [p for n in inner for p in CANDIDATES[n].parameters]
    if not params:
        return None
    problem = stage.problem_at(values.get("encoder_offset_rad", 0.0))
    delay = int(values.get("extra_delay_samples", 0))
    measured, _ = problem.measured(delay)
    rows = problem.rows
    keys = {"time": problem.motion.t_s[rows], "command": np.abs(measured).mean(axis=1)}
    words = {"time": ("the first half of the run", "the second half of the run"),
             "command": ("small commands", "large commands")}
    worst: dict | None = None
    for p in params:  # a value the fit pushed to the edge of its range: the candidate was stretched
        if p.field in ROUNDED_FIELDS:
            continue
        lo, hi = p.lower, p.upper
        value = values.get(p.field, p.nominal)
        span = (hi - lo) if math.isfinite(hi - lo) else abs(value)
        if (value >= hi - STRETCH_SHARE * span) or (lo != 0.0 and value <= lo + STRETCH_SHARE * span):
            return {"split": "bound", "field": p.field, "values": [value], "std": [values.get(p.field)],
                    "sigmas": math.inf, "relative": math.inf, "halves": [f"the bound of its range [{lo:g}, {hi:g}]"]}
    for split in CONSISTENCY_SPLITS:
        low = keys[split] <= np.median(keys[split])
        fits = [fit_smooth(problem, params, stage.base, delay, values, inflation=stage.tau, rows=mask)
                for mask in (low, ~low)]
        for p in params:
            a, b = fits[0].values[p.field], fits[1].values[p.field]
            sd = math.hypot(fits[0].std.get(p.field, math.inf), fits[1].std.get(p.field, math.inf))
            size = max(abs(values.get(p.field, p.nominal) - (p.nominal if math.isfinite(p.nominal) else 0.0)),
                       p.scale)
            sigmas = abs(a - b) / sd if sd > 0 else math.inf
            relative = abs(a - b) / size
            if p.field in ROUNDED_FIELDS and math.copysign(1.0, a) == math.copysign(1.0, b):
                continue   # only its sign is used: the halves agree
            if sigmas > CONSISTENCY_SIGMAS and relative > CONSISTENCY_MIN_RELATIVE and \
                    (worst is None or relative > worst["relative"]):
                worst = {"split": split, "field": p.field, "values": [a, b],
                         "std": [fits[0].std.get(p.field), fits[1].std.get(p.field)],
                         "sigmas": sigmas, "relative": relative, "halves": list(words[split])}
            LOG.debug("consistency %s %s: %.4g vs %.4g (%.1f sigma, %.2f relative)", split, p.field, a, b,
                      sigmas, relative)
    return worst


SHAPES = ("command dead band", "gain drift", "cogging")
"""Shapes of the inverse-dynamics residual that no candidate of the library has, each a
plausible fault of a real Falcon a user can act on (:func:`shape_check`):

- command dead band: the motors ignore commands below some size; the logged commands are
  larger than the dynamics need by about that size, with the sign of the command (a
  friction would have the sign of the motion);
- gain drift: the motor gain changes over the run (heating); the residual grows with time in
  proportion to the command (a gain error would not change in time); fitted with its level
  (the motor-gain candidate's column: the gain's mean over the run), so that an effect named
  for that mean is weighed against a drifting gain, not against a drift about nominal;
- cogging: a torque periodic in the motor angle (c cycles per motor turn, c searched among
  :data:`COGGING_CYCLES`)."""
COGGING_CYCLES = (6, 8, 12, 16, 24)
"""Cogging periods tried [cycles per motor turn]."""
SHAPE_MIN_GAIN = 0.1
"""A shape must remove at least this share of the residual left by the named effects."""


def _least_squares_rss(r: np.ndarray, columns: np.ndarray) -> float:
    if columns.shape[1] == 0:
        return float(r @ r)
    coef, *_ = np.linalg.lstsq(columns, r, rcond=None)
    resid = r - columns @ coef
    return float(resid @ resid)


def shape_check(stage: SmoothStage, chosen: tuple[str, ...], values: dict[str, float]) -> dict | None:
    """Does the inverse-dynamics residual follow a shape of :data:`SHAPES` that the named
    smooth effects ``chosen`` (fitted ``values``) do not have? Linearised at the nominal
    model: the residual r0, the named effects' columns J, a shape's columns S. A shape is
    found when, on top of J, it lowers BIC by more than the stage's threshold and removes at
    least :data:`SHAPE_MIN_GAIN` of what J leaves. Returns None, or the strongest shape: its
    name, delta BIC on top of the named effects, the share it removes, and whether the named
    effects are still needed beside it (their delta BIC given the shape above the threshold;
    if not, they were stand-ins for the shape)."""
    problem = stage.problem_at(values.get("encoder_offset_rad", 0.0))
    delay = int(values.get("extra_delay_samples", 0))
    measured, ok = problem.measured(delay)
    tc0, jac = problem.evaluate(stage.base)
    r0 = np.where(ok, measured - tc0, 0.0).reshape(-1)
    params = [p for n in chosen if CANDIDATES[n].kind == "smooth" for p in CANDIDATES[n].parameters]
    idx = [SMOOTH_EFFECT_FIELDS.index(p.field) for p in params]
    mask = ok.reshape(-1)
    named = np.where(ok[:, :, None], jac[:, :, idx], 0.0).reshape(ok.size, len(idx))[mask]
    r = r0[mask]
    n, n_eff, threshold = r.size, r.size / stage.tau, stage.threshold
    motion = problem.motion
    t = motion.t_s[problem.rows]
    span = max(float(t[-1] - t[0]), 1e-9)
    theta = motion.theta1_rad[problem.rows]
    motor_turns = theta * problem.model.params.drive_ratio / (2 * np.pi)
    shapes: dict[str, list[np.ndarray]] = {
        "command dead band": [np.sign(measured)],
        "gain drift": [jac[:, :, SMOOTH_EFFECT_FIELDS.index("motor_gain")],
                       measured * ((t - t[0]) / span - 0.5)[:, None]],
    }
    for cycles in COGGING_CYCLES:
        phase = 2 * np.pi * cycles * motor_turns
        shapes[f"cogging ({cycles} cycles per motor turn)"] = [np.sin(phase), np.cos(phase)]
    rss_named = _least_squares_rss(r, named)
    best: dict | None = None
    for name, cols in shapes.items():
        s = np.column_stack([np.where(ok, c, 0.0).reshape(-1)[mask] for c in cols])
        rss_both = _least_squares_rss(r, np.hstack([named, s]))
        rss_shape = _least_squares_rss(r, s)
        gain_bic = bic(rss_named, n, len(idx), n_eff) - bic(rss_both, n, len(idx) + s.shape[1], n_eff)
        share = (rss_named - rss_both) / rss_named if rss_named > 0 else 0.0
        named_needed = bic(rss_shape, n, s.shape[1], n_eff) - bic(rss_both, n, len(idx) + s.shape[1], n_eff)
        LOG.debug("shape %s: delta BIC %.1f on top of %s (removes %.2f); the named given it: %.1f",
                  name, gain_bic, chosen, share, named_needed)
        if gain_bic > threshold and share >= SHAPE_MIN_GAIN and (best is None or gain_bic > best["delta_bic"]):
            best = {"shape": name, "delta_bic": gain_bic, "share": share,
                    "named_needed": bool(idx) and named_needed > threshold, "named_delta_bic": named_needed}
    return best
