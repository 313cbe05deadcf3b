"""The plant-only effects (backlash, cable compliance): evidence and fits on the closed-loop
replay of the training log, on top of the smooth effects already chosen.

Every trial is a closed-loop simulation of the training log, so the searches are frugal: a
coarse grid of three values per parameter decides whether a parameter is worth refining (its
best value must already beat the reference model by the evidence threshold), the refinement
is successive parabolic interpolation in log space from the grid's points
(:func:`~.search.parabolic_minimum`), the standard deviation comes from the curvature of the
points already evaluated, a set with one more effect starts from the fitted subset, and the
re-fits of the re-check start from the current values (:data:`REPLAY_LOCAL_STEP` apart).
"""
from __future__ import annotations

import functools
import logging
import math
import threading
from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, sosfiltfilt

from falcon_plan.control import Controller
from falcon_plan.discrepancy.identify import autocorrelation_time
from falcon_plan.discrepancy.library import CANDIDATES, effect_fields
from falcon_plan.discrepancy.replay import (FIT_STEP_PHASE_RAD, REPLAY_FAILURES, START_TRANSIENT_S, cable_substeps,
                                            at_points, closed_loop_replay, judged_rows, side_by_side)
from falcon_plan.discrepancy.search import curvature, parabolic_minimum
from falcon_plan.discrepancy.select import Evaluation, Selection, bic, greedy_select
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import NOMINAL, Effects

LOG = logging.getLogger(__name__)

REPLAY_GRID = {"backlash": (0.002, 0.006, 0.018), "cable_compliance": (10.0, 40.0, 160.0)}
"""First values tried for the plant-only parameters (backlash [rad], stiffness [N.m/rad]);
the search is refined around the best only if it already beats the reference model by the
threshold."""
REPLAY_BOUNDS = {"backlash": (2e-4, 0.04), "cable_compliance": (1.0, 3000.0)}
"""Search bounds of the plant-only parameters (same units as :data:`REPLAY_GRID`)."""
REPLAY_MAX_S = 10.0
"""The plant-only effects are fitted on at most the first seconds of the training log (each
trial is a closed-loop simulation). With 5 s the backlash estimate scattered by 25 % between
seeds; with the whole 6-8 s log by about 5 %."""
REPLAY_ERROR_CUTOFF_HZ = 10.0
"""Cut-off [Hz] of the zero-phase low-pass applied to the replay error before squaring."""
CHAOS_OFFSETS_COUNTS = (-0.3, -0.1, 0.1, 0.3)
"""Start-pose shifts [counts] used to measure the chaotic part of the replay error."""
REPLAY_LOG_TOLERANCE = 0.03
"""Step [log units, 3 %] below which the parabolic refinement of a plant-only parameter stops."""
REPLAY_MAX_REFINE = 4
"""At most this many replays refine one plant-only parameter after its coarse grid."""
SWAP_MAX_RSS_RATIO = 4.0
"""A smooth effect whose removal multiplies the training replay's RSS by more than this is
not tried as a plant-only effect in disguise (slop or a cable spring of the library's range
leaves count-level traces; such a smooth effect explains most of the replay)."""
REPLAY_LOCAL_STEP = 0.25
"""Log spacing of the three first trials of a re-fit around a current value (about +-28 %)."""


@dataclass(frozen=True)
class Swap:
    """A swap the replay criterion weighs: the smooth effect ``removed`` out, the plant-only
    effect ``added`` in (its ``fit`` on the reduced base), and the replay BIC's change
    ``delta_bic`` (positive favours the swap)."""

    delta_bic: float
    removed: str
    added: str
    fit: Evaluation


