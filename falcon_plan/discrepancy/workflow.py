"""find_discrepancy: locate, name, fit and check what the nominal model misses.

1. **Locate** (:mod:`.locate`): inverse-dynamics residual of the training log per leg, motion
   phase, frequency and lag; windowed open-loop replay; closed-loop replay.
2. **Name** by evidence on the training log only (:mod:`.select`; the stages in
   :mod:`.smooth_stage` and :mod:`.replay_stage`):
   - the smooth effects and the command delay by BIC on the inverse-dynamics residual from
     the motion's start on (:mod:`.identify`; the approach from rest before it is not judged),
     greedy forward selection with a backward check; a rival that came
     close to a chosen effect in its round is weighed against it on the training replay;
   - then the plant-only effects (backlash, cable compliance) by BIC on the closed-loop
     replay error of the training log, on top of the smooth ones; if one of them is chosen,
     the smooth ones are re-checked under the replay criterion, refitting the plant-only
     parameters (a slop under a constant gravity load offsets the encoder like a small tilt;
     a cable spring looks like a small gain error in the inverse-dynamics residual). The
     replay error of whole counts is partly chaotic (sub-count details of the start decide
     how counts round), so its effective sample size is calibrated on replays from starts
     shifted by fractions of a count.
   The encoder home-angle offset is searched as a scalar (each trial re-reads the counts with
   that home angle and refits the rest on the inverse-dynamics residual).
3. **Validate** (so that model-form error is not rewarded): each smooth effect must remove at
   least CV_MIN_GAIN of the *blocked cross-validated* inverse-dynamics residual (contiguous
   blocks, each predicted from a fit on the others: correlated residuals cannot leak into the
   test block), and every effect must lower the training log's closed-loop replay RMS by a
   practical amount (PRACTICAL_MIN_FRACTION and PRACTICAL_MIN_COUNTS), weakest dropped first.
   :data:`SELECTION_RULE` states the whole rule; every report carries it.
4. **Fit**: the chosen parameters with standard deviations (Gauss-Newton + OSQP for the smooth
   ones, a discrete search for the delay, a bounded scalar search on the replay error for the
   plant-only ones) -> a corrected :class:`~falcon_plan.model.effects.Effects`. When a friction
   effect is named, the speed scale of its smoothed sign is then fitted on the training replay
   and kept only by the practical rule (:func:`~.checks.fit_friction_smoothing`): a parameter
   of that friction effect, never a named effect of its own. With a Stribeck curve named, its
   break-away and speed are refitted with it (:func:`~.checks.fit_stribeck_on_replay`).
5. **Open world**: the named smooth effects are checked for model form (:mod:`.smooth_stage`:
   a fit at the edge of its range, a fit that changes between halves of the data, a residual
   shape outside the library; then nothing is named and the answer is unexplained, with the
   reason); and (:mod:`.checks`) if the corrected model still replays the training log above
   UNEXPLAINED_FACTOR x the floor (quantisation, or the sub-count chaos measured by replaying
   from starts 0.5 count apart and the spread of a transport delay known to a quarter period,
   whichever is larger), both taken from the motion's start on and without the windows after
   host stalls (:func:`~.replay.judged_rows`: what the replay cannot know), the report says so
   and where (leg, motion phase) instead of stretching a candidate to cover it. A candidate
   fitted at the edge of its range is left out and the effects are named again without it.
6. **Check** on the held-out log (a different motion): closed-loop tracking-replay error per
   leg, nominal model against corrected model, in counts and mm.
"""
from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from falcon_plan.control import Controller
from falcon_plan.discrepancy.checks import (DELAY_TOLERANCE_PERIODS, LATE_NAMED_MIN_PERIODS, PRACTICAL_MIN_COUNTS,
                                            PRACTICAL_MIN_FRACTION, fit_friction_smoothing, fit_stribeck_on_replay,
                                            fit_transport_delay, later_than_assumed, unmeasured_link,
                                            QUANTISATION_FLOOR_COUNTS, UNEXPLAINED_FACTOR, OpenWorldCheck,
                                            PracticalGate, SmoothingFit, open_world_check, practical_gate,
                                            without_effect)
from falcon_plan.discrepancy.identify import ResidualProblem
from falcon_plan.discrepancy.library import CANDIDATES, candidate, clip_to_bounds, effect_fields
from falcon_plan.discrepancy.locate import Localisation, locate
from falcon_plan.discrepancy.motion import (PHASES, MotionEstimate, estimate_motion, log_rate_hz, require_samples,
                                            warn_if_cut_short)
from falcon_plan.discrepancy.replay import (CHECK_STEP_PHASE_RAD, STALL_PERIODS, STALL_SETTLE_S, TrackingError,
                                            cable_substeps, closed_loop_replay, log_controller, tick_schedule,
                                            motion_start_slot, side_by_side, tracking_error, transport_delay_samples,
                                            with_transport_delay)
from falcon_plan.discrepancy.replay_stage import ReplayStage
from falcon_plan.discrepancy.select import DEFAULT_THRESHOLD, Evaluation, Selection
from falcon_plan.discrepancy.smooth_stage import (CONSISTENCY_MIN_RELATIVE, CONSISTENCY_SIGMAS, CV_FOLDS,
                                                  CV_MIN_GAIN, SmoothStage, cross_validation_gate,
                                                  shape_check)
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import EFFECT_NAMES, NOMINAL, SMOOTH_EFFECT_FIELDS, Effects

