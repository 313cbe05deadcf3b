"""The bang-bang command pattern of a minimum-time motion, read off a coarse transcription.

Why: with a constant command limit, every benchmark solution of the minimum-time
transcription is bang-bang: each leg's command sits at +-(tc_max - reserve) and changes sign
once or twice (``docs/figures/bang-bang.png``). Such a motion is fixed by a handful of numbers,
the switch times and the duration, while the transcription's duration converges only at second
order in 1/N (0.3 % needs N = 24, ~30 ms of IPOPT). So the planner reads the command pattern
off a coarse transcription (:func:`coarse_solve`) and solves for those numbers with the exact
forward dynamics (:mod:`.shooting`):

- **pattern** (:class:`CommandPattern`): each leg's starting sign and switch times, the via
  points' pass times and the legs that switch there; its :class:`Phases` between consecutive
  events; every switch is a linear command ramp of :data:`SWITCH_RAMP_S` (the motion then has
  a continuous command, which a drive and a piecewise-linear acceleration can follow);
- **reading it** (:func:`pattern_of`, :func:`candidate_patterns`) from a plan's commands,
  with the pulses too short for the coarse grid guessed at its ends and at dips of the command
  (:func:`with_dips`);
- **a pulse that collapsed** in a solve is removed (:func:`without_collapsed`).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.bound import CommandBound
from falcon_plan.planning.min_time import solve_min_time
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.planning.transcription import (DEFAULT_HESSIAN, DEFAULT_PROFILE, MinTimeSettings, SolveResult,
                                                initial_guess, via_nodes)
from falcon_plan.trajectory import Trajectory


SWITCH_RAMP_S = 2e-5
"""Length of the linear command ramp at every switch [s] (the device runs at 1 kHz: a ramp of
20 us is a step to it; the ramp costs ~1e-5 of the duration per switch)."""
COARSE_INTERVALS = 8
"""N of the coarse transcription the pattern is read from (plus :data:`COARSE_INTERVALS_PER_VIA`
per via point)."""
DEVICE_COARSE_INTERVALS = 12
"""The same under the device's limit: at N = 8 the legs' first pulses (~3 ms, while the limit
rises from its value at rest) and the switches were read 25-75 % off and Newton's method
stalled on the benchmark move (0, 0, 0.12) -> (0.03, 0.02, 0.14) m; from N = 12, 16 and 24 it
converged to the same duration (within 2e-5)."""
COARSE_INTERVALS_PER_VIA = 4
"""Coarse intervals added per via point."""
COARSE_GUESS_ACCEL_FRACTION = 1.0
"""The coarse solve's initial guess accelerates at this fraction of what the start's command
room allows (:func:`~falcon_plan.planning.transcription.initial_guess`): its duration is then
0.64-1.47x the solution's (median 1.09), against 0.76-1.76x (1.31) at the transcription's
0.7, and IPOPT takes 14 % fewer iterations over the benchmark problems (481 against 559; 1.3
and 1.6 took 535 and 541)."""
COARSE_WALL_TIME_S = 0.5
"""IPOPT's wall-time limit of the coarse solve [s] (it takes 7-30 ms on the benchmark problems;
with a shorter time budget the budget's deadline callback stops it instead)."""
COARSE_COMMAND_POINTS = 1
"""The coarse transcription imposes the command limit at its nodes only (the pattern is all
it has to show): ~10 ms against ~14 ms with the planner's 3 points per interval, and the
pattern was as good (33 of the 34 benchmark problems without via points solved from it)."""
HYSTERESIS = 0.5
"""A leg's command counts as switched only once it reaches this fraction of the limit with
the other sign (:func:`pattern_of`; a coarse plan's command can wander around zero)."""
END_PULSE_SHORTFALL = 0.15
"""A coarse plan's command at the start (end) more than this fraction short of the limit,
next to a sample at the limit with the same sign, marks a pulse too short for its grid
(:func:`pattern_of`)."""
MAX_CANDIDATES = 4
"""Patterns tried per coarse plan (:func:`candidate_patterns`)."""