class ReplayStage:
    """Evidence and fits of the plant-only effects on the closed-loop replay of the training
    log, on top of fixed smooth effects.

    Parameters
    ----------
    log : the training log (its first :data:`REPLAY_MAX_S` seconds are used).
    base : the effects chosen so far (the smooth ones); every score is relative to it.
    model : the nominal model (parameter set; its effects are ignored).
    rate_hz : the log's control rate [Hz].
    controller : the loop that produced the log (None: replay the logged commands).
    threshold : delta BIC an effect must win to be named.
    """

    def __init__(self, log: FalconLog, base: Effects, model: FalconModel, rate_hz: float,
                 controller: Controller | None, threshold: float) -> None:
        keep = int(np.searchsorted(np.asarray(log.t_s), log.t_s[0] + REPLAY_MAX_S))
        if keep < len(log):
            log = log.rows(0, keep)
        self.log, self.base, self.model = log, base, model
        self.rate_hz, self.controller, self.threshold = rate_hz, controller, threshold
        self.enc = np.asarray(log.enc, float)
        self.replays = 0
        """Closed-loop replays run so far (for the timings)."""
        self._fits: dict[tuple[str, ...], Evaluation] = {}
        self._sos = butter(4, REPLAY_ERROR_CUTOFF_HZ, fs=rate_hz, output="sos")
        # the start transient depends on how the replay is initialised, not on the effects, and
        # a host stall's window on timing the replay knows only to the frame (judged_rows)
        self.judged = judged_rows(log, rate_hz, START_TRANSIENT_S)
        self._replays_lock = threading.Lock()
        errors = side_by_side([functools.partial(self._error, base)]
                              + [functools.partial(self._error, base, offset) for offset in CHAOS_OFFSETS_COUNTS])
        err0 = errors[0]
        self.rss0 = float(np.sum(err0 ** 2))
        self.n = err0.size
        # The replay error of whole counts is partly chaotic: sub-count details of the start
        # change which way counts round, and that persists. Its effect on RSS is measured by
        # replaying the base model from starts shifted by a fraction of a count; the effective
        # sample size is capped so that this spread counts as one unit of evidence
        # (n_eff ln(RSS0 / (RSS0 - spread)) ~ 1), on top of the autocorrelation cap n / tau.
        spread = [float(np.sum(e ** 2)) for e in errors[1:]]
        self.rss_spread = float(np.std(spread + [self.rss0], ddof=1))
        tau = autocorrelation_time(err0)
        n_eff = min(self.n / tau, self.rss0 / max(self.rss_spread, 1e-12 * self.rss0))
        self.tau = self.n / max(n_eff, 1.0)  # n_eff = 0 when the base replays the log exactly

    def _error(self, effects: Effects, offset_counts: float = 0.0) -> np.ndarray:
        """Low-passed replay error (counts) of the log under ``effects`` on the judged rows
        (:func:`~.replay.judged_rows`: the start transient and host stalls' windows cut)."""
        with self._replays_lock:
            self.replays += 1
        try:
            sim = closed_loop_replay(self.log, effects, self.model, self.rate_hz, self.controller,
                                     compliant_substeps=cable_substeps(effects, self.model, self.rate_hz,
                                                                       FIT_STEP_PHASE_RAD),
                                     initial_offset_counts=offset_counts)
        except REPLAY_FAILURES as exc:  # the replay left the workspace: this parameter is wrong
            LOG.debug("replay failed for %s: %s", effects.to_dict(), exc)
            return np.full_like(self.enc[self.judged.mask], 1e4)
        # Low-pass the error: the chaotic part of a whole-count replay error is count flicker
        # (broadband); the effects' traces are slower. On the test logs this raised the
        # evidence for a true backlash from ~6-34 to ~50-230 while nominal data stayed < 0.
        return sosfiltfilt(self._sos, sim - self.enc, axis=0)[self.judged.mask]

    def _rss(self, effects: Effects) -> float:
        return float(np.sum(self._error(effects) ** 2))

    def _bic(self, rss: float, k: int) -> float:
        return bic(rss, self.n, k, self.n / self.tau)

    def delta_bic(self, effects: Effects, extra_parameters: int = 0) -> float:
        """How much the replay BIC drops from the base to ``effects``, which fit
        ``extra_parameters`` more parameters than the base (positive favours ``effects``)."""
        return self._bic(self.rss0, 0) - self._bic(self._rss(effects), extra_parameters)

    @staticmethod
    def _apply(effects: Effects, name: str, value: float) -> Effects:
        if name == "backlash":
            return effects.replace(backlash_rad=value)
        return effects.replace(cable_stiffness_Nm_rad=value)

    def _fit_one(self, name: str, effects: Effects, gate: tuple[float, float],
                 around: float | None = None) -> tuple[float, float, float]:
        """(value, std, rss) of the plant-only parameter ``name`` added to ``effects``.

        Three first trials: the coarse grid, or ``around`` a current value. The search stops
        there (std = inf) unless their best beats ``gate`` = (reference RSS, margin) by the
        margin in BIC; then it is refined by parabolic steps in log space."""
        lo, hi = (math.log(b) for b in REPLAY_BOUNDS[name])
        if around is None:
            xs = [math.log(v) for v in REPLAY_GRID[name]]
        else:
            x0 = min(max(math.log(around), lo + REPLAY_LOCAL_STEP), hi - REPLAY_LOCAL_STEP)
            xs = [x0 - REPLAY_LOCAL_STEP, x0, x0 + REPLAY_LOCAL_STEP]

        def f(x: float) -> float:
            return self._rss(self._apply(effects, name, math.exp(x)))

        points = at_points(f, xs)
        best = min(points, key=lambda x: points[x])
        if self._bic(gate[0], 0) - self._bic(points[best], 1) <= gate[1]:
            return math.exp(best), math.inf, points[best]
        x, fx = parabolic_minimum(f, points, lo, hi, REPLAY_LOG_TOLERANCE, REPLAY_MAX_REFINE)
        # variance of x from the curvature of RSS (the points of the search), then of the value
        curv = curvature(points, x)
        s2 = fx / max(self.n - 1, 1) * self.tau
        std_x = math.sqrt(2 * s2 / curv) if curv > 0 else math.inf
        return math.exp(x), math.exp(x) * std_x, fx

    def _evaluation(self, names: tuple[str, ...], values: dict[str, float], std: dict[str, float],
                    rss: float, effects: Effects) -> Evaluation:
        return Evaluation(names, values, std, rss, self.n, len(names), self._bic(rss, len(names)), effects)

    def evaluate(self, names: tuple[str, ...]) -> Evaluation:
        """Fit the plant-only effects ``names`` on the base and score the set (BIC, replay
        residual); ``detail`` holds the resulting Effects. A set starts from its best fitted
        subset with one effect fewer and fits the one added on top of it."""
        parents = [e for k, e in self._fits.items() if len(k) == len(names) - 1 and set(k) <= set(names)]
        parent = min(parents, key=lambda e: e.rss) if parents else None
        if parent is None:
            effects, values, std, rss, done = self.base, {}, {}, self.rss0, ()
        else:
            effects, values, std, rss = parent.detail, dict(parent.values), dict(parent.std), parent.rss
            done = parent.names
        for name in names:
            if name in done:
                continue
            value, sd, rss = self._fit_one(name, effects, gate=(rss, self.threshold))
            effects = self._apply(effects, name, value)
            fld = CANDIDATES[name].parameters[0].field
            values[fld], std[fld] = value, sd
        ev = self._evaluation(tuple(names), values, std, rss, effects)
        self._fits[tuple(sorted(names))] = ev
        return ev

    def select(self, names: list[str]) -> Selection:
        """Greedy forward selection over the plant-only candidates ``names``."""
        return greedy_select(self.evaluate, names, self.threshold, together=side_by_side)

    def _refit_on(self, base: Effects, current: Effects, names: tuple[str, ...]) -> Evaluation:
        """Re-fit the plant-only effects ``names`` on another base, each starting around its
        value in ``current``."""
        effects, values, std = base, {}, {}
        rss = self._rss(base)
        for name in names:
            fld = CANDIDATES[name].parameters[0].field
            value, sd, rss = self._fit_one(name, effects, gate=(rss, self.threshold),
                                           around=float(getattr(current, fld)))
            effects = self._apply(effects, name, value)
            values[fld], std[fld] = value, sd
        return self._evaluation(names, values, std, rss, effects)

    def recheck(self, effects: Effects, smooth_chosen: list[str],
                replay_chosen: tuple[str, ...]) -> tuple[list[str], Evaluation | None]:
        """Backward check of the smooth effects under the replay criterion once plant-only
        effects are in: for each smooth effect, drop it, refit the plant-only parameters, and
        drop it for good if that costs no more than the threshold (a slop under a constant
        gravity load offsets the encoder like a small tilt, for example). ``effects`` are the
        current effects (smooth + plant-only), ``smooth_chosen`` the smooth names and
        ``replay_chosen`` the plant-only names chosen. Returns the dropped names and the refitted
        plant-only evaluation (None if nothing was dropped)."""
        current = effects
        full_rss = self._rss(current)
        full: Evaluation | None = None
        dropped: list[str] = []
        changed = True
        while changed:
            changed = False
            kept = [c for c in smooth_chosen if c not in dropped]
            k_full = len(kept) + len(replay_chosen)
            for name in kept:
                reset = {f: getattr(NOMINAL, f) for f in effect_fields(name)}
                reset.update(backlash_rad=NOMINAL.backlash_rad,
                             cable_stiffness_Nm_rad=NOMINAL.cable_stiffness_Nm_rad)
                trial = self._refit_on(current.replace(**reset), current, replay_chosen)
                if self._bic(trial.rss, k_full - 1) - self._bic(full_rss, k_full) <= self.threshold:
                    dropped.append(name)
                    current, full, full_rss = trial.detail, trial, trial.rss
                    changed = True
                    break
        return dropped, full

    def swap(self, effects: Effects, smooth_chosen: list[str], replay_names: list[str]) -> Swap | None:
        """When no plant-only effect passed on top of the smooth ones (``effects``, named
        ``smooth_chosen``): does replacing one smooth effect by one of the plant-only
        ``replay_names`` lower the replay BIC by more than the threshold? (The inverse-dynamics stage cannot see slop or springs and may have
        explained their static trace with, e.g., a small tilt; see :data:`SWAP_MAX_RSS_RATIO`
        for which smooth effects are tried.) Returns the best :class:`Swap`, or None if there
        is nothing to swap."""
        k = len(smooth_chosen)
        current = self._bic(self.rss0, k)
        reduced = {out: effects.replace(**{f: getattr(NOMINAL, f) for f in effect_fields(out)})
                   for out in smooth_chosen}
        without = side_by_side([functools.partial(self._rss, reduced[out]) for out in smooth_chosen])
        tried = []
        for out, rss in zip(smooth_chosen, without):
            ratio = rss / max(self.rss0, 1e-300)
            if ratio > SWAP_MAX_RSS_RATIO:
                LOG.debug("no swap of %s: without it the replay RSS is %.0f x larger", out, ratio)
            else:
                tried += [(out, into) for into in replay_names]
        # each pair's fit (refined only when its coarse grid is already close to the current
        # model) is independent of the others': side by side
        fits = side_by_side([functools.partial(self._fit_one, into, reduced[out], (self.rss0, -self.threshold))
                             for out, into in tried])
        best: Swap | None = None
        for (out, into), (value, sd, rss) in zip(tried, fits):
            fld = CANDIDATES[into].parameters[0].field
            trial = Evaluation((into,), {fld: value}, {fld: sd}, rss, self.n, 1,
                               self._bic(rss, 1), self._apply(reduced[out], into, value))
            gain = current - self._bic(trial.rss, k)
            LOG.debug("swap %s -> %s: delta BIC %.1f", out, into, gain)
            if best is None or gain > best.delta_bic:
                best = Swap(gain, out, into, trial)
        return best
