"""The checks after the fit, on the training log's closed-loop replay: the practical-improvement
gate (an effect must lower the replay error by a useful amount, not only win a likelihood), the
friction's smoothing speed (a parameter of a named friction effect, fitted on the replay), and
the open-world answer (a replay error left clearly above the floor is reported as unexplained,
with the leg and motion phase where it sits, instead of stretching a candidate to cover it).
"""
from __future__ import annotations

import functools
import logging
import math
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import numpy as np

from falcon_plan.control import Controller
from falcon_plan.discrepancy.library import CANDIDATES, effect_fields
from falcon_plan.discrepancy.motion import PHASES, MotionEstimate, motion_phases
from falcon_plan.discrepancy.replay import (FIT_STEP_PHASE_RAD, REPLAY_FAILURES, TRANSPORT_DELAY_KEY, cable_substeps,
                                            closed_loop_replay, judged_rows, lived_timing, settled_start_s,
                                            nominal_transport_delay, transport_delay_samples,
                                            at_points, side_by_side, with_transport_delay)
from falcon_plan.discrepancy.search import curvature, parabolic_minimum
from falcon_plan.falconlog import LINK_DELAY_KEY, FalconLog
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import COULOMB_SMOOTHING_RAD_S, NOMINAL, Effects

LOG = logging.getLogger(__name__)
LEG_NAMES = ("top", "right", "left")
"""Leg names in leg order (the report's words)."""
PRACTICAL_MIN_FRACTION = 0.10
PRACTICAL_MIN_COUNTS = 0.15
"""An effect must lower the training log's closed-loop replay RMS by at least this fraction
of the RMS without it and by at least this many counts (practical improvement). Measured over
the host table and five live sets of the independent world (126 cases), the count floor
decided only twice, both a true cable compliance (stiffness fitted at its true value, replay
BIC +46 and +64) lowering the replay by 0.18 and 0.20 counts, 14-16 %; every wrongly proposed
effect the gate removed lowered it by 0.05 counts or less. It was 0.2, set on the first clean
synthetic logs; 0.15 keeps three times the largest of those wrong gains."""
QUANTISATION_FLOOR_COUNTS = 0.5
"""Replay RMS [counts] that whole-count rounding alone leaves (two roundings of a uniform
error plus sub-count chaos; the issue measured about 0.5 on effect-free logs)."""
UNEXPLAINED_FACTOR = 2.0
"""A replay RMS above this multiple of the floor is reported as unexplained."""
WINDOW_S = 0.5
"""Length of the windows in which the open-world check says when the replay error sits [s]."""
TIMING_UNCERTAINTY_PERIODS = 0.25
"""How well a log's transport delay is known [periods] (a measured or default delay on a
real host): the floor of a log with timing columns includes the spread of replays this far
either side of it."""
OPEN_WORLD_RULE = (f"replay RMS > {UNEXPLAINED_FACTOR:g} x max({QUANTISATION_FLOOR_COUNTS} counts, "
                   "hypot(chaos, timing)), both from the motion's start on, host stalls' windows left out")
"""The open-world check's rule, as the report states it."""


@dataclass(frozen=True)
class PracticalGate:
    """What :func:`practical_gate` decided: the effects it ``dropped`` (weakest first), the
    replay RMS ``gains`` and paired-window ``window_gains`` (:func:`window_gain`) [counts] of
    the effects it last weighed (name -> error without it minus error with it), and the
    training log's replay RMS ``train_replay_rms`` with the effects kept [counts]."""

    dropped: list[str]
    gains: dict[str, float]
    window_gains: dict[str, float]
    train_replay_rms: float


class _Fields:
    """A check's result whose JSON form is its fields in order."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (the report's ``settings``): the fields in order."""
        return asdict(self)


@dataclass(frozen=True)
class SmoothingFit(_Fields):
    """:func:`fit_friction_smoothing`'s result: the friction ``effect`` the smoothing speed
    belongs to, its ``value`` and ``std`` [rad/s] (inf at the sharp bound), the replay RMS with
    the default ``rms_default`` and the fitted value ``rms_fitted`` [counts], and ``kept``."""

    effect: str
    value: float
    std: float
    rms_default: float
    rms_fitted: float
    kept: bool