@dataclass(frozen=True)
class Phases:
    """The phases of a pattern between consecutive events (switches and via points).

    bounds : (m + 1,) event times [s] from 0 to T; signs : (3, m) the commands' signs on each
    phase; order : (m - 1,) which unknown (entry of :attr:`CommandPattern.times_s`) each inner
    event is; ramp : (m - 1,) the event changes a command (a command ramp starts there);
    via : (m - 1,) the via point's index of a via event, -1 for a switch.
    """

    bounds: np.ndarray
    signs: np.ndarray
    order: np.ndarray
    ramp: np.ndarray
    via: np.ndarray

    @property
    def durations(self) -> np.ndarray:
        """(m,) [s]."""
        return np.diff(self.bounds)


@dataclass(frozen=True)
class CommandPattern:
    """A bang-bang command pattern: each leg's command is +-level, starting with ``signs[i]``
    and changing sign at ``switches_s[i]`` [s] (increasing, inside (0, T)) and at the via
    points listed in ``via_flips`` (the legs whose command changes sign the moment via point k
    is passed, at ``via_s[k]`` [s]: with a via point the optimal command may switch exactly
    there).

    ``level`` is applied by the caller (tc_max - reserve [command units]). ``pulse``: the
    switches added as a trial pulse, if any (indices in :attr:`times_s`)."""

    signs: tuple[float, float, float]
    switches_s: tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]
    via_s: tuple[float, ...] = ()
    via_flips: tuple[tuple[int, ...], ...] = ()
    pulse: tuple[int, ...] = ()
    """Switches added as a trial pulse (:func:`.shooting.with_pulse`; indices in :attr:`times_s`): T is
    minimised over them first (their pair is a weak lever on the end state)."""

    @property
    def counts(self) -> tuple[int, ...]:
        """Free switches per leg."""
        return tuple(len(s) for s in self.switches_s)

    @property
    def n_switches(self) -> int:
        """Free switches of all legs."""
        return sum(self.counts)

    @property
    def n_phases(self) -> int:
        """Phases between consecutive events (free switches and via points), which is also
        the number of unknowns of the solve: every event time, and T."""
        return self.n_switches + len(self.via_s) + 1

    def with_times(self, times_s: np.ndarray) -> "CommandPattern":
        """The same pattern with the event times ``times_s`` (as in :attr:`times_s`)."""
        ends = np.cumsum((0,) + self.counts)
        legs = tuple(tuple(float(t) for t in times_s[a:b]) for a, b in zip(ends[:-1], ends[1:]))
        via = tuple(float(t) for t in times_s[ends[-1]:])
        return CommandPattern(self.signs, legs, via, self.via_flips, self.pulse)  # type: ignore[arg-type]

    @property
    def times_s(self) -> np.ndarray:
        """The event times: every leg's free switches (leg 0's, then 1's, then 2's), then the
        via points' [s]."""
        return np.array([t for leg in self.switches_s for t in leg] + list(self.via_s), float)

    @cached_property
    def _events(self) -> tuple[np.ndarray, np.ndarray]:
        """Per event (in :attr:`times_s` order): (3, n) -1 for the legs it switches, +1 for the
        others; (n,) the via point's index, -1 for a switch."""
        flips = [(leg,) for leg, count in enumerate(self.counts) for _ in range(count)]
        flips += [tuple(legs) for legs in self.via_flips]
        factor = np.ones((3, len(flips)))
        for e, legs in enumerate(flips):
            factor[list(legs), e] = -1.0
        return factor, np.concatenate([-np.ones(self.n_switches, int), np.arange(len(self.via_s))])

    def phases(self, duration_s: float, times_s: np.ndarray | None = None) -> Phases:
        """The phases up to T = ``duration_s`` [s], with the event times ``times_s`` (as in
        :attr:`times_s`; default this pattern's)."""
        times = self.times_s if times_s is None else np.asarray(times_s, float)
        order = np.argsort(times, kind="stable")
        factor, via = self._events
        factor = factor[:, order]
        signs = np.array(self.signs, float)[:, None] * np.hstack([np.ones((3, 1)), np.cumprod(factor, axis=1)])
        return Phases(np.concatenate([[0.0], times[order], [duration_s]]), signs, order,
                      np.any(factor < 0.0, axis=0), via[order])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: starting signs, switch times [s] per leg, via times [s] and the legs
        switching at each via point."""
        return {"signs": [int(s) for s in self.signs], "switches_s": [list(leg) for leg in self.switches_s],
                "via_s": list(self.via_s), "via_flips": [list(legs) for legs in self.via_flips]}


def pattern_of(traj: Trajectory, level: Any, via_times_s: Any = (), tie_to_via: bool = True) -> CommandPattern | None:
    """The bang-bang pattern of ``traj``'s commands (a coarse plan): per leg the sign at the
    start and the times where the command changes sign (the zero crossing, linear between
    samples, between two samples at least :data:`HYSTERESIS` of ``level`` [command units]:
    the bound, a number or (n, 3) its value at each sample
    with opposite signs).

    A coarse grid cannot show a pulse shorter than its first or last interval (on the benchmark
    problems a leg often starts with a pulse of 1-2 % of T against its next sign): such a leg
    starts (ends) with its command short of ``level`` by more than :data:`END_PULSE_SHORTFALL`
    while the next sample is at the limit with the same sign, and gets a pulse of the opposite
    sign there, its length guessed from the shortfall (a quarter of the first interval times
    the missing fraction; Newton's method then places it). :func:`candidate_patterns` tries
    the other legs when that leaves a switch missing.

    ``via_times_s``: when the plan passes its via points [s]. Where there are more switches
    than equations (:func:`square_switches`) and ``tie_to_via``, the surplus switches nearest a
    via point (within the plan's longest interval) are taken to happen at it. None when a
    leg's command never reaches the hysteresis level."""
    t = traj.t_s
    c = np.asarray(traj.commands, float) / np.asarray(level, float)  # fractions of the bound
    level = 1.0
    first, last = t[1] - t[0], t[-1] - t[-2]

    def crossing(a: int, b: int) -> float | None:
        """The zero crossing between samples a < b nearest their middle (None: none)."""
        seg = c_leg[a:b + 1]
        k = np.nonzero(seg[:-1] * seg[1:] <= 0.0)[0]
        k = k[seg[k] != seg[k + 1]]
        if not len(k):
            return None
        j = a + int(k[np.argmin(np.abs(k - (b - a - 1) / 2.0))])
        return float(t[j] + (t[j + 1] - t[j]) * c_leg[j] / (c_leg[j] - c_leg[j + 1]))

    signs, legs = [], []
    for leg in range(3):
        c_leg = c[:, leg]
        decisive = np.nonzero(np.abs(c_leg) >= HYSTERESIS * level)[0]
        if not len(decisive):
            return None
        sign = float(np.sign(c_leg[decisive[0]]))
        times = [x for a, b in zip(decisive[:-1], decisive[1:])
                 if c_leg[a] * c_leg[b] < 0.0 and (x := crossing(int(a), int(b))) is not None]
        before = crossing(0, int(decisive[0]))
        if before is not None:  # a weak pulse before the first decisive sample
            sign, times = -sign, [before, *times]
        elif (1.0 - abs(c_leg[0]) / level > END_PULSE_SHORTFALL and c_leg[0] * c_leg[1] > 0.0
              and abs(c_leg[1]) >= (1.0 - END_PULSE_SHORTFALL) * level):
            sign, times = -sign, [max(0.25 * first * (1.0 - abs(c_leg[0]) / level), 3 * SWITCH_RAMP_S), *times]
        after = crossing(int(decisive[-1]), len(t) - 1)
        if after is not None:
            times.append(after)
        elif (1.0 - abs(c_leg[-1]) / level > END_PULSE_SHORTFALL and c_leg[-1] * c_leg[-2] > 0.0
              and abs(c_leg[-2]) >= (1.0 - END_PULSE_SHORTFALL) * level):
            times.append(t[-1] - max(0.25 * last * (1.0 - abs(c_leg[-1]) / level), 3 * SWITCH_RAMP_S))
        signs.append(sign)
        legs.append([float(x) for x in times])
    via = [float(x) for x in via_times_s]
    flips: list[list[int]] = [[] for _ in via]
    surplus = sum(len(times) for times in legs) - square_switches(len(via))
    if via and surplus > 0 and tie_to_via:
        window = float(np.max(np.diff(t)))
        near = sorted((abs(x - tv), leg, x, k) for leg, times in enumerate(legs) for x in times
                      for k, tv in enumerate(via) if abs(x - tv) <= window)
        for _, leg, x, k in near:
            if surplus and leg not in flips[k] and x in legs[leg]:
                legs[leg].remove(x)
                flips[k].append(leg)
                surplus -= 1
    return CommandPattern(tuple(signs), tuple(tuple(times) for times in legs),  # type: ignore[arg-type]
                          tuple(via), tuple(tuple(sorted(f)) for f in flips))


def candidate_patterns(traj: Trajectory, level: Any, via_times_s: Any = ()) -> list[CommandPattern]:
    """Patterns to try for the coarse plan ``traj``, most likely first: :func:`pattern_of`
    (``level`` [command units], ``via_times_s`` [s] as there), with more switches than
    equations as read (T minimised over the surplus), then with the surplus switches next to a
    via point tied to it; when it has one switch fewer than the solve takes, the same with a
    pulse added at the start or the end of one leg, the legs whose first (last) two samples
    fall furthest short of ``level`` first (a pulse the coarse grid smeared over its first or
    last interval); with as many or more, such a pulse (a surplus switch) only where those
    samples fall short by more than :data:`END_PULSE_SHORTFALL` (under the device's limit the
    legs often start with a pulse of 2-3 ms while the limit rises from its value at rest)."""
    base = pattern_of(traj, level, via_times_s)
    if base is None:
        return []
    untied = pattern_of(traj, level, via_times_s, tie_to_via=False)
    candidates = [base] if untied is None or untied == base else [untied, base]
    square = square_switches(len(base.via_s))
    if base.n_switches + 1 >= square:
        c = np.abs(np.asarray(traj.commands, float)) / np.asarray(level, float)
        first, last = traj.t_s[1] - traj.t_s[0], traj.t_s[-1] - traj.t_s[-2]
        ends = [(min(c[0, leg], c[1, leg]), leg, "start") for leg in range(3)] + \
               [(min(c[-1, leg], c[-2, leg]), leg, "end") for leg in range(3)]
        if base.n_switches >= square:  # a surplus pulse only where the plan's end falls short
            ends = [e for e in ends if e[0] < 1.0 - END_PULSE_SHORTFALL]
        for _, leg, end in sorted(ends):
            legs = [list(times) for times in base.switches_s]
            signs = list(base.signs)
            if end == "start":
                signs[leg] = -signs[leg]
                legs[leg].insert(0, 0.25 * first)
            else:
                legs[leg].append(traj.t_s[-1] - 0.25 * last)
            candidates.append(CommandPattern(tuple(signs), tuple(tuple(x) for x in legs),  # type: ignore[arg-type]
                                             base.via_s, base.via_flips))
    if base.n_switches < square:  # pulses the coarse grid smeared into a dip between samples
        dipped = with_dips(traj, level, base, square - base.n_switches)
        if dipped is not None:
            candidates.insert(1, dipped)
    return candidates[:MAX_CANDIDATES]


DIP_SHORTFALL = 0.05
"""A coarse command sample this fraction short of the limit between two samples at it is a
dip (:func:`with_dips`; read only for a pattern short of switches, which fails without: on
short_z under the device's limit the dips were 12 % and 34 % deep)."""


def with_dips(traj: Trajectory, level: Any, base: CommandPattern, missing: int) -> CommandPattern | None:
    """``base`` (read off ``traj``, the coarse plan, with ``level`` [command units] as in
    :func:`pattern_of`) with a pulse of the opposite command at every dip of the coarse
    command (a sample more than :data:`DIP_SHORTFALL` short of the limit between two at it
    with the same sign: a pulse shorter than the grid), its width guessed from the dip (at
    least twice :data:`COLLAPSE_S`); None when they make up fewer than the ``missing``
    switches. On short_z under the device's limit two legs reverse briefly where the limit
    rises from its value at rest (T minimised over the surplus: with a pulse on one leg only,
    Newton's method stalled)."""
    c = np.asarray(traj.commands, float) / np.asarray(level, float)
    t = traj.t_s
    dips = [(leg, k) for leg in range(3) for k in range(1, len(t) - 1)
            if c[k - 1, leg] * c[k + 1, leg] > 0.0 and c[k, leg] * c[k - 1, leg] > 0.0
            and min(abs(c[k - 1, leg]), abs(c[k + 1, leg])) >= 1.0 - END_PULSE_SHORTFALL
            and abs(c[k, leg]) < 1.0 - DIP_SHORTFALL]
    if 2 * len(dips) < missing:
        return None
    legs = [list(times) for times in base.switches_s]
    for leg, k in dips:
        width = max(0.25 * (1.0 - abs(c[k, leg])) * (t[k + 1] - t[k - 1]), 2.0 * COLLAPSE_S)
        legs[leg] += [float(t[k] - width / 2.0), float(t[k] + width / 2.0)]
    return CommandPattern(base.signs, tuple(tuple(sorted(times)) for times in legs),  # type: ignore[arg-type]
                          base.via_s, base.via_flips)


def square_switches(n_via: int) -> int:
    """Free switches that make the equations square with ``n_via`` via points: the goal state
    (6) and each via position (3) against the switch times, each via time and T."""
    return 6 + 3 * n_via - n_via - 1


def coarse_intervals(problem: PlanProblem, bound: CommandBound) -> int:
    """N of the coarse transcription for ``problem`` under ``bound``."""
    base = COARSE_INTERVALS if bound.kind == "constant" else DEVICE_COARSE_INTERVALS
    return base + COARSE_INTERVALS_PER_VIA * len(problem.via_m)


def coarse_solve(model: FalconModel, problem: PlanProblem, bound: CommandBound, *, time_budget_s: float,
                 hessian: str = DEFAULT_HESSIAN, profile: str = DEFAULT_PROFILE) -> SolveResult:
    """The coarse transcription of ``problem`` for ``model`` under ``bound`` that a pattern is
    read from: :func:`coarse_intervals`, the command
    limit at the nodes only (:data:`COARSE_COMMAND_POINTS`), without the workspace margins
    (the switching-time plan's dense re-check checks its motion), stopped by IPOPT's own
    wall-time limit of :data:`COARSE_WALL_TIME_S` (no per-iteration Python callback) unless
    ``time_budget_s`` [s] is shorter; ``hessian`` and ``profile`` as the planner's."""
    n = coarse_intervals(problem, bound)
    guess = initial_guess(model, problem, n, bound.at_rest, via_nodes(problem, n), COARSE_GUESS_ACCEL_FRACTION)
    settings = MinTimeSettings(n, hessian=hessian, profile=profile, time_budget_s=time_budget_s, workspace="ignore",
                               command_points=COARSE_COMMAND_POINTS,
                               wall_time_s=COARSE_WALL_TIME_S if time_budget_s >= COARSE_WALL_TIME_S else None)
    return solve_min_time(model, problem, bound, settings, guess)


def via_times(problem: PlanProblem, traj: Trajectory) -> np.ndarray:
    """When the transcription's plan ``traj`` passes ``problem``'s via points [s] (its
    segments' ends)."""
    from falcon_plan.planning.refinement import plan_segments

    return traj.t_s[np.cumsum(plan_segments(problem, traj))[:-1]]

COLLAPSE_S = 2e-4
"""A pulse shorter than this [s] (at a leg's start or end, or between two of its switches)
has collapsed: :func:`without_collapsed` removes it (a fifth of the device's 1 ms control
period, which holds one command through it: the device could not show such a pulse; on
moving_start_reverse a guessed start pulse took 64 Newton iterations to shrink to 3 ramps)."""


def without_collapsed(pattern: CommandPattern, duration_s: float) -> CommandPattern | None:
    """``pattern`` (solved, or given up, with T = ``duration_s`` [s]) without the pulses that
    collapsed there (:data:`COLLAPSE_S`: a first switch that reached the start flips the leg's
    starting sign instead, a last one that reached the end goes, two switches of a leg that met
    both go; the minimisation over surplus switch times cannot remove a pulse itself, the
    phases must stay longer than their ramps); None when none collapsed."""
    legs, signs = [], list(pattern.signs)
    for leg, times in enumerate(pattern.switches_s):
        kept = sorted(times)
        if kept and kept[0] < COLLAPSE_S:
            kept, signs[leg] = kept[1:], -signs[leg]
        if kept and kept[-1] > duration_s - COLLAPSE_S:
            kept = kept[:-1]
        k = 0
        while k + 1 < len(kept):
            if kept[k + 1] - kept[k] < COLLAPSE_S:
                del kept[k:k + 2]
            else:
                k += 1
        legs.append(tuple(kept))
    if tuple(legs) == tuple(tuple(sorted(t)) for t in pattern.switches_s) and tuple(signs) == pattern.signs:
        return None
    return CommandPattern(tuple(signs), tuple(legs), pattern.via_s, pattern.via_flips)  # type: ignore[arg-type]


__all__ = ["CommandPattern", "Phases", "pattern_of", "candidate_patterns", "with_dips", "square_switches",
           "coarse_intervals", "coarse_solve", "via_times", "without_collapsed", "COARSE_COMMAND_POINTS",
           "COARSE_INTERVALS", "SWITCH_RAMP_S", "COLLAPSE_S"]