LOG = logging.getLogger(__name__)

__all__ = ["find_discrepancy", "DiscrepancyReport", "ParameterEstimate", "SELECTION_RULE", "PHASES",
           "UNEXPLAINED_FACTOR"]

RIVAL_MARGIN = 2.0
"""A candidate is a chosen smooth effect's rival when, in the selection round that added the
effect, it also passed the threshold and came within this many thresholds of it: the
inverse-dynamics residual prefers one, but its effective sample size counts the model's form
error (the real dynamics are not the nominal model's) as evidence, so the training replay
decides (:func:`_settle_rivals`)."""


SELECTION_RULE = (
    "An effect is named only if (1) greedy forward selection adds it with delta BIC > threshold "
    "on the inverse-dynamics residual (from the motion's start on: not the approach from rest), "
    "n_eff = n / tau (tau the residual's integrated "
    "autocorrelation time), and the backward check keeps it; (2) blocked cross-validation "
    f"({CV_FOLDS} contiguous blocks, each predicted from a fit on the others) shows it removes "
    f">= {CV_MIN_GAIN:.0%} of the cross-validated residual; (3) it lowers the training log's "
    f"closed-loop replay RMS (or, for a log a real-time host recorded, the median over half-second windows "
    f"of its gain window by window; a command delay, which acts everywhere: that median on every log) by "
    f">= {PRACTICAL_MIN_FRACTION:.0%} "
    f"and >= {PRACTICAL_MIN_COUNTS} counts "
    "(backlash and cable compliance: BIC on the replay error instead of (1)-(2)); a chosen smooth effect and a "
    f"rival that also passed (1) in the round that added it, within {RIVAL_MARGIN:g} x the threshold of it, are "
    "weighed on the training replay (BIC on the low-passed replay error, as for backlash): the rival, fitted in "
    "its place, replaces it if it wins by more than the threshold; every replay criterion "
    f"leaves out, on a log a real-time host recorded, {STALL_SETTLE_S:g} s after each host stall (a send gap "
    f"or a reading age of {STALL_PERIODS:g} periods or more) unless that is most of the log. A replay RMS "
    f"left above {UNEXPLAINED_FACTOR:g} x max({QUANTISATION_FLOOR_COUNTS} counts, sub-count chaos) "
    "is reported as unexplained, with the leg and motion phase where it sits (the floor is measured on the log: "
    "quantisation, the replay's chaos, and for a log with timing columns a quarter period of transport delay; "
    "the remainder and the floor are taken from the motion's start on: the replay does not know the device's "
    "state and clock before it). "
    "A smooth effect fitted at the edge of its range is dropped; if a named smooth effect's fit differs between "
    f"halves of the data (by time, by command size; > {CONSISTENCY_SIGMAS:g} sigma and > {CONSISTENCY_MIN_RELATIVE:.0%}) "
    "or the residual follows a shape no candidate has (command dead band, gain drift, cogging) that makes the "
    "named effects unnecessary, nothing is named and the answer is unexplained. When a friction "
    "effect is named, the speed scale of its smoothed sign is fitted on the training replay and "
    "kept only if it passes (3); it is a parameter of that effect, not an effect; a named Stribeck curve's "
    "break-away and speed are refitted on the training replay the same way, together with that speed scale. A log with timing columns "
    "but no measured transport delay gets one fitted on the training replay (median over half-second windows), "
    "kept only if it passes (3) (seeded by a command delay the residual chose: by >= 10 % alone); it is "
    "the link's, used for both logs; a command delay found on such a log seeds that fit instead of being "
    "named (the logs cannot tell the link's delay from the device's), and a kept delay later by >= "
    f"{LATE_NAMED_MIN_PERIODS:g} periods than the one the run assumed, on a log that records the link delay "
    "its controller led by, is named as the command delay (the device's or the link's) and written as the "
    "model's link delay.")
"""The selection rule, stated in every report."""