@dataclass(frozen=True)
class StribeckRefit(_Fields):
    """:func:`fit_stribeck_on_replay`'s result: the Stribeck parameters ``before`` and
    ``after`` the refit (Effects field -> value: ``stribeck_Nm`` [N m],
    ``stribeck_velocity_rad_s`` [rad/s], ``friction_smoothing_rad_s`` [rad/s]), the replay
    RMS before ``rms_default`` and after ``rms_fitted`` [counts], and ``kept``."""

    before: dict[str, float]
    after: dict[str, float]
    rms_default: float
    rms_fitted: float
    kept: bool


@dataclass(frozen=True)
class DelayFit(_Fields):
    """:func:`fit_transport_delay`'s result: the transport delay ``value`` [periods], the
    criterion (window-median replay RMS) at the run's own delay ``rms_default`` and at the
    fitted value ``rms_fitted`` [counts], ``kept``, ``default``: the run's own delay, the one
    it assumed (:func:`~.replay.nominal_transport_delay`) [periods], and
    ``seeded_by_command_delay``: the delay the search started from when a named command delay
    seeded it [periods] (None: from the run's delay)."""

    value: float
    rms_default: float
    rms_fitted: float
    kept: bool
    default: float
    seeded_by_command_delay: float | None = None


@dataclass(frozen=True)
class ErrorWindow:
    """The half-second window of a log with the largest replay error: from ``start_s`` to
    ``end_s`` [s from the log's first row], its RMS ``rms_counts`` [counts, all legs]."""

    start_s: float
    end_s: float
    rms_counts: float


@dataclass(frozen=True)
class ErrorSite:
    """Where an unexplained replay error sits: the ``leg`` (0, 1, 2) and its ``leg_name``
    (:data:`LEG_NAMES`), the motion ``phase`` (:data:`~.motion.PHASES`), and the RMS there
    ``rms_counts`` [counts]."""

    leg: int
    leg_name: str
    phase: str
    rms_counts: float