@dataclass(frozen=True)
class ParameterEstimate:
    """One fitted parameter: the ``effect`` (candidate name) it belongs to, the Effects
    ``field`` it sets, its ``value``, standard deviation ``std`` (same unit) and ``unit``."""

    effect: str
    field: str
    value: float
    std: float
    unit: str

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (inf written as a string)."""
        return {"effect": self.effect, "value": _json_float(self.value), "std": _json_float(self.std),
                "unit": self.unit}


def _json_float(x: float) -> float | str:
    return x if math.isfinite(x) else ("inf" if x > 0 else "-inf" if x < 0 else "nan")


@dataclass
class DiscrepancyReport:
    """Everything :func:`find_discrepancy` found; :meth:`to_dict` is the JSON report.

    ``effects`` are names from EFFECT_NAMES, or ["none"]; ``parameters`` their fitted
    parameters by Effects field; ``corrected`` the Effects to load in the plant
    (``SimPlant(model, effects=...)``) and the planner (``FalconModel(params, effects)``);
    ``evidence`` one row per candidate; ``indistinguishable`` groups of names the data cannot
    tell apart; ``heldout_before``/``heldout_after`` (and ``train_before``/``train_after``)
    the closed-loop replay error of the held-out (training) log under the nominal and
    corrected models; ``localisation``/``heldout_localisation`` the residual summaries of
    both logs; ``unexplained`` the open-world check; ``settings`` the criteria and what the
    logs said; ``timings_s`` the time of each step [s]; ``traces`` the logged and replayed
    counts behind the plots.
    """

    effects: list[str]
    parameters: dict[str, ParameterEstimate]
    corrected: Effects
    evidence: list[dict[str, Any]]
    indistinguishable: list[list[str]]
    heldout_before: TrackingError
    heldout_after: TrackingError
    train_before: TrackingError
    train_after: TrackingError
    localisation: Localisation
    heldout_localisation: Localisation
    unexplained: OpenWorldCheck
    """The open-world check (:func:`~.checks.open_world_check`): floor, remaining replay RMS, and where a
    remainder above UNEXPLAINED_FACTOR x floor sits (leg, motion phase)."""
    settings: dict[str, Any]
    timings_s: dict[str, float]
    traces: dict[str, np.ndarray] = field(repr=False, default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The JSON report: effects, parameters (with uncertainties), evidence, held-out RMS
        before/after (encoder counts, all legs, and per leg in counts and mm), corrected
        effects (Effects.to_dict()), localisation summaries, settings and timings."""
        return {
            "effects": list(self.effects),
            "parameters": {k: p.to_dict() for k, p in self.parameters.items()},
            "corrected_effects": self.corrected.to_dict(),
            "evidence": self.evidence,
            "indistinguishable": self.indistinguishable,
            "heldout_rms_before": self.heldout_before.rms_counts_all,
            "heldout_rms_after": self.heldout_after.rms_counts_all,
            "heldout_before": self.heldout_before.to_dict(),
            "heldout_after": self.heldout_after.to_dict(),
            "train_replay_before": self.train_before.to_dict(),
            "train_replay_after": self.train_after.to_dict(),
            "locate_train": self.localisation.to_dict(),
            "locate_heldout": self.heldout_localisation.to_dict(),
            "unexplained": self.unexplained.to_dict(),
            "settings": self.settings,
            "timings_s": self.timings_s,
        }


@dataclass
class _Choice:
    """The effects chosen so far: names, the corrected Effects, fitted values and their
    standard deviations (Effects field -> value)."""

    chosen: list[str]
    corrected: Effects
    values: dict[str, float]
    stds: dict[str, float]
    smoothing: SmoothingFit | None = None
    """The friction smoothing speed when it was fitted and kept
    (:func:`~.checks.fit_friction_smoothing`, or with a Stribeck curve), else None."""

    def forget(self, name: str) -> None:
        """Remove ``name`` from the names and its fields from the values (not from Effects)."""
        self.chosen.remove(name)
        for fld in effect_fields(name):
            self.values.pop(fld, None)
            self.stds.pop(fld, None)

    def take(self, ev: Evaluation) -> None:
        """Adopt a replay-stage evaluation: its Effects, values and deviations."""
        self.corrected = ev.detail
        self.values.update(ev.values)
        self.stds.update(ev.std)

    def estimates(self) -> dict[str, ParameterEstimate]:
        """The fitted parameters of the chosen effects."""
        out = {p.field: ParameterEstimate(name, p.field, float(self.values[p.field]),
                                          float(self.stds.get(p.field, math.nan)), p.unit)
               for name in self.chosen for p in CANDIDATES[name].parameters if p.field in self.values}
        if self.smoothing is not None:
            out["friction_smoothing_rad_s"] = ParameterEstimate(
                self.smoothing.effect, "friction_smoothing_rad_s", float(self.smoothing.value),
                float(self.smoothing.std), "rad/s")
        return out


@dataclass
class _PlantOnly:
    """Outcome of the plant-only stage: its selection, the smooth effects it swapped out, and
    a smooth/plant-only pair the replay cannot tell apart."""

    stage: ReplayStage | None = None
    selection: Selection | None = None
    swapped: list[str] = field(default_factory=list)
    swap_group: list[str] | None = None


def inverse_dynamics_delay(log: FalconLog, rate_hz: float, transport_delay: float) -> float:
    """The delay [samples, fractional] from a row's counts to the middle of the period its
    command acts over, for the inverse-dynamics residual of ``log`` at ``rate_hz`` [Hz]: the ``transport_delay`` [periods]
    from sending to acting, plus how long after its reading arrived a command was sent on
    average (the log's timing columns; 0 without them: the replay's convention, a reading
    is the state when it arrives), plus half a period (a command acts for one period)."""
    schedule = tick_schedule(log, rate_hz)
    late = float(np.mean(schedule.sent - schedule.read)) if schedule.timed else 0.0
    return transport_delay + late + 0.5


def _effects_from_values(values: dict[str, float], extra_delay: int = 0) -> Effects:
    """Effects from fitted field values, each clipped into its candidate's bounds
    (:func:`~.library.clip_to_bounds`); the continuous Kd factor is rounded to its sign."""
    kwargs: dict[str, Any] = {}
    for name, value in clip_to_bounds(values).items():
        if name == "kd_sign":
            kwargs[name] = -1.0 if value < 0 else 1.0
        else:
            kwargs[name] = value
    if extra_delay:
        kwargs["extra_delay_samples"] = int(extra_delay)
    return Effects(**kwargs)


def _name_smooth(log: FalconLog, rate_hz: float, problem: ResidualProblem, names: list[str],
                 threshold: float) -> tuple[SmoothStage, Selection, _Choice, list[str], dict[str, float]]:
    """Step 2a: the smooth effects, delay and encoder offset by BIC on the inverse-dynamics
    residual, then the blocked cross-validation gate. Returns the stage, its selection, the
    choice, the names the gate dropped and each kept effect's cross-validation gain."""
    smooth_names = [n for n in names if CANDIDATES[n].kind in ("smooth", "delay", "encoder")]
    stage = SmoothStage(log, rate_hz, problem, smooth_names, threshold)
    sel = stage.select()
    cv_dropped, cv_gains = cross_validation_gate(stage, sel)
    final = sel.final
    smooth_values = {k: v for k, v in final.values.items() if k in SMOOTH_EFFECT_FIELDS}
    corrected = _effects_from_values(smooth_values, int(final.values.get("extra_delay_samples", 0)))
    choice = _Choice(list(sel.chosen), corrected, dict(final.values), dict(final.std))
    return stage, sel, choice, cv_dropped, cv_gains


@dataclass(frozen=True)
class _ModelForm:
    """What the model-form checks found: the effects ``dropped`` (name -> reason) and
    ``outside``: the residual shape or inconsistency outside the library (None: none)."""

    dropped: dict[str, str]
    outside: dict[str, Any] | None


def _stretched(stage: SmoothStage, choice: _Choice) -> tuple[str, str] | None:
    """A named smooth effect of ``choice`` fitted at the edge of its range (it was stretched to
    cover something else, :func:`~.smooth_stage.consistency_check`): (its name, the reason),
    or None."""
    found = stage.consistency(tuple(choice.chosen), choice.values) if choice.chosen else None
    if found is None or found["split"] != "bound":
        return None
    name = next(n for n in choice.chosen if found["field"] in effect_fields(n))
    return name, f"fitted {found['field']} at the edge of its range: stretched"


def _name_smooth_unstretched(log: FalconLog, rate_hz: float, problem: ResidualProblem, names: list[str],
                             threshold: float) -> tuple[SmoothStage, Selection, _Choice, list[str],
                                                        dict[str, float], dict[str, str]]:
    """:func:`_name_smooth`, again without each candidate the fit stretched to the edge of its
    range (:func:`_stretched`) until none is: a stretched candidate may have pushed out, in the
    backward check, the effect it stood in for (a Stribeck curve at its largest speed is a
    Coulomb level). Returns :func:`_name_smooth`'s values and the candidates left out (name ->
    reason)."""
    stretched: dict[str, str] = {}
    while True:
        stage, sel, choice, cv_dropped, cv_gains = _name_smooth(
            log, rate_hz, problem, [n for n in names if n not in stretched], threshold)
        found = _stretched(stage, choice)
        if found is None:
            return stage, sel, choice, cv_dropped, cv_gains, stretched
        LOG.info("%s %s; naming again without it", *found)
        stretched[found[0]] = found[1]


def _model_form(stage: SmoothStage, choice: _Choice) -> _ModelForm:
    """Step 2a's model-form checks on the named smooth effects (``choice``, updated in
    place): an effect whose fit differs between halves of the data
    (:func:`~.smooth_stage.consistency_check`), or a residual shape no candidate has
    (:func:`~.smooth_stage.shape_check`) that makes the named effects unnecessary, means the
    named effects stood in for something outside the library: all are dropped and the answer
    is "unexplained". (A candidate stretched to the edge of its range is left out before,
    :func:`_name_smooth_unstretched`.)"""
    dropped: dict[str, str] = {}
    outside = None
    shape = shape_check(stage, tuple(choice.chosen), choice.values)
    inconsistent = stage.consistency(tuple(choice.chosen), choice.values) if choice.chosen else None
    if shape is not None and not shape["named_needed"]:
        outside = {"kind": "shape", **shape,
                   "reason": f"the residual follows a {shape['shape']} (delta BIC {shape['delta_bic']:.0f}, "
                             f"{shape['share']:.0%} of what the named effects leave), which no candidate has"}
    elif inconsistent is not None:
        a, b = inconsistent["values"]
        outside = {"kind": "inconsistent", **inconsistent,
                   "reason": f"the fitted {inconsistent['field']} is {a:.4g} in {inconsistent['halves'][0]} and "
                             f"{b:.4g} in {inconsistent['halves'][1]} ({inconsistent['sigmas']:.1f} sigma): "
                             f"an effect that acts by {inconsistent['split']}, which no candidate has"}
    if outside is not None:
        for name in list(choice.chosen):
            dropped[name] = "outside the library: " + outside["reason"]
            choice.forget(name)
        choice.corrected = NOMINAL
    return _ModelForm(dropped, outside)