@dataclass(frozen=True)
class OpenWorldCheck:
    """:func:`open_world_check`'s answer (the report's ``unexplained``): whether a remainder is
    ``unexplained``; the floor ``floor_counts`` and its parts ``chaos_counts`` (sub-count
    chaos) and ``timing_counts`` (the link's timing) [counts]; ``outside_library``: what the
    model-form checks found outside the library (None: nothing); ``when``: the window with the
    largest replay error; the replay RMS ``replay_rms_counts`` over all legs, per leg
    ``rms_per_leg_counts`` and per motion phase and leg ``rms_per_phase_counts`` (None: too few
    samples) [counts]; ``where``: the site of an unexplained remainder (None when explained);
    ``judged``: which rows all of these are over (:meth:`~.replay.JudgedRows.to_dict`: from the
    motion's start, host stalls' windows left out)."""

    unexplained: bool
    floor_counts: float
    chaos_counts: float
    timing_counts: float
    outside_library: dict[str, Any] | None
    when: ErrorWindow
    replay_rms_counts: float
    rms_per_leg_counts: list[float]
    rms_per_phase_counts: dict[str, list[float | None]]
    where: ErrorSite | None
    judged: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the fields in order, then the ``rule`` (:data:`OPEN_WORLD_RULE`)."""
        return {**asdict(self), "rule": OPEN_WORLD_RULE}


def without_effect(effects: Effects, name: str) -> Effects:
    """``effects`` with the fields of the candidate ``name`` (an EFFECT_NAMES entry) back at
    their nominal values."""
    return effects.replace(**{f: getattr(NOMINAL, f) for f in effect_fields(name)})


def window_rms(log: FalconLog, err: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """The RMS of ``err`` (N, 3) [counts] over the ``rows`` (N,) bool (default all) in each
    half-second window (:data:`WINDOW_S`) of ``log`` that has any, in time order."""
    t = np.asarray(log.t_s, float)
    rows = np.ones(t.size, bool) if rows is None else rows
    window = np.floor((t[rows] - t[0]) / WINDOW_S).astype(int)
    sq = np.mean(np.asarray(err, float)[rows] ** 2, axis=1)
    counts = np.bincount(window)
    return np.sqrt(np.bincount(window, sq) / np.maximum(counts, 1))[counts > 0]


class ReplayErrors(NamedTuple):
    """How far a closed-loop replay is from its log [counts, all legs]: the ``rms`` over the
    judged rows and the RMS in each half-second window (``windows``, :func:`window_rms`)."""

    rms: float
    windows: np.ndarray

    @property
    def window_median(self) -> float:
        """The median over the windows: a replay error that shows everywhere counts, an
        excursion in one window (a host stall the replay cannot follow) does not decide it."""
        return float(np.median(self.windows))


FAILED_REPLAY = ReplayErrors(math.inf, np.array([math.inf]))
"""The errors of a replay that left the workspace: as bad as it gets."""


def window_gain(without: ReplayErrors, with_: ReplayErrors) -> float:
    """How much an effect lowers the replay error window by window [counts]: the median over
    the windows of the error ``without`` it minus the error ``with_`` it, paired window by
    window (the difference of the two medians when a replay failed). Paired, a gain must show
    in most windows; the two medians alone can differ by a shuffle of which windows sit in
    the middle."""
    if without.windows.shape != with_.windows.shape:
        return without.window_median - with_.window_median
    return float(np.median(without.windows - with_.windows))


def replay_errors(log: FalconLog, effects: Effects, model: FalconModel, rate_hz: float,
                  spec: Controller | None) -> ReplayErrors:
    """The errors (:class:`ReplayErrors`) of the closed-loop replay of ``log`` with the plant
    carrying ``effects`` (``model``: the nominal parameter set; ``rate_hz``: the log's rate
    [Hz]; ``spec``: its controller, None to play the logged commands), over the rows
    :func:`~.replay.judged_rows` judges; :data:`FAILED_REPLAY` if the replay leaves the
    workspace. Besides the RMS, the windows: on a busy host a stall now and then throws the
    replay off for a while, more than any effect; a loop ringing in one stretch of the
    motion, which the replay does not follow, does the same."""
    try:
        sim = closed_loop_replay(log, effects, model, rate_hz, spec,
                                 compliant_substeps=cable_substeps(effects, model, rate_hz, FIT_STEP_PHASE_RAD))
    except REPLAY_FAILURES as exc:   # the replay left the workspace: as bad as it gets
        LOG.debug("replay failed for %s: %s", effects.to_dict(), exc)
        return FAILED_REPLAY
    rows = judged_rows(log, rate_hz).mask
    err = sim - np.asarray(log.enc, float)
    return ReplayErrors(float(np.sqrt(np.mean(err[rows] ** 2))), window_rms(log, err, rows))


def replay_rms(log: FalconLog, effects: Effects, model: FalconModel, rate_hz: float,
               spec: Controller | None) -> float:
    """RMS [counts, all legs] of the closed-loop replay of ``log`` under ``effects`` on
    ``model`` at ``rate_hz`` [Hz] with the logged controller ``spec`` (:func:`replay_errors`'
    first)."""
    return replay_errors(log, effects, model, rate_hz, spec).rms


def _useful_gain(gain: float, without: float) -> bool:
    """The practical rule: an effect's ``gain`` (the error without it minus the error with it
    [counts]) is >= PRACTICAL_MIN_FRACTION of the error ``without`` it and >= PRACTICAL_MIN_COUNTS."""
    return gain >= max(PRACTICAL_MIN_COUNTS, PRACTICAL_MIN_FRACTION * without)


def _useful(with_: float, without: float) -> bool:
    """The practical rule (:func:`_useful_gain`) on two errors: ``without`` an effect and ``with_`` it."""
    return _useful_gain(without - with_, without)


EVERYWHERE_EFFECTS = tuple(c.name for c in CANDIDATES.values() if c.kind == "delay")
"""Effects that act on every command alike (the library's delay kind: the command delay), kept
by :func:`practical_gate` only on the half-second windows (:func:`window_gain`): a delay shows
in every window. A loop that rings in one
stretch of the motion, where the replay does not ring, can look like one extra period there:
on a nominal emulated Falcon recorded through framed USB with 8 Hz reversals (near the
paper's PD's resonance), one extra period cut the training replay RMS from 3.98 to 3.00
counts, all of it in the two ringing windows, while the window median rose from 0.75 to 1.23
and the held-out replay RMS from 1.58 to 2.81. The windows are paired: on another recording
of that device one extra period lowered the window median from 1.73 to 1.46 counts while it
was better in only half of the windows (median paired gain -0.02 counts; held-out 1.54 ->
2.86); judged by the two medians, 2 of 12 such recordings named a delay, paired none of 24."""


def practical_gate(log: FalconLog, model: FalconModel, rate_hz: float, spec: Controller | None,
                   corrected: Effects, chosen: list[str]) -> tuple[Effects, list[str], PracticalGate]:
    """Keep an effect only if the training log's closed-loop replay error without it exceeds
    the error with it by >= PRACTICAL_MIN_FRACTION of the former and >= PRACTICAL_MIN_COUNTS,
    by the RMS or, for a log a real-time host recorded, by the median over half-second windows
    of the gain window by window (:func:`window_gain`: an effect that shows in most of the log
    is not hidden by a few stalls the replay cannot follow, nor one that shows in a few places
    by that median), the gain's fraction taken of the windows' median without it; the
    :data:`EVERYWHERE_EFFECTS` by the windows alone, on every log (weakest dropped
    first, then re-check). ``log``, ``model``, ``rate_hz``, ``spec`` as in
    :func:`replay_rms`; ``corrected`` the fitted effects; ``chosen`` their names. Returns
    (effects, names kept, what the gate decided)."""
    chosen = list(chosen)
    lived = lived_timing(log)
    dropped: list[str] = []
    gains: dict[str, float] = {}
    window_gains: dict[str, float] = {}

    def errors(effects: list[Effects]) -> list[ReplayErrors]:
        return side_by_side([functools.partial(replay_errors, log, e, model, rate_hz, spec) for e in effects])

    def useful(name: str) -> bool:
        by_rms = _useful(with_.rms, without[name].rms)
        by_windows = _useful_gain(window_gain(without[name], with_), without[name].window_median)
        return by_windows if name in EVERYWHERE_EFFECTS else by_rms or (lived and by_windows)

    trials = errors([corrected] + [without_effect(corrected, n) for n in chosen])
    with_, without = trials[0], dict(zip(chosen, trials[1:]))
    while chosen:
        gains = {n: without[n].rms - with_.rms for n in chosen}
        window_gains = {n: window_gain(without[n], with_) for n in chosen}
        ok = {n: useful(n) for n in chosen}
        if all(ok.values()):
            break
        weakest = min((n for n in chosen if not ok[n]), key=lambda n: gains[n])
        LOG.info("practical gate drops %s (replay gain %.2f counts)", weakest, gains[weakest])
        dropped.append(weakest)
        chosen.remove(weakest)
        corrected = without_effect(corrected, weakest)
        with_ = without[weakest]
        without = dict(zip(chosen, errors([without_effect(corrected, n) for n in chosen])))
    return corrected, chosen, PracticalGate(dropped, gains, window_gains, with_.rms)


FRICTION_EFFECTS = ("coulomb_friction", "stribeck_friction", "leg_friction")
"""The candidates whose torque goes through the smoothed sign (friction_smoothing_rad_s)."""
SMOOTHING_BOUNDS_RAD_S = (0.001, COULOMB_SMOOTHING_RAD_S)
"""Search bounds of the friction smoothing speed [rad/s]: from the model's default down to a
sign 20x sharper (the plant then takes up to 4 RK4 substeps per period,
:func:`falcon_plan.sim.equations.friction_substeps`)."""
SMOOTHING_GRID_RAD_S = (0.005, 0.002)
"""First trials of the smoothing search beside the default (whose replay is already known)."""
SMOOTHING_LOG_TOLERANCE = 0.1
"""Step [log units, 10 %] below which the smoothing search stops."""
SMOOTHING_MAX_REFINE = 3
"""At most this many replays refine the smoothing speed after its first trials."""


def fit_friction_smoothing(log: FalconLog, model: FalconModel, rate_hz: float, spec: Controller | None,
                           corrected: Effects, chosen: list[str],
                           rms_with: float) -> tuple[Effects, SmoothingFit | None]:
    """Fit the speed scale of the friction's smoothed sign (``friction_smoothing_rad_s``) by the
    training log's closed-loop replay RMS, only when a friction effect of
    :data:`FRICTION_EFFECTS` is among ``chosen``: parabolic search in log space on
    :data:`SMOOTHING_BOUNDS_RAD_S`. A real leg that sticks under a torque below break-away is
    held where the model's smooth sign lets it creep; a sharper sign holds it too. The value is
    kept only if it lowers the RMS by the practical rule (>= PRACTICAL_MIN_FRACTION and
    >= PRACTICAL_MIN_COUNTS of ``rms_with``, the RMS of ``corrected`` as it is).

    ``log``, ``model``, ``rate_hz``, ``spec`` as in :func:`replay_rms`. Returns (effects, the
    fit), the fit None when no friction effect is named, or a Stribeck curve is
    (:func:`fit_stribeck_on_replay` fits the smoothing with the curve)."""
    friction = [n for n in chosen if n in FRICTION_EFFECTS]
    if not friction or "stribeck_friction" in chosen:
        return corrected, None

    def f(x: float) -> float:
        return replay_rms(log, corrected.replace(friction_smoothing_rad_s=math.exp(x)), model, rate_hz, spec)

    lo, hi = (math.log(b) for b in SMOOTHING_BOUNDS_RAD_S)
    points = {math.log(corrected.friction_smoothing_rad_s): rms_with}
    points.update(at_points(f, [math.log(v) for v in SMOOTHING_GRID_RAD_S]))
    x, rms = parabolic_minimum(f, points, lo, hi, SMOOTHING_LOG_TOLERANCE, SMOOTHING_MAX_REFINE)
    # std of x from the curvature of the sum of squares n * RMS^2 around the minimum (samples
    # taken as independent: a lower bound); none at the sharp bound (the sign is at least
    # that sharp, e.g. a world whose sign is a step)
    n = np.asarray(log.enc).size
    curv = curvature({k: n * v ** 2 for k, v in points.items() if math.isfinite(v)}, x)
    at_bound = x <= lo + SMOOTHING_LOG_TOLERANCE
    std_x = math.sqrt(2 * rms ** 2 / curv) if curv > 0 and not at_bound else math.inf
    value = math.exp(x)
    keep = _useful(rms, rms_with)
    LOG.info("friction smoothing %.4g rad/s: replay RMS %.2f -> %.2f counts (%s)", value, rms_with, rms,
             "kept" if keep else "not kept")
    fit = SmoothingFit(friction[0], value, value * std_x, rms_with, rms, keep)
    return (corrected.replace(friction_smoothing_rad_s=value) if keep else corrected), fit


STRIBECK_FIELDS = ("stribeck_Nm", "stribeck_velocity_rad_s", "friction_smoothing_rad_s")
"""The parameters refitted on the replay with a Stribeck curve: its break-away excess and speed,
and the sharpness of the friction's sign, which decides with them how a leg sticks and breaks
away. On a clean world log with fast reversals the sharper sign alone lowered the replay by
0.03 counts and the refitted curve alone by 0.12, both below the practical rule, and together
by 0.59. On the busy-host world's Stribeck case (deterministic host table) the joint refit
left no unexplained flag (held-out 0.84 counts; fitted in turn: flagged, 1.06), on a live
recording of it likewise (1.57; flagged, 1.56)."""
STRIBECK_LOG_RANGE = math.log(4.0)
"""The replay refit searches each Stribeck parameter within this factor [log units] of the
inverse-dynamics fit (and within its candidate's bounds)."""
STRIBECK_LOG_TOLERANCE = 0.05
"""Step [log units, 5 %] below which a Stribeck parameter's search stops."""
STRIBECK_MAX_REFINE = 3
"""At most this many replays refine each Stribeck parameter after its first three (measured on
two recordings of a Stribeck world behind the threaded USB path: with 4, a fourth refinement
moved a fitted speed by 3 % and the held-out replay by 0.01 count, for 0.3 s of the case's
4.8 s)."""


def fit_stribeck_on_replay(log: FalconLog, model: FalconModel, rate_hz: float, spec: Controller | None,
                           corrected: Effects, chosen: list[str], rms_with: float) -> tuple[Effects, StribeckRefit | None]:
    """Refit the Stribeck curve (break-away excess ``stribeck_Nm`` and speed
    ``stribeck_velocity_rad_s``) on the training log's closed-loop replay RMS, only when
    ``stribeck_friction`` is among ``chosen``: the inverse-dynamics fit sees the curve only
    where the legs move faster than its cut-off, while the replay sees the sticking and
    break-away it decides. One parabolic search in log space per parameter (the excess, the
    speed, the friction smoothing, the excess again: :data:`STRIBECK_FIELDS`), within
    :data:`STRIBECK_LOG_RANGE` of the first fit and the candidate's bounds (the smoothing as
    :func:`fit_friction_smoothing` searches it); kept only by the practical rule against
    ``rms_with`` (the RMS of ``corrected`` as it is). ``log``, ``model``, ``rate_hz``, ``spec`` as in
    :func:`replay_rms`. Returns (effects, the refit), the refit None when the Stribeck curve
    is not named."""
    from falcon_plan.discrepancy.library import PARAMETER_BOUNDS

    if "stribeck_friction" not in chosen or corrected.stribeck_Nm <= 0:
        return corrected, None
    before = {f: float(getattr(corrected, f)) for f in STRIBECK_FIELDS}
    current, rms = corrected, rms_with
    for fld in (*STRIBECK_FIELDS, STRIBECK_FIELDS[0]):
        x0 = math.log(getattr(current, fld))
        if fld == "friction_smoothing_rad_s":   # as fit_friction_smoothing searches it
            lo, hi = (math.log(b) for b in SMOOTHING_BOUNDS_RAD_S)
            first = [math.log(v) for v in SMOOTHING_GRID_RAD_S]
        else:
            lo_b, hi_b = PARAMETER_BOUNDS[fld]
            lo = max(x0 - STRIBECK_LOG_RANGE, math.log(max(lo_b, 1e-6)))
            hi = min(x0 + STRIBECK_LOG_RANGE, math.log(hi_b))
            first = [x0 - 0.4, x0 + 0.4]
        base = current

        def f(x: float, base: Effects = base, fld: str = fld) -> float:
            return replay_rms(log, base.replace(**{fld: math.exp(x)}), model, rate_hz, spec)

        points = {x0: rms}
        points.update(at_points(f, [x for x in first if lo <= x <= hi and abs(x - x0) > STRIBECK_LOG_TOLERANCE]))
        x, rms = parabolic_minimum(f, points, lo, hi, STRIBECK_LOG_TOLERANCE, STRIBECK_MAX_REFINE)
        current = current.replace(**{fld: math.exp(x)})
    keep = _useful(rms, rms_with)
    after = {f: float(getattr(current, f)) for f in STRIBECK_FIELDS}
    LOG.info("Stribeck refit on the replay %s -> %s: RMS %.2f -> %.2f counts (%s)", before, after, rms_with, rms,
             "kept" if keep else "not kept")
    return (current if keep else corrected), StribeckRefit(before, after, rms_with, rms, keep)


DELAY_BOUNDS_PERIODS = (1.0, 8.0)
"""Search bounds of a fitted transport delay [periods]."""
DELAY_TOLERANCE_PERIODS = 0.1
"""Step [periods] below which the transport-delay search stops: well inside the quarter period
(:data:`TIMING_UNCERTAINTY_PERIODS`) the open-world floor already grants the delay, so a finer
search spends replays on what the floor does not use."""
DELAY_FIRST_OFFSETS = (-0.5, 0.0, 0.5, 1.25)
"""The transport-delay search's first trials [periods] from its start, replayed side by side
before any refinement: half a period either side, and further out later (a link slower than
assumed: from the half-period points alone, successive parabolas walked 2.25 periods out to a
window-median criterion of 0.65 counts at 3.2 periods, where 4.25 gave 0.49, on a busy host's
log whose noise the walk followed)."""
DELAY_FAR_OFFSET = 2.5
"""A further first trial [periods from the start], replayed only when the latest of
:data:`DELAY_FIRST_OFFSETS` is the best of them (a link slower than assumed). The search then
goes on as from all five together: its parabolas use the best trial and its neighbours only.
On seven busy-host world sets (147 cases) it was never needed and every result stayed the same
without it, one replay fewer a log; on host-world logs of a link 3 periods slower than
assumed, the fit without it stopped at 4.75 periods, its criterion twice that at 5.0."""
DELAY_MAX_REFINE = 4
"""At most this many replays refine the transport delay after its first trials."""


def unmeasured_link(log: FalconLog) -> bool:
    """Whether ``log`` has timing columns of a device in wall-clock time but no measured
    transport delay (:data:`~.replay.TRANSPORT_DELAY_KEY`): its link's delay is unknown and
    is fitted (:func:`fit_transport_delay`)."""
    return lived_timing(log) and TRANSPORT_DELAY_KEY not in (log.meta or {})


def fit_transport_delay(log: FalconLog, model: FalconModel, rate_hz: float, spec: Controller | None,
                        corrected: Effects, start: float | None = None) -> DelayFit | None:
    """The transport delay of a log with timing columns but no measured delay
    (:func:`unmeasured_link`): the fractional delay [periods] from sending a
    command to its acting that makes the training log's closed-loop replay with ``corrected``
    closest, by the median over half-second windows of the replay RMS (parabolic search from
    the nominal delay and the :data:`DELAY_FIRST_OFFSETS` around ``start`` (default: the run's
    nominal delay, :func:`~.replay.nominal_transport_delay`), and :data:`DELAY_FAR_OFFSET` when
    the latest of them is best, on :data:`DELAY_BOUNDS_PERIODS`).
    Kept by the practical rule against that criterion at the nominal delay; when the fit was seeded by a command delay the
    inverse-dynamics residual chose (``start`` given: evidence of its own), by its
    :data:`PRACTICAL_MIN_FRACTION` alone (a device's one extra period behind an unmeasured link
    lowered a busy-host training log's criterion by 25 %, 0.16 counts; left out, the held-out
    replay of a live recording with two stayed 3.3 counts off, where a nominal device's is 1.4).
    Unseeded, the fraction alone also kept 1.8 periods on a live calibration's logs of a device
    with no extra delay, where the practical rule keeps none: without evidence of its own, a
    delay must make a practical difference. Returns None for other logs, else the fit
    (``start`` recorded as its seed). ``log``, ``model``,
    ``rate_hz``, ``spec`` as in :func:`replay_rms`; ``log`` may carry ``start`` as its delay
    metadata already."""
    if not lived_timing(log) or (start is None and TRANSPORT_DELAY_KEY in (log.meta or {})):
        return None
    base = nominal_transport_delay(log, model)

    def f(d: float) -> float:
        """The median over half-second windows of the replay's RMS with delay ``d``
        (:func:`replay_errors`): a delay shows everywhere, an excursion in one window does not
        decide it."""
        return replay_errors(with_transport_delay(log, d), corrected, model, rate_hz, spec).window_median

    centre = base if start is None else float(start)
    trials = sorted({base} | {centre + d for d in DELAY_FIRST_OFFSETS})
    points = at_points(f, [d for d in trials if DELAY_BOUNDS_PERIODS[0] <= d <= DELAY_BOUNDS_PERIODS[1] or d == base])
    far = centre + DELAY_FAR_OFFSET
    if min(points, key=lambda d: points[d]) == max(points) and far <= DELAY_BOUNDS_PERIODS[1]:
        points[far] = f(far)
    rms_with = points[base]
    value, rms = parabolic_minimum(f, points, *DELAY_BOUNDS_PERIODS, DELAY_TOLERANCE_PERIODS, DELAY_MAX_REFINE)
    gain = rms_with - rms
    keep = gain >= PRACTICAL_MIN_FRACTION * rms_with and (start is not None or gain >= PRACTICAL_MIN_COUNTS)
    LOG.info("transport delay %.2f periods: replay RMS %.2f -> %.2f counts (%s)", value, rms_with, rms,
             "kept" if keep else "not kept")
    return DelayFit(value, rms_with, rms, keep, base, start)


LATE_NAMED_MIN_PERIODS = 3 * TIMING_UNCERTAINTY_PERIODS
"""A kept transport-delay fit this much later [periods] than the delay the run assumed names a
command delay (:func:`later_than_assumed`): three times the uncertainty of a log's known delay,
midway between what the fit finds on devices with no extra delay and the smallest delay a
device adds (one period: the library's command delay is whole periods). On the busy-host world
sets (eight sets of 21 cases, the threaded USB path under stress) two devices with none, a
motor-gain error and a flipped derivative sign, were fitted 0.50 periods late (their window
medians 0.67 -> 0.52 and 0.65 -> 0.44 counts) and were named a command delay at twice the
uncertainty; every device with two extra periods was fitted 1.57-2.00 periods late. The
windows do not tell them apart: the fitted delay beat the one a quarter period after the
assumed in 13 of 16 windows on both devices with none and in 10 to 16 of 16 on the devices
with two."""


def later_than_assumed(fit: DelayFit | None, log: FalconLog) -> float | None:
    """How much later [periods] the commands act than the run that recorded ``log`` assumed
    (the fit's ``default``), when the log records the link delay the run's controller led by
    (:data:`~falcon_plan.falconlog.LINK_DELAY_KEY`, as the executor's logs do) and a kept fit
    (:func:`fit_transport_delay`) is later by at least :data:`LATE_NAMED_MIN_PERIODS`; else
    None. Whether the device or the USB link holds the commands back the logs cannot tell
    (both act between a command's sending and its effect), so the workflow names it as the
    library's command delay and writes it as the link delay (a fractional figure, as
    ``doctor`` measures it). A log without the record did not say what its link does: its
    fitted delay is the link's and is not named. Earlier than assumed is not named: no effect
    makes a command act sooner."""
    if fit is None or not fit.kept or LINK_DELAY_KEY not in (log.meta or {}):
        return None
    late = fit.value - fit.default
    return float(late) if late >= LATE_NAMED_MIN_PERIODS else None


def open_world_check(log: FalconLog, motion: MotionEstimate, simulated: np.ndarray, model: FalconModel,
                     rate_hz: float, spec: Controller | None, corrected: Effects,
                     outside: dict[str, Any] | None = None) -> OpenWorldCheck:
    """The open-world check: the floor of the replay error, estimated from the log itself
    (quantisation; sub-count chaos measured by replaying the corrected model from starts
    +-0.25 count apart; for a log with timing columns, the spread of replays with the
    transport delay :data:`TIMING_UNCERTAINTY_PERIODS` either side), the remaining
    replay RMS, and, when it exceeds UNEXPLAINED_FACTOR x floor, where it sits (the leg and
    the motion phase with the largest RMS). All over the settled rows
    :func:`~.replay.judged_rows` judges: what the replay cannot know (the start from rest
    before the motion, the windows after host stalls) is not counted as a remainder.

    ``log`` the training log, ``motion`` its motion estimate (for the phases), ``simulated``
    its replay counts (N, 3) under ``corrected``; ``model``, ``rate_hz``, ``spec`` as in
    :func:`replay_rms`. ``outside``: what the model-form checks found outside the library
    (a residual shape, an inconsistent fit; see ``workflow._model_form``), which makes the
    answer unexplained whatever the floor. Returns the report's ``unexplained`` (with
    ``when``: the half-second window of the training log with the largest replay error)."""
    judged = judged_rows(log, rate_hz, settled_start_s(log, rate_hz))
    rows = judged.mask
    enc = np.asarray(log.enc, float)
    err = (simulated - enc)[rows]

    def spread(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.sqrt(np.mean((a - b)[rows] ** 2) / 2.0))

    substeps = cable_substeps(corrected, model, rate_hz, FIT_STEP_PHASE_RAD)

    def replay(trial: FalconLog, shift: float = 0.0) -> np.ndarray | None:
        try:
            return closed_loop_replay(trial, corrected, model, rate_hz, spec, compliant_substeps=substeps,
                                      initial_offset_counts=shift)
        except REPLAY_FAILURES:   # a failed replay leaves that part of the floor out
            return None

    # sub-count chaos: replays from starts a quarter count either side; and what the link's
    # timing, known to about a quarter period, leaves unexplained: the spread of replays with
    # the transport delay a quarter period either side
    jobs = [functools.partial(replay, log, shift) for shift in (0.25, -0.25)]
    if lived_timing(log):
        delay = transport_delay_samples(log, corrected, model) - corrected.extra_delay_samples
        jobs += [functools.partial(replay, with_transport_delay(log, delay + shift))
                 for shift in (TIMING_UNCERTAINTY_PERIODS, -TIMING_UNCERTAINTY_PERIODS)]
    runs = side_by_side(jobs)

    def spread_of(pair: list[np.ndarray | None]) -> float:
        return spread(pair[0], pair[1]) if len(pair) == 2 and pair[0] is not None and pair[1] is not None else 0.0

    chaos, timing = spread_of(runs[0:2]), spread_of(runs[2:4])
    floor = max(QUANTISATION_FLOOR_COUNTS, math.hypot(chaos, timing))
    per_leg = np.sqrt(np.mean(err ** 2, axis=0))
    phases = motion_phases(motion)[rows]
    per_phase: dict[str, list[float | None]] = {}
    for ph in PHASES:
        per_phase[ph] = [float(np.sqrt(np.mean(err[phases[:, leg] == ph, leg] ** 2)))
                         if np.sum(phases[:, leg] == ph) > 10 else None for leg in range(3)]
    rms_all = float(np.sqrt(np.mean(err ** 2)))
    leg = int(np.argmax(per_leg))
    phase = max((ph for ph in PHASES if per_phase[ph][leg] is not None), key=lambda ph: per_phase[ph][leg])
    found = rms_all > UNEXPLAINED_FACTOR * floor or outside is not None
    t = np.asarray(log.t_s, float)[rows]
    t0 = float(log.t_s[0])
    starts = np.arange(t[0], max(t[-1] - WINDOW_S, t[0]) + 1e-9, WINDOW_S / 2)
    windows = [float(np.sqrt(np.mean(err[(t >= a) & (t < a + WINDOW_S)] ** 2))) if np.any((t >= a) & (t < a + WINDOW_S))
               else 0.0 for a in starts]
    worst = int(np.argmax(windows))
    return OpenWorldCheck(
        found, floor, chaos, timing, outside,
        ErrorWindow(float(starts[worst] - t0), float(starts[worst] + WINDOW_S - t0), windows[worst]),
        rms_all, [float(x) for x in per_leg], per_phase,
        ErrorSite(leg, LEG_NAMES[leg], phase, per_phase[phase][leg]) if found else None, judged.to_dict())