def _rivals(sel: Selection, threshold: float) -> list[tuple[str, str]]:
    """(chosen, rival) pairs of smooth effects (:data:`RIVAL_MARGIN`) from ``sel``'s rounds."""
    pairs = []
    for deltas in sel.rounds:
        best = max(deltas, key=lambda c: deltas[c])
        if deltas[best] <= threshold or best not in sel.chosen or CANDIDATES[best].kind != "smooth":
            continue
        pairs += [(best, c) for c in deltas if c != best and c not in sel.chosen and CANDIDATES[c].kind == "smooth"
                  and threshold < deltas[c] and deltas[best] - deltas[c] < RIVAL_MARGIN * threshold]
    return pairs


def _settle_rivals(stage: SmoothStage, sel: Selection, choice: _Choice, replay: ReplayStage,
                   threshold: float) -> tuple[str, str] | None:
    """Step 2a': a chosen smooth effect and a rival (:func:`_rivals`) the inverse-dynamics
    residual barely tells apart are weighed on the training replay (``replay``, built on
    ``choice.corrected``): the rival, fitted in its place on the inverse-dynamics residual,
    replaces it when it lowers the replay BIC (its parameters counted) by more than ``threshold``. ``choice`` is
    updated in place; returns the (removed, added) pair, or None."""
    best: tuple[float, str, str, Evaluation, Effects] | None = None
    for out, into in _rivals(sel, threshold):
        names = tuple(sorted([c for c in choice.chosen if c != out] + [into]))
        ev = stage.evaluate(names)
        effects = _effects_from_values({f: v for f, v in ev.values.items() if f in SMOOTH_EFFECT_FIELDS},
                                       int(ev.values.get("extra_delay_samples", 0)))
        gain = replay.delta_bic(effects, CANDIDATES[into].n_parameters - CANDIDATES[out].n_parameters)
        LOG.info("rival %s for %s: replay delta BIC %.1f", into, out, gain)
        if gain > threshold and (best is None or gain > best[0]):
            best = (gain, out, into, ev, effects)
    if best is None:
        return None
    _, out, into, ev, effects = best
    choice.forget(out)
    choice.chosen.append(into)
    choice.corrected = effects
    choice.values, choice.stds = dict(ev.values), dict(ev.std)
    return out, into


def _name_plant_only(log: FalconLog, model: FalconModel, rate_hz: float, spec: Controller | None,
                     names: list[str], threshold: float, choice: _Choice,
                     stage: ReplayStage | None = None) -> _PlantOnly:
    """Step 2b: backlash and cable compliance by BIC on the training replay, on top of the
    smooth effects (``choice``, updated in place): a chosen one re-checks the smooth effects
    under the replay criterion; if none is chosen, a swap of one smooth effect for one
    plant-only effect is tried. ``stage``: a replay stage already built on ``choice.corrected``
    (None: built here)."""
    replay_names = [n for n in names if CANDIDATES[n].kind == "replay"]
    if not replay_names:
        return _PlantOnly()
    if stage is None or stage.base != choice.corrected:
        stage = ReplayStage(log, choice.corrected, model, rate_hz, spec, threshold)
    out = _PlantOnly(stage, stage.select(replay_names))
    if out.selection.chosen:
        choice.take(out.selection.final)
        dropped, refit = stage.recheck(choice.corrected, list(choice.chosen), out.selection.chosen)
        if dropped and refit is not None:
            LOG.info("replay re-check drops %s", dropped)
            for name in dropped:
                choice.forget(name)
            choice.take(refit)
        choice.chosen += list(out.selection.chosen)
    elif choice.chosen:
        swap = stage.swap(choice.corrected, list(choice.chosen), replay_names)
        if swap is not None and abs(swap.delta_bic) <= threshold:
            # the replay cannot tell the smooth effect from the plant-only one
            out.swap_group = [swap.removed, swap.added]
            LOG.info("%s and %s are indistinguishable (swap delta BIC %.1f)", swap.removed, swap.added, swap.delta_bic)
        elif swap is not None and swap.delta_bic > threshold:
            LOG.info("replay criterion swaps %s for %s", swap.removed, swap.added)
            choice.forget(swap.removed)
            choice.take(swap.fit)
            choice.chosen.append(swap.added)
            out.swapped.append(swap.removed)
    return out


def _evidence_table(names: list[str], sel: Selection, stage: SmoothStage, plant: _PlantOnly,
                    chosen: list[str], cv_dropped: list[str], cv_gains: dict[str, float],
                    practical: PracticalGate) -> tuple[list[dict[str, Any]], list[list[str]]]:
    """The evidence rows (:func:`_evidence_rows`) with the gates' verdicts and gains, and the
    groups of indistinguishable effects."""
    evidence = _evidence_rows(names, sel, stage, plant.selection, plant.stage, chosen)
    groups = [list(g) for g in sel.indistinguishable]
    if plant.selection is not None:
        groups += [list(g) for g in plant.selection.indistinguishable]
    if plant.swap_group is not None:
        groups.append(plant.swap_group)
    for row in evidence:
        name = row["effect"]
        if name in cv_dropped:
            row["status"] = "dropped (blocked cross-validation gain below threshold)"
        if name in practical.dropped:
            row["status"] = "dropped (no practical improvement of the training replay)"
        if name in plant.swapped:
            row["status"] = "dropped (replaced by a plant-only effect under the replay criterion)"
        if name in cv_gains:
            row["cross_validation_gain"] = cv_gains[name]
        if name in practical.gains:
            row["replay_gain_counts"] = practical.gains[name]
        for g in groups:
            if name in g:
                row["indistinguishable_from"] = [x for x in g if x != name]
    return evidence, groups


@dataclass(frozen=True)
class _Replays:
    """Counts of the closed-loop replays of both logs under the nominal and corrected models."""

    held_nominal: np.ndarray
    held_corrected: np.ndarray
    train_nominal: np.ndarray
    train_corrected: np.ndarray


def _check_replays(train_log: FalconLog, heldout_log: FalconLog, model: FalconModel, corrected: Effects,
                   rates: tuple[float, float], specs: tuple[Controller | None, Controller | None],
                   as_run: tuple[FalconLog, FalconLog]) -> _Replays:
    """Step 6: replay both logs under the nominal and the corrected model (a cable model with
    :data:`~.replay.CHECK_STEP_PHASE_RAD` per substep); the nominal replays are those of
    ``as_run`` (training, held-out: the logs with the transport delay the nominal model has,
    which differs from the logs' own when a delay was named); the corrected replay of a log is
    the nominal one when nothing was corrected."""
    def replays(log: FalconLog, nominal_log: FalconLog, rate: float,
                spec: Controller | None) -> list[Callable[[], np.ndarray]]:
        nominal = functools.partial(closed_loop_replay, nominal_log, NOMINAL, model, rate, spec)
        if corrected == NOMINAL and nominal_log is log:
            return [nominal]
        substeps = cable_substeps(corrected, model, rate, CHECK_STEP_PHASE_RAD)
        return [nominal, functools.partial(closed_loop_replay, log, corrected, model, rate, spec,
                                           compliant_substeps=substeps)]

    held = replays(heldout_log, as_run[1], rates[1], specs[1])
    train = replays(train_log, as_run[0], rates[0], specs[0])
    runs = side_by_side(held + train)
    held_runs, train_runs = runs[:len(held)], runs[len(held):]
    return _Replays(held_runs[0], held_runs[-1], train_runs[0], train_runs[-1])


def find_discrepancy(train_log: FalconLog, heldout_log: FalconLog, *, rate_hz: float | None = None,
                     controller: str | None = None, model: FalconModel | None = None,
                     threshold: float = DEFAULT_THRESHOLD,
                     candidates: list[str] | None = None) -> DiscrepancyReport:
    """Find which named effects explain the difference between the logs and the nominal model.

    Parameters
    ----------
    train_log, heldout_log : FalconLog
        Identification is done on ``train_log`` only; ``heldout_log`` (a different motion)
        is used only to measure the tracking-replay error before and after.
    rate_hz : control rate [Hz] when the logs lack ``rate_hz`` metadata (overrides it).
    controller : e.g. "pd kp=10 kd=0.1" when the logs lack ``controller`` metadata, or
        "open-loop" to replay the logged commands.
    model : the nominal model (default acra2009, no effects).
    threshold : delta BIC for "very strong" evidence (default 10).
    candidates : names to consider (default: all of EFFECT_NAMES).
    """
    started = time.perf_counter()
    timings: dict[str, float] = {}
    model = model or FalconModel()
    names = list(candidates) if candidates is not None else list(EFFECT_NAMES)
    for n in names:
        candidate(n)
    for log_, what in ((train_log, "the training log"), (heldout_log, "the held-out log")):
        require_samples(log_, what)
        warn_if_cut_short(log_, what)
    rates = (log_rate_hz(train_log, rate_hz), log_rate_hz(heldout_log, rate_hz))
    specs = (log_controller(train_log, controller), log_controller(heldout_log, controller))
    transport = transport_delay_samples(train_log, NOMINAL, model)
    nominal_delay = inverse_dynamics_delay(train_log, rates[0], transport)
    as_run = (train_log, heldout_log)   # with the delay the run assumed

    def lap(key: str, t0: float) -> float:
        now = time.perf_counter()
        timings[key] = now - t0
        return now

    t0 = time.perf_counter()
    motion = estimate_motion(train_log, rates[0], model.params)
    motion_start = motion_start_slot(train_log, rates[0]) / rates[0]
    problem = ResidualProblem(model, motion, nominal_delay, start_s=motion_start)
    t0 = lap("motion_s", t0)
    stage, sel, choice, cv_dropped, cv_gains, stretched = _name_smooth_unstretched(train_log, rates[0], problem,
                                                                                   names, threshold)
    link_seed = None
    if "command_delay" in choice.chosen and unmeasured_link(train_log):
        # Without a measured transport delay, a command delay is the link's as much as the
        # device's (the logs cannot tell them apart): it seeds the link's fractional delay,
        # used by every replay from here, and is not named as an effect of the device. The
        # smooth effects are chosen again on the residual with that delay (effects chosen
        # against the wrong delay stood in for it).
        link_seed = transport + float(choice.corrected.extra_delay_samples)
        train_log = with_transport_delay(train_log, link_seed)
        heldout_log = with_transport_delay(heldout_log, link_seed)
        nominal_delay = inverse_dynamics_delay(train_log, rates[0], link_seed)
        problem = ResidualProblem(model, motion, nominal_delay, start_s=motion_start)
        stage, sel, choice, cv_dropped, cv_gains, stretched = _name_smooth_unstretched(
            train_log, rates[0], problem, [n for n in names if n != "command_delay"], threshold)
    form = _model_form(stage, choice)
    form.dropped.update(stretched)
    if link_seed is not None:
        form.dropped["command_delay"] = (f"taken as the link's transport delay ({link_seed:g} periods, "
                                            "fitted below): the log has no measured one")
    if form.outside is not None:  # the residual has a shape no candidate has: name nothing
        names = [n for n in names if CANDIDATES[n].kind != "replay"]
    replay_stage = None
    if form.outside is None and _rivals(sel, threshold):
        replay_stage = ReplayStage(train_log, choice.corrected, model, rates[0], specs[0], threshold)
        rival = _settle_rivals(stage, sel, choice, replay_stage, threshold)
        if rival is not None:
            form.dropped[rival[0]] = f"replaced by {rival[1]} (the training replay tells them apart)"
    t0 = lap("smooth_selection_s", t0)
    plant = _name_plant_only(train_log, model, rates[0], specs[0], names, threshold, choice, replay_stage)
    t0 = lap("replay_selection_s", t0)
    choice.corrected, choice.chosen, practical = practical_gate(train_log, model, rates[0], specs[0],
                                                                choice.corrected, choice.chosen)
    for name in practical.dropped:
        for fld in effect_fields(name):
            choice.values.pop(fld, None)
    t0 = lap("practical_gate_s", t0)
    choice.corrected, smoothing = fit_friction_smoothing(train_log, model, rates[0], specs[0], choice.corrected,
                                                         choice.chosen, practical.train_replay_rms)
    choice.smoothing = smoothing if smoothing and smoothing.kept else None
    rms_now = smoothing.rms_fitted if smoothing and smoothing.kept else practical.train_replay_rms
    choice.corrected, stribeck = fit_stribeck_on_replay(train_log, model, rates[0], specs[0], choice.corrected,
                                                        choice.chosen, rms_now)
    if stribeck is not None and stribeck.kept:
        after = dict(stribeck.after)
        sharpness = after.pop("friction_smoothing_rad_s")
        choice.values.update(after)
        if sharpness != stribeck.before["friction_smoothing_rad_s"]:   # refitted with the curve: no std of its own
            choice.smoothing = SmoothingFit("stribeck_friction", sharpness, math.nan, stribeck.rms_default,
                                            stribeck.rms_fitted, True)
    t0 = lap("friction_smoothing_s", t0)
    delay_fit = fit_transport_delay(train_log, model, rates[0], specs[0], choice.corrected, start=link_seed)
    if delay_fit is not None:
        # the link's delay: both logs came over it (not kept: the model's command delay)
        value = delay_fit.value if delay_fit.kept else transport
        train_log = with_transport_delay(train_log, value)
        heldout_log = with_transport_delay(heldout_log, value)
    late = later_than_assumed(delay_fit, as_run[0]) if "command_delay" in names else None
    if late is not None:
        choice.chosen.append("command_delay")
        choice.values["extra_delay_samples"] = late
        choice.stds["extra_delay_samples"] = DELAY_TOLERANCE_PERIODS   # the search's resolution
        form.dropped.pop("command_delay", None)
    t0 = lap("transport_delay_s", t0)
    evidence, groups = _evidence_table(names, sel, stage, plant, choice.chosen, cv_dropped, cv_gains, practical)
    for row in evidence:
        if row["effect"] in form.dropped:
            row["status"] = f"dropped ({form.dropped[row['effect']]})"
        if row["effect"] == "command_delay" and late is not None:
            row["status"] = (f"named: the commands act {late:.2f} periods later than the run assumed "
                             f"({delay_fit.default:g}), in the device or the link (the logs cannot tell them apart); "
                             "written as the model's link delay")
    replays = _check_replays(train_log, heldout_log, model, choice.corrected, rates, specs,
                             as_run if late is not None else (train_log, heldout_log))
    t0 = lap("replay_check_s", t0)
    unexplained = open_world_check(train_log, motion, replays.train_corrected, model, rates[0], specs[0],
                                   choice.corrected, outside=form.outside)
    t0 = lap("open_world_s", t0)
    loc_train, loc_held = _localise(train_log, heldout_log, motion, model, choice.corrected, rates, nominal_delay)
    lap("locate_s", t0)
    timings["total_s"] = time.perf_counter() - started
    if plant.stage is not None:
        timings["plant_only_replays"] = float(plant.stage.replays)
    report = DiscrepancyReport(
        effects=choice.chosen or ["none"], parameters=choice.estimates(), corrected=choice.corrected,
        evidence=evidence, indistinguishable=groups,
        heldout_before=tracking_error(heldout_log, replays.held_nominal, model),
        heldout_after=tracking_error(heldout_log, replays.held_corrected, model),
        train_before=tracking_error(train_log, replays.train_nominal, model),
        train_after=tracking_error(train_log, replays.train_corrected, model),
        localisation=loc_train, heldout_localisation=loc_held, unexplained=unexplained,
        settings={**_settings(threshold, stage, plant.stage, problem, motion, nominal_delay, rates, specs, model,
                              train_log, transport),
                  "friction_smoothing": None if smoothing is None else
                  {k: _json_float(v) if isinstance(v, float) else v for k, v in smoothing.to_dict().items()},
                  "transport_delay_fit": None if delay_fit is None else delay_fit.to_dict(),
                  "stribeck_replay_refit": None if stribeck is None else stribeck.to_dict()},
        timings_s=timings,
        traces={"train_t": np.asarray(train_log.t_s), "train_enc": np.asarray(train_log.enc, float),
                "train_nominal": replays.train_nominal, "train_corrected": replays.train_corrected,
                "held_t": np.asarray(heldout_log.t_s), "held_enc": np.asarray(heldout_log.enc, float),
                "held_nominal": replays.held_nominal, "held_corrected": replays.held_corrected},
    )
    LOG.info("discrepancy: effects %s in %.1f s", report.effects, timings["total_s"])
    return report


def _localise(train_log: FalconLog, heldout_log: FalconLog, motion: MotionEstimate, model: FalconModel,
              corrected: Effects, rates: tuple[float, float],
              nominal_delay: float) -> tuple[Localisation, Localisation]:
    """Step 1's summaries under the corrected model, training and held-out (the logs re-read
    with a fitted encoder offset)."""
    enc_params = corrected.encoder_params(model.params)
    if enc_params is not model.params:
        motion = estimate_motion(train_log, rates[0], enc_params)
    held_motion = estimate_motion(heldout_log, rates[1], enc_params)
    return (locate(motion, model, corrected, nominal_delay),
            locate(held_motion, model, corrected, nominal_delay, windows=False))


def _settings(threshold: float, stage: SmoothStage, replay_stage: ReplayStage | None,
              problem: ResidualProblem, motion: MotionEstimate, nominal_delay: float,
              rates: tuple[float, float], specs: tuple[Controller | None, Controller | None],
              model: FalconModel, log: FalconLog, transport_delay: float) -> dict[str, Any]:
    """The report's ``settings``: criteria, rule, thresholds and what the logs said."""
    return {"criterion": "BIC = n_eff ln(RSS/n) + k ln(n_eff), n_eff = n / tau",
            "selection_rule": SELECTION_RULE, "unexplained_factor": UNEXPLAINED_FACTOR,
            "threshold_delta_bic": threshold,
            "smooth_residual": "inverse dynamics, command units, legs moving faster than "
                               "0.05 rad/s, acting command below 95 % of the static saturation",
            "replay_residual": "closed-loop replay of the training log, counts",
            "tau_smooth_samples": stage.tau * problem.stride,
            "tau_replay_samples": replay_stage.tau if replay_stage else None,
            "lowpass_cutoff_hz": motion.cutoff_hz, "nominal_delay_samples": nominal_delay,
            "transport_delay_samples": transport_delay, "timed_log": tick_schedule(log, rates[0]).timed,
            "rate_hz_train": rates[0], "rate_hz_heldout": rates[1],
            "controller_train": str(specs[0]), "controller_heldout": str(specs[1]),
            "params": model.params.name}


def _evidence_rows(names: list[str], sel: Selection, stage: SmoothStage,
                   replay_sel: Selection | None, replay_stage: ReplayStage | None,
                   chosen: list[str]) -> list[dict[str, Any]]:
    """One row per candidate: criterion, delta BIC alone (against the nominal / base model),
    delta BIC given the final choice (the cost of removing it, or the gain of adding it), the
    values fitted alone, and the status."""
    rows = []
    for name in names:
        cand = CANDIDATES[name]
        s = sel if cand.kind in ("smooth", "delay", "encoder") else replay_sel
        if s is None:
            continue
        base = s.evaluation(())
        alone = s.evaluations.get((name,))
        final_set = tuple(sorted(s.chosen))
        if name in s.chosen:
            without = s.evaluations.get(tuple(sorted(x for x in s.chosen if x != name)))
            given = None if without is None else without.bic - s.final.bic
        else:
            added = s.evaluations.get(tuple(sorted(final_set + (name,))))
            given = None if added is None else s.final.bic - added.bic
        rows.append({
            "effect": name,
            "criterion": ("BIC, inverse-dynamics residual" if cand.kind != "replay"
                          else "BIC, closed-loop replay residual (training log)"),
            "delta_bic_alone": None if alone is None else base.bic - alone.bic,
            "delta_bic_given_final": given,
            "rms_alone": None if alone is None else math.sqrt(alone.rss / alone.n),
            "rms_base": math.sqrt(base.rss / base.n),
            "fitted_alone": {} if alone is None else {k: _json_float(v) for k, v in alone.values.items()},
            "status": ("selected" if name in chosen else
                       "dropped (backward check)" if name in s.chosen or name in s.dropped else
                       "rejected (delta BIC below threshold)"),
        })
    return rows
