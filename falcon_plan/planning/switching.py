"""Exact bang-bang minimum-time motions: shooting on the switching times.

Why: with a constant command limit, every benchmark solution of the minimum-time
transcription is bang-bang: each leg's command sits at +-(tc_max - reserve) and changes sign
once or twice (``docs/figures/bang-bang.png``). Such a motion is fixed by a handful of numbers,
the switch times and the duration, while the transcription's duration converges only at second
order in 1/N (0.3 % needs N = 24, ~30 ms of IPOPT). So the planner reads the command pattern
off a coarse transcription and solves for those numbers with the exact forward dynamics:

- **pattern** (:class:`CommandPattern`): each leg's starting sign and switch times, read
  from a plan's commands (:func:`pattern_of`);
- **unknowns** z = (every switch time, T) [s]; **equations**: the state at T, integrated
  with RK4 through the model's forward dynamics (``steps_per_phase`` steps between
  consecutive switches of any leg), equals the goal state. As many unknowns as equations
  (six without via points): Newton's method solves them in 2-7 iterations, the Jacobian of
  the final state with respect to the phase durations coming from CasADi's AD through a
  compiled RK4 step at the start and from Broyden's update after that;
- every switch is a linear command ramp of :data:`SWITCH_RAMP_S` (the motion then has a
  continuous command, which a drive and a piecewise-linear acceleration can follow);
- **optimality check** (Pontryagin's principle): with the multipliers lam of the terminal
  equations (grad T = G^T lam), more command on leg i over step j changes T by
  -lam^T dx(T)/du_ij per unit. The pattern is optimal only if more command in its own
  direction never lengthens the motion on any step (:data:`CHECK_TOLERANCE`); a missed
  switch or a singular arc shows as steps that hurt, and the pattern is rejected;
- **converged duration**: the same solve with twice the steps per phase, extrapolated at the
  fourth order of RK4 (:func:`refinement`).

It applies to a constant limit and to the device's speed-dependent limit (:class:`CommandRule`:
there each leg's command rides +-(L(w_s) - reserve), the limit the device allows at the leg
speed the control period samples, solved inside the RK4 step, with steps of at most
:data:`DEVICE_STEP_S`; Pontryagin's check is the same, the multipliers of the mixed
command-state constraint entering through the adjoint of that closed-loop step), with or
without via points (their pass times are unknowns too, and a leg may switch exactly at one). With via
points a pattern can have more switches than equations (two of the three benchmark via
problems: 1 and 4 more): T is then minimised over the surplus switch times, the others
solved from the equations for each (:func:`_minimise_on_family`). Everywhere else, and
whenever the shooting fails, the check rejects the pattern or the plan fails the dense
re-check, the planner keeps the transcription and its own refinement sequence.

Friction with a sign (Coulomb, Stribeck: tanh(w / w_s)) does not change the bang-bang
structure (the command still enters affinely), but the friction torque changes sign within
~0.1 ms where a leg reverses (and sets in over as long at a start from rest): on the coarse
steps RK4 misses it and the output nodes straddle it (2.9 % over the bound on the dense
re-check of a calibrated model). So those places are found (:func:`find_reversals`) and the
steps and output nodes graded down to a fraction of that time there (:func:`phase_grid`).
"""
from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
from pathlib import Path
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import casadi as ca
import numpy as np

from falcon_plan.compiled import BufferedFunction, build_shared_library
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import LEG_COULOMB_FIELDS
from falcon_plan.model.saturation import SaturationModel
from falcon_plan.planning.bound import CommandBound, command_on_limit, leg_motion, sampled_speed
from falcon_plan.planning.casadi_planner import (DEFAULT_HESSIAN, DEFAULT_PROFILE, MinTimeSettings, NodeMotion, SolveResult,
                                                 initial_guess, nodes_to_trajectory, payload_model, solve_min_time,
                                                 via_nodes)
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.trajectory import Trajectory

STEPS_PER_PHASE = 2
"""RK4 steps between consecutive switches in the plan's solve (the refinement doubles it).
On the benchmark problems 2 steps take the same Newton iterations as 3 and pass the same
optimality checks, the extrapolated durations from 2 and 4 steps agree with those from 3 and
6 within 2e-5 (relative), and a solve costs a third less; with 1 step three problems fail the
check (issue 12). The returned motion is re-solved on the output grid anyway (:func:`sample`)."""
SWITCH_RAMP_S = 2e-5
"""Length of the linear command ramp at every switch [s] (the device runs at 1 kHz: a ramp of
20 us is a step to it; the ramp costs ~1e-5 of the duration per switch)."""
OUTPUT_STEP_S = 4e-3
"""Longest interval of the returned trajectory [s] (its acceleration is piecewise linear
between nodes; the command between them leaves the bound by < 0.3 % at this spacing on the
benchmark problems, < 0.1 % at 2 ms, which doubles the nodes and the dense re-check's cost)."""
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
room allows (:func:`~falcon_plan.planning.casadi_planner.initial_guess`): its duration is then
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
CHECK_TOLERANCE = 0.02
"""The optimality check passes when no step hurts by more than this fraction of the most
helpful step's effect (steps next to a switch have nearly zero effect either way)."""
MAX_ITERATIONS = 20
"""Newton iterations before a pattern is given up (converging ones take 2-7)."""
FAMILY_FIRST_STEP = 0.02
"""The first step over the surplus event times, as a fraction of T (the BFGS model's scale)."""
FAMILY_TOLERANCE = 1e-8
"""The minimisation over surplus event times stops when its model promises less than this
fraction of T."""
FAMILY_STALL = 1e-5
"""Where no step along the model's direction shortens the motion any more (T is then flat to
the Newton solves' tolerance, ~1e-9 of T), the minimisation ends there if the model promised
less than this fraction of T, else the pattern is given up. (Under the device's limit, whose
L(w_s) has kinks in its second derivative, the model promised 1.4e-6 where it stalled on the
benchmark problem edge_top_to_right, its T 0.004 % from a 192-interval solve.)"""
FAMILY_MAX_STEPS = 25
"""Steps of that minimisation before the pattern is given up."""
MAX_CANDIDATES = 4
"""Patterns tried per coarse plan (:func:`candidate_patterns`)."""
POSITION_TOLERANCE_M = 1e-7
"""Largest position error at T [m] of a converged shooting solve."""
VELOCITY_TOLERANCE_M_S = 1e-5
"""Largest velocity error at T [m/s] of a converged shooting solve."""
STEP_FLAGS = ("-O1", "-march=native")
"""Compiler options of the RK4 step, its Jacobian and adjoint (measured: the Jacobian 63 us
a call against 74 us at -O1 alone and 83 us at -O2, which compiles for longer still). The
compilation is the longest of the project: about 155 s for the constant rule on this machine
(8 s at -O0, whose code is slower; CasADi's ``avoid_stack`` halves the time and costs ~8 % a
call), so ``dev.py`` builds it at set-up (:mod:`falcon_plan.compiled.prepare`)."""
FRICTION_REGRADINGS = 2
"""With a friction sign, the solve is repeated at most this many times on steps graded around
the legs' reversals (:func:`find_reversals`): first found on a run with
:data:`REVERSAL_SEARCH_STEPS` times the steps, then again on the graded run itself, solved
once more only if one of them moved by more than its width."""
REVERSAL_SEARCH_STEPS = 4
"""Steps per phase of the run the reversals are first found on, per step of the solve."""
DEVICE_OUTPUT_STEP_S = 2.5e-4
"""Longest interval of a device-limit plan's output where a leg's limit is changing (between
its value at rest and the full range) [s]: the command follows L(w_s), a cubic in the speed,
which a linear acceleration between nodes 4 ms apart missed by 11-16 % (on the dense
re-check of the benchmark problems); elsewhere :data:`OUTPUT_STEP_S`."""
DEVICE_STEP_S = 4e-3
"""Longest RK4 step under the device's limit [s]: the command follows L(w_s), which turns from
2500 to 4096 within a few ms of a leg's reversal and has kinks in its second derivative (at
w_s = 0 and at the release speed), so RK4 needs short steps there. With 2 steps per phase the
duration of the benchmark move (0, 0, 0.12) -> (0.03, 0.02, 0.14) m was 0.9 % off a
192-interval transcription; with at most 2 ms steps within 0.01 %. With at most 4 ms steps
the 37 benchmark problems' durations moved from those of 2 ms steps by 1.7e-4 at most
(moving_both), the rest by < 1e-4, all within 0.06 % of 192-interval solves (the returned
motion is re-solved on the output grid, nodes 0.25 ms apart where the limit changes,
:data:`DEVICE_OUTPUT_STEP_S`), for about a quarter less time in the switching stage."""
RK4_ORDER = 4
"""Convergence order of the duration in the step length (for the extrapolation)."""


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
    """Switches added as a trial pulse (:func:`with_pulse`; indices in :attr:`times_s`): T is
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


def not_applicable(problem: PlanProblem, bound: CommandBound) -> str | None:
    """Why the switching-time solve does not apply to ``problem`` under ``bound`` (None when it
    does): it applies to both kinds of bound (under the device's limit the commands ride
    L(w_s) - reserve, :class:`CommandRule`), with or without via points."""
    if bound.kind not in ("constant", "device"):
        return f"a command bound of kind {bound.kind!r}"
    return None


# --- compiled pieces --------------------------------------------------------------------

_lock = threading.Lock()
_steppers: dict[Any, "_Stepper"] = {}


class _Stepper:
    """One RK4 step of a model's forward dynamics, x = (p, v) [m, m/s] -> x', with the command
    of a :class:`CommandRule` (constant: sign * level + delta; device: riding the device's
    limit, :func:`~falcon_plan.planning.bound.command_on_limit`), its sign ramping linearly
    from s0 to s1 over the step of h [s]; its Jacobian blocks d/dx (6, 6) and d/dh (6,) and its
    adjoint (mu -> mu^T d/dx, mu^T d/ddelta, the latter the check's figure): compiled once per
    parameter set and rule and called in place (:class:`~falcon_plan.compiled.BufferedFunction`:
    ~5 us a step, ~65 us with the Jacobian, ~12 us the adjoint, for the constant rule)."""

    def __init__(self, model: FalconModel, rule: str, saturation: SaturationModel) -> None:
        self.rule = rule
        self.lock = threading.Lock()  # the buffers are shared: planner threads take turns per run
        name = f"falcon_rk4_{rule}_step"
        recipe = _recipe_file(model, rule, saturation)
        libraries = _recorded_libraries(recipe)
        if libraries is not None:  # built before on this machine: load it without the ~0.4 s of symbolics
            step_lib, command_lib = libraries
            self.step, self.jac, self.adjoint = (BufferedFunction(ca.external(n, str(step_lib)), step_lib)
                                                 for n in (name, name + "_jac", name + "_adj"))
            self.command = BufferedFunction(ca.external(name + "_command", str(command_lib)), command_lib)
            return
        fns = model.functions
        n_eff = fns.expressions.eff.numel()
        x, s0, s1 = ca.SX.sym("x", 6), ca.SX.sym("s0", 3), ca.SX.sym("s1", 3)
        h, eff, level, delta = ca.SX.sym("h"), ca.SX.sym("eff", n_eff), ca.SX.sym("level"), ca.SX.sym("delta", 3)

        def rate(state: ca.SX, sign: ca.SX) -> ca.SX:
            p, v = state[:3], state[3:]
            u = sign * level + delta if rule == "constant" else \
                command_on_limit(model, saturation, p, v, sign, eff, level, delta)
            return ca.vertcat(v, fns.forward_dynamics(p, v, u, eff))

        mid = 0.5 * (s0 + s1)
        k1 = rate(x, s0)
        k2 = rate(x + 0.5 * h * k1, mid)
        k3 = rate(x + 0.5 * h * k2, mid)
        k4 = rate(x + h * k3, s1)
        inputs = [x, s0, s1, h, eff, level, delta]
        out = ca.cse(x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4))
        step = ca.Function(name, inputs, [out])
        jac = ca.Function(name + "_jac", inputs, [ca.jacobian(out, x), ca.jacobian(out, h)])
        mu = ca.SX.sym("mu", 6)
        adjoint = ca.Function(name + "_adj", inputs + [mu], [ca.jtimes(out, x, mu, True), ca.jtimes(out, delta, mu, True)])
        library = build_shared_library(name, [step, jac, adjoint], STEP_FLAGS)
        self.step, self.jac = BufferedFunction(step, library), BufferedFunction(jac, library)
        self.adjoint = BufferedFunction(adjoint, library)
        zero = ca.DM.zeros(3)
        command = ca.Function(name + "_command", [x, s0, eff, level], [
            s0 * level if rule == "constant" else command_on_limit(model, saturation, x[:3], x[3:], s0, eff, level, zero)])
        command_library = build_shared_library(command.name(), [command], STEP_FLAGS)
        self.command = BufferedFunction(command, command_library)
        """The command [command units] at state x with sign s0 (no offset)."""
        if library is not None and command_library is not None:
            _record_libraries(recipe, library, command_library)

    def commands(self, states: np.ndarray, signs: np.ndarray, eff: np.ndarray, level: float) -> np.ndarray:
        """The commands (n, 3) [command units] at ``states`` (n, 6) with ``signs`` (n, 3)."""
        buf = self.command
        out = np.empty((len(states), 3))
        with self.lock:
            buf.inputs[2][:] = eff
            buf.inputs[3][:] = level
            for n, (x, s) in enumerate(zip(states, signs)):
                buf.inputs[0][:] = x
                buf.inputs[1][:] = s
                buf()
                out[n] = buf.outputs[0]
        return out

    def adjoint_pass(self, states: np.ndarray, eff: np.ndarray, level: float, hs: np.ndarray, s0s: np.ndarray,
                     s1s: np.ndarray, mu: np.ndarray, jumps: dict[int, np.ndarray]) -> list[np.ndarray]:
        """Backward through the steps of a run (``states`` from :meth:`run`) from the costate
        ``mu`` (6,) at the end, adding ``jumps[n]`` (3,) to its position part at state n:
        per step, mu^T d x'/d delta (3,) (more command on the whole step), in time order."""
        buf = self.adjoint
        mu = np.array(mu, float)
        ddelta = []
        with self.lock:
            buf.inputs[4][:] = eff
            buf.inputs[5][:] = level
            buf.inputs[6][:] = 0.0
            for n in reversed(range(len(hs))):
                if n + 1 in jumps:
                    mu[:3] += jumps[n + 1]
                buf.inputs[0][:] = states[n]
                buf.inputs[1][:] = s0s[n]
                buf.inputs[2][:] = s1s[n]
                buf.inputs[3][:] = hs[n]
                buf.inputs[7][:] = mu
                buf()
                ddelta.append(buf.outputs[1].copy())
                mu = buf.outputs[0].copy()
        return ddelta[::-1]

    def run(self, x0: np.ndarray, eff: np.ndarray, level: float, hs: np.ndarray, s0s: np.ndarray,
            s1s: np.ndarray, jacobians: bool = False,
            deltas: np.ndarray | None = None) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        """The states after each step (n + 1, 6), from ``x0``, with the rule's ``level`` and the
        signs ``s0s``, ``s1s`` (n, 3) at each step's ends (and ``deltas`` (n, 3) [command units]
        added to the commands; default none); with ``jacobians`` also each step's
        (d/dx (6, 6), d/dh (6,)) at its start."""
        states = np.empty((len(hs) + 1, 6))
        states[0] = x0
        blocks = []
        with self.lock:
            for buf in (self.step, self.jac):
                buf.inputs[4][:] = eff
                buf.inputs[5][:] = level
                buf.inputs[6][:] = 0.0
            for n, (h, s0, s1) in enumerate(zip(hs, s0s, s1s)):
                for buf in ((self.step, self.jac) if jacobians else (self.step,)):
                    buf.inputs[0][:] = states[n]
                    buf.inputs[1][:] = s0
                    buf.inputs[2][:] = s1
                    buf.inputs[3][:] = h
                    if deltas is not None:
                        buf.inputs[6][:] = deltas[n]
                    buf()
                if jacobians:
                    out = self.jac.outputs
                    blocks.append((out[0].copy(), out[1].copy()))
                states[n + 1] = self.step.outputs[0]
        return states, blocks


_RECIPE_SOURCES = ("planning/switching.py", "planning/bound.py", "compiled/build.py", "model")
"""The sources a step's expressions come from (relative to the package; a folder: every .py
in it): a change in any of them is a new recipe, built and compiled afresh."""


def _recipe_file(model: FalconModel, rule: str, saturation: SaturationModel | None) -> Path:
    """Where the libraries of the step of ``model``, ``rule`` and ``saturation`` are recorded once
    built: a file in the kernel cache named by a hash of everything the step is made from (the
    sources, the parameter set, limits, rule, saturation, flags, CasADi's version)."""
    import hashlib

    from falcon_plan.compiled.build import cache_dir

    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for source in _RECIPE_SOURCES:
        path = package / source
        for file in sorted(path.glob("*.py")) if path.is_dir() else [path]:
            digest.update(file.name.encode())
            digest.update(file.read_bytes())
    digest.update(repr((model.params, model.limits, model.functions.expressions.eff.numel(), rule,
                        saturation if rule == "device" else None, STEP_FLAGS, ca.__version__)).encode())
    return cache_dir() / f"falcon_rk4_{rule}_step-{digest.hexdigest()[:20]}.recipe"


def _recorded_libraries(recipe: Path) -> tuple[Path, Path] | None:
    """The (step, command) libraries ``recipe`` records, or None when it does not exist or names
    a library that is gone."""
    try:
        step_lib, command_lib = (Path(line) for line in recipe.read_text().split("\n")[:2])
    except (OSError, ValueError):
        return None
    return (step_lib, command_lib) if step_lib.is_file() and command_lib.is_file() else None


def _record_libraries(recipe: Path, step_lib: Path, command_lib: Path) -> None:
    """Record the built libraries for ``recipe`` (atomically; a failure only costs the next
    process the symbolics again)."""
    try:
        part = recipe.with_suffix(f".{os.getpid()}.part")
        part.write_text(f"{step_lib}\n{command_lib}\n")
        part.replace(recipe)
    except OSError:
        pass


def _stepper(model: FalconModel, rule: CommandRule) -> _Stepper:
    """The :class:`_Stepper` of ``model``'s parameter set and ``rule`` (built and compiled once)."""
    saturation = rule.saturation if rule.kind == "device" else None
    key = (model.params, model.limits, model.functions.expressions.eff.numel(), rule.kind, saturation)
    with _lock:
        if key not in _steppers:
            _steppers[key] = _Stepper(model, rule.kind, rule.saturation)
        return _steppers[key]


@dataclass(frozen=True)
class CommandRule:
    """How a pattern's commands are set: ``kind`` "constant", +-``level`` (tc_max - reserve)
    [command units]; or "device", riding the device's limit ``saturation`` minus the reserve
    ``level`` [command units] (:func:`~falcon_plan.planning.bound.command_on_limit`)."""

    kind: str
    level: float
    saturation: SaturationModel

    @classmethod
    def of(cls, bound: CommandBound) -> "CommandRule":
        """The rule of a plan under ``bound``."""
        if bound.kind == "constant":
            return cls("constant", bound.tc_max - bound.reserve, bound.saturation)
        return cls("device", bound.reserve, bound.saturation)


@dataclass(frozen=True)
class StepPlan:
    """The integration steps of a phase sequence (one row per step): length h (n,) [s], the
    commands' signs at its start u0 and end u1 (n, 3) (+-1; between on a ramp), the phase it belongs to
    (n,) (-1 for a command ramp) and its share of that phase's regular span (n,) (dh/d of the
    phase's duration; 0 for a ramp); ``ends[j]`` is the index of the state at the end of
    phase j."""

    h: np.ndarray
    u0: np.ndarray
    u1: np.ndarray
    phase: np.ndarray
    share: np.ndarray
    ends: np.ndarray


@dataclass(frozen=True)
class Reversal:
    """Where a leg's speed passes zero (or starts or ends at rest) in a model with a
    friction sign (tanh(w / w_s), :mod:`falcon_plan.model.effects`): its friction torque
    changes sign within a few ``width`` there, so the steps are graded down to a fraction
    of it (:func:`phase_grid`). ``phase``: the phase it falls in; ``at`` and ``width``: its
    place and w_s / |dw/dt| as fractions of that phase's regular span (after any ramp)."""

    phase: int
    at: float
    width: float


GRADED_OFFSETS = np.array([0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0])
"""Nodes added on both sides of a :class:`Reversal`, in its widths (divided by the grid's
fineness): a linear acceleration between them follows the friction's tanh within ~0.2 % of
the command bound, and RK4 integrates through it; past 8 widths tanh is flat to 5e-7 and the
phase's own steps take over (offsets longer than them are left out)."""


def phase_grid(count: int, reversals: Any = (), fineness: float = 1.0) -> np.ndarray:
    """The step lengths of one phase as fractions of its regular span (summing to 1):
    ``count`` equal steps, plus the nodes of :data:`GRADED_OFFSETS` around each of
    ``reversals`` (:class:`Reversal` of this phase), their spacing divided by ``fineness``."""
    nodes = [np.linspace(0.0, 1.0, count + 1)]
    for rev in reversals:
        offsets = GRADED_OFFSETS * rev.width / fineness
        offsets = np.concatenate([[0.0], offsets[offsets < 1.0 / count]])
        nodes.append(rev.at + np.concatenate([offsets, -offsets]))
    x = np.unique(np.clip(np.concatenate(nodes), 0.0, 1.0))
    x = x[np.concatenate([[True], np.diff(x) > 1e-9])]
    x[-1] = 1.0
    return np.diff(x)


def _same_reversals(a: tuple[Reversal, ...], b: tuple[Reversal, ...]) -> bool:
    """Whether the reversals ``a`` are those of ``b``, each within its width."""
    return len(a) == len(b) and all(x.phase == y.phase and abs(x.at - y.at) <= y.width
                                    for x, y in zip(sorted(a, key=lambda r: (r.phase, r.at)),
                                                    sorted(b, key=lambda r: (r.phase, r.at))))


def step_plan(phases: Phases, grid: list[np.ndarray]) -> StepPlan:
    """The steps of ``phases`` (their commands' signs) and the steps of each phase
    ``grid[j]`` (fractions of its regular span, :func:`phase_grid`); a phase that starts with
    a command change starts with the ramp (SWITCH_RAMP_S, from the previous phase's command
    to its own)."""
    commands = phases.signs.T                                 # (m, 3) signs
    counts = np.array([len(g) for g in grid], int)
    ramp = np.concatenate([[False], phases.ramp])             # phase j starts with a ramp
    per_phase = counts + ramp
    ends = np.cumsum(per_phase)
    phase = np.repeat(np.arange(len(counts)), per_phase)
    is_ramp = np.zeros(len(phase), bool)
    is_ramp[(ends - per_phase)[ramp]] = True
    share = np.zeros(len(phase))
    share[~is_ramp] = np.concatenate(grid)
    h = (phases.durations - SWITCH_RAMP_S * ramp)[phase] * share
    h[is_ramp] = SWITCH_RAMP_S
    u1 = commands[phase]
    u0 = u1.copy()
    u0[is_ramp] = commands[phase[is_ramp] - 1]
    return StepPlan(h, u0, u1, np.where(is_ramp, -1, phase), share, ends)


def has_friction_sign(model: FalconModel) -> bool:
    """Whether ``model``'s dynamics have a friction torque with a (smoothed) sign: Coulomb,
    per-leg Coulomb or Stribeck friction."""
    eff = model.effects
    return eff.coulomb_Nm + eff.stribeck_Nm + sum(getattr(eff, f) for f in LEG_COULOMB_FIELDS) > 0.0


def find_reversals(model: FalconModel, phases: Phases, steps: StepPlan, states: np.ndarray) -> tuple[Reversal, ...]:
    """The :class:`Reversal` s of a run of ``model`` (``states`` after each of ``steps`` of ``phases``):
    every sign change of a leg speed w = J(p) v (linear between states), and the ends of the
    motion where the legs are at rest, their width from the fastest leg's |dw/dt| there."""
    t = np.concatenate([[0.0], np.cumsum(steps.h)])
    w = leg_motion(model, states[:, :3], states[:, 3:], np.zeros_like(states[:, 3:]))[0]
    smoothing = model.effects.friction_smoothing_rad_s
    found = []  # (time [s], |dw/dt| [rad/s^2])
    rest = [bool(np.abs(w[k]).max() <= 0.1 * smoothing) for k in (0, -1)]
    for k, h in ((0, steps.h[0]), (-1, steps.h[-1])):  # at rest: the friction sets in (dies out) there
        if rest[k]:
            found.append((t[k], float(np.abs(w[1 if k == 0 else -2]).max()) / h))
    for leg in range(3):
        for k in np.nonzero(w[:-1, leg] * w[1:, leg] < 0.0)[0]:
            if (k == 0 and rest[0]) or (k == len(w) - 2 and rest[-1]):
                continue  # the rounding around rest itself
            dw = w[k + 1, leg] - w[k, leg]
            found.append((t[k] - steps.h[k] * w[k, leg] / dw, abs(dw) / steps.h[k]))
    regular = phases.bounds[:-1] + SWITCH_RAMP_S * np.concatenate([[False], phases.ramp])
    span = phases.bounds[1:] - regular
    out = []
    for time_s, rate in found:
        j = int(np.clip(np.searchsorted(phases.bounds, time_s, side="right") - 1, 0, len(span) - 1))
        out.append(Reversal(j, float(np.clip((time_s - regular[j]) / span[j], 0.0, 1.0)),
                            smoothing / max(rate, 1e-6) / span[j]))
    return tuple(out)


# --- the solve ----------------------------------------------------------------------------

@dataclass(frozen=True)
class SwitchingResult:
    """One switching-time solve.

    success : converged, the final state within tolerance and the optimality check passed.
    reason : why not ("" on success).
    pattern : the solved pattern (switch times [s]).
    duration_s : T [s].
    iterations : Newton iterations; jacobians : full Jacobian evaluations (the rest were
        Broyden updates).
    steps_per_phase : RK4 steps between switches (at least; ``counts``: per phase).
    solve_time_s : wall time [s].
    worst_help : the optimality check's figure: the smallest effect of more command on any
        step (in its own direction) on shortening the motion, as a fraction of the largest;
        >= -CHECK_TOLERANCE passes.
    final_error : (position [m], velocity [m/s]) error at T.
    rule : how the commands were set (:class:`CommandRule`).
    jacobian : dc/dz at the solution, Broyden's (or the exact one when the check needed it).
    surplus : event times beyond the equations, over which T was minimised (0: a square solve).
    reversals : where the steps were graded for a friction sign (:class:`Reversal`; empty
        without friction).
    counts : the RK4 steps of each phase (:func:`step_counts`).
    hurting : where the optimality check failed (its worst step): (leg, start [s], end [s]);
        None when it passed or did not run.
    """

    success: bool
    reason: str
    pattern: CommandPattern
    duration_s: float
    iterations: int
    jacobians: int
    steps_per_phase: int
    solve_time_s: float
    worst_help: float = float("nan")
    final_error: tuple[float, float] = (float("nan"), float("nan"))
    rule: CommandRule | None = None
    jacobian: np.ndarray | None = field(default=None, repr=False, compare=False)
    surplus: int = 0
    reversals: tuple[Reversal, ...] = ()
    counts: tuple[int, ...] = ()
    hurting: tuple[int, float, float] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (for the plan report)."""
        return {"success": self.success, "reason": self.reason, **self.pattern.to_dict(),
                "duration_s": self.duration_s, "iterations": self.iterations, "jacobians": self.jacobians,
                "steps_per_phase": self.steps_per_phase, "solve_time_s": self.solve_time_s,
                "worst_help": self.worst_help, "final_error_m": self.final_error[0],
                "final_error_m_s": self.final_error[1], "surplus": self.surplus,
                "graded_reversals": len(self.reversals)}


class _Shooting:
    """The equations c(z) = 0 of a pattern, z = (event times, T) [s] (:attr:`CommandPattern.times_s`):
    the state at T minus the goal state (6), then each via point's position when it is
    passed minus the via point (3 each)."""

    def __init__(self, model: FalconModel, problem: PlanProblem, pattern: CommandPattern, rule: CommandRule,
                 steps_per_phase: int | list[int], reversals: tuple[Reversal, ...] = (),
                 fineness: float = 1.0, grid: list[np.ndarray] | None = None) -> None:
        """``steps_per_phase``: RK4 steps of every phase, or a list of them per phase, plus the
        graded steps around ``reversals`` (their spacing divided by ``fineness``,
        :func:`phase_grid`); or ``grid``, each phase's steps as fractions of it."""
        self.stepper = _stepper(model, rule)
        self.eff = model.effect_vector
        self.pattern, self.rule, self.reversals = pattern, rule, tuple(reversals)
        counts = [int(steps_per_phase)] * pattern.n_phases if np.isscalar(steps_per_phase) \
            else list(steps_per_phase)
        self.grid = grid if grid is not None else \
            [phase_grid(k, [r for r in reversals if r.phase == j], fineness) for j, k in enumerate(counts)]
        self.deadline = math.inf
        """perf_counter time [s] after which the solve on this shooting gives up."""
        self.x0 = np.concatenate([problem.start_m, problem.start_velocity_m_s])
        self.target = np.concatenate([problem.goal_m, problem.goal_velocity_m_s,
                                      np.asarray(problem.via_m, float).ravel()])

    def plan(self, z: np.ndarray) -> tuple[Phases, StepPlan]:
        """The phases and steps of ``z``."""
        phases = self.pattern.phases(float(z[-1]), z[:-1])
        return phases, step_plan(phases, self.grid)

    def feasible(self, z: np.ndarray) -> bool:
        """Every phase longer than its command ramp, T > 0."""
        phases = self.pattern.phases(float(z[-1]), z[:-1])
        return bool(z[-1] > 0 and np.all(phases.durations > SWITCH_RAMP_S))

    def _equations(self, states: np.ndarray, phases: Phases, steps: StepPlan) -> np.ndarray:
        """c from the states of a run."""
        at_via = np.empty((len(self.pattern.via_s), 3))
        for e, k in enumerate(phases.via):
            if k >= 0:
                at_via[k] = states[steps.ends[e], :3]
        return np.concatenate([states[-1], at_via.ravel()]) - self.target

    def residual(self, z: np.ndarray) -> np.ndarray:
        """c(z) [m, m/s]."""
        phases, steps = self.plan(z)
        states, _ = self.stepper.run(self.x0, self.eff, self.rule.level, steps.h, steps.u0, steps.u1)
        return self._equations(states, phases, steps)

    def linearise(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(c(z), dc/dz (n_c, n_z)) at ``z``, the Jacobian by forward sensitivities through
        the steps."""
        phases, steps = self.plan(z)
        states, blocks = self.stepper.run(self.x0, self.eff, self.rule.level, steps.h, steps.u0, steps.u1, True)
        sens = np.zeros((6, self.pattern.n_phases))  # d x / d (phase durations)
        at_end = []
        ends = set(steps.ends.tolist())
        for n, ((a, b), j) in enumerate(zip(blocks, steps.phase.tolist())):
            sens = a @ sens
            if j >= 0:  # a regular step of phase j: h = (d_j - ramp) * share
                sens[:, j] += b * steps.share[n]
            if n + 1 in ends:
                at_end.append(sens.copy())

        def columns(rows: np.ndarray) -> np.ndarray:
            g = np.zeros((rows.shape[0], len(z)))
            g[:, phases.order] = rows[:, :-1] - rows[:, 1:]  # an event ends one phase, starts the next
            g[:, -1] = rows[:, -1]
            return g

        g = np.vstack([columns(sens)] + [columns(at_end[e][:3]) for e in np.argsort(phases.via)
                                         if phases.via[e] >= 0])
        return self._equations(states, phases, steps), g

    def landed(self, z: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``z`` re-solved on this grid as by :meth:`resolved`, stopping as soon as its run
        lands within the solve's own tolerance of the goal and via points (:func:`_converged`:
        one pass on the benchmark problems, 3e-9 to 7e-8 m and 2e-7 to 2e-6 m/s off, where the
        second pass of :meth:`resolved` reached ~1e-10 m; two at most; every step kept
        feasible): (z, the states of its run), one run fewer on the output grid."""
        phases, steps = self.plan(z)
        states, _ = self.stepper.run(self.x0, self.eff, self.rule.level, steps.h, steps.u0, steps.u1)
        for _ in range(2):
            r = self._equations(states, phases, steps)
            if _converged(r):
                break
            trial = z + np.linalg.lstsq(g, -r, rcond=None)[0]
            if not self.feasible(trial):
                break
            z = trial
            phases, steps = self.plan(z)
            states, _ = self.stepper.run(self.x0, self.eff, self.rule.level, steps.h, steps.u0, steps.u1)
        return z, states

    def resolved(self, z: np.ndarray, g: np.ndarray) -> np.ndarray:
        """``z``, solved on this shooting's grid by two Newton passes with the Jacobian ``g``
        of a nearby grid (a solve's own: they differ by the integration error, and Broyden's
        by a few %, so the passes land within ~1e-9 s of a full solve)."""
        for _ in range(2):  # (with surplus event times: the least-norm step)
            z = z + np.linalg.lstsq(g, -self.residual(z), rcond=None)[0]
        return z


def _helps(shooting: "_Shooting", z: np.ndarray, g: np.ndarray) -> np.ndarray:
    """The optimality check's figures at ``z``, (n_steps, 3): for every step but the ramps
    (in time order) and every leg, -dT/du per unit of command in the direction of the step's
    own command (Pontryagin, the module docstring): the multipliers from G^T lam = grad T
    with the Jacobian ``g`` (exact or Broyden's), the via points' added to the costate where
    they are passed, through one adjoint pass of the compiled step (~12 us a step). NaN when
    ``g`` is singular."""
    phases, steps = shooting.plan(z)
    n_regular = int(np.sum(steps.phase >= 0))
    try:  # square: exact; with surplus event times: least squares (exact at the minimum)
        lam = np.linalg.lstsq(g.T, np.eye(len(z))[-1], rcond=None)[0]
    except np.linalg.LinAlgError:
        return np.full((n_regular, 3), np.nan)
    level = shooting.rule.level
    states, _ = shooting.stepper.run(shooting.x0, shooting.eff, level, steps.h, steps.u0, steps.u1)
    jumps = {steps.ends[e]: lam[6 + 3 * k: 9 + 3 * k] for e, k in enumerate(phases.via) if k >= 0}
    more = shooting.stepper.adjoint_pass(states, shooting.eff, level, steps.h, steps.u0, steps.u1, lam[:6], jumps)
    return np.array([phases.signs[:, j] * d for d, j in zip(more, steps.phase) if j >= 0])


def worst_help(helps: np.ndarray) -> float:
    """The optimality check's figure: the smallest entry of ``helps`` as a fraction of the
    largest (>= -CHECK_TOLERANCE passes; -inf when they are not finite)."""
    if not np.all(np.isfinite(helps)):
        return -math.inf
    return float(helps.min() / max(helps.max(), 1e-300))


def _worst_step(shooting: "_Shooting", z: np.ndarray, helps: np.ndarray) -> tuple[int, float, float] | None:
    """The regular step and leg where more command in its own direction lengthens the motion
    most (``helps`` from :func:`_helps` at ``z``): (leg, start [s], end [s]); None when the
    figures are not finite."""
    if not np.all(np.isfinite(helps)):
        return None
    _, steps = shooting.plan(z)
    t = np.concatenate([[0.0], np.cumsum(steps.h)])
    regular = np.nonzero(steps.phase >= 0)[0]
    n, leg = np.unravel_index(int(np.argmin(helps)), helps.shape)
    return int(leg), float(t[regular[n]]), float(t[regular[n] + 1])


def with_pulse(result: SwitchingResult) -> CommandPattern | None:
    """The pattern of a solve that failed the optimality check with a pulse of the opposite
    command added on the leg and step where more of its own command hurt most
    (``result.hurting``; Pontryagin's needle variation: a missed switch pair shows there): two
    switches around the step's middle third (at least twice :data:`COLLAPSE_S`), or, on the
    motion's first (last) step, the leg's starting sign flipped with one switch there (one
    switch before its end). None without
    such a step."""
    if result.hurting is None:
        return None
    leg, start, end = result.hurting
    legs = [list(times) for times in result.pattern.switches_s]
    signs = list(result.pattern.signs)
    width = max((end - start) / 3.0, 2.0 * COLLAPSE_S)  # the pulse's
    if start <= 0.0:
        signs[leg] = -signs[leg]
        added = [start + width]
    elif end >= result.duration_s - 1e-12:
        added = [end - width]
    else:
        middle = 0.5 * (start + end)
        added = [middle - width / 2.0, middle + width / 2.0]
    legs[leg] = sorted(legs[leg] + added)
    first = sum(len(times) for times in legs[:leg])
    return CommandPattern(tuple(signs), tuple(tuple(times) for times in legs),  # type: ignore[arg-type]
                          result.pattern.via_s, result.pattern.via_flips,
                          tuple(first + legs[leg].index(x) for x in added))


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


def follow_ups(result: SwitchingResult) -> list[CommandPattern]:
    """Patterns to try after the failed solve ``result``, from what it ended with: without a
    pulse that collapsed (:func:`without_collapsed`), and with a pulse where the optimality
    check failed (:func:`with_pulse`)."""
    out = [without_collapsed(result.pattern, result.duration_s), with_pulse(result)]
    return [p for p in out if p is not None]


def _converged(residual: np.ndarray) -> bool:
    """Positions (the goal's and the via points') within POSITION_TOLERANCE_M, the goal
    velocity within VELOCITY_TOLERANCE_M_S."""
    position = np.concatenate([residual[:3], residual[6:]])
    return bool(np.abs(position).max() <= POSITION_TOLERANCE_M and np.abs(residual[3:6]).max() <= VELOCITY_TOLERANCE_M_S)


def _newton(shooting: "_Shooting", z: np.ndarray, r: np.ndarray, g: np.ndarray,
            unknowns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, str]:
    """Newton's method on c(z) = 0 over the entries ``unknowns`` of z (as many as equations;
    the others stay), from ``z`` with c = ``r`` and the Jacobian ``g`` (n_c, n_z), damped so
    that the scaled residual falls and every phase stays longer than its ramp, ``g`` updated
    by Broyden after every step: (z, r, g, iterations, why it failed or "")."""
    scale = np.array([100.0] * 3 + [1.0] * 3 + [100.0] * (len(r) - 6))  # 1 cm ~ 0.1 m/s
    iterations = 0
    while not _converged(r):
        if iterations >= MAX_ITERATIONS:
            return z, r, g, iterations, f"no convergence in {MAX_ITERATIONS} iterations"
        if time.perf_counter() > shooting.deadline:
            return z, r, g, iterations, OUT_OF_TIME
        iterations += 1
        try:
            dz = np.zeros_like(z)
            dz[unknowns] = np.linalg.solve(g[:, unknowns], -r)
        except np.linalg.LinAlgError:
            return z, r, g, iterations, "singular terminal Jacobian"
        step = 1.0
        while True:  # damped: stay feasible and reduce the scaled residual
            trial = z + step * dz
            if shooting.feasible(trial):
                r_trial = shooting.residual(trial)
                if np.linalg.norm(scale * r_trial) < np.linalg.norm(scale * r) or step < 1e-3:
                    break
            step *= 0.5
            if step < 1e-3:
                return z, r, g, iterations, "Newton's method stalled (two switches meet or the pattern has no solution)"
        s = trial - z
        g = g + np.outer(r_trial - r - g @ s, s) / float(s @ s)  # Broyden
        z, r = trial, r_trial
    return z, r, g, iterations, ""


def _family_split(g: np.ndarray, preferred: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    """For a pattern with more event times than equations: (dependent, free) indices of z.
    The free ones are the ``preferred`` event times (a trial pulse's), then those least
    needed to meet the equations (the last pivots of a column-pivoted QR of the other
    event-time columns, T's column projected out first: T is always dependent, being the
    objective)."""
    n_c, n_z = g.shape
    surplus = n_z - n_c
    preferred = tuple(preferred)[:surplus]
    others = np.array([k for k in range(n_z - 1) if k not in preferred], int)
    t_col = g[:, -1] / max(float(np.linalg.norm(g[:, -1])), 1e-300)
    events = g[:, others] - np.outer(t_col, t_col @ g[:, others])
    import scipy.linalg  # ~0.2 s to import: only for via points with surplus switch times

    _, _, pivots = scipy.linalg.qr(events, pivoting=True, mode="economic")
    free = np.sort(np.concatenate([np.array(preferred, int), others[pivots[len(others) - surplus + len(preferred):]]]))
    return np.setdiff1d(np.arange(n_z), free), free


def _minimise_on_family(shooting: "_Shooting", z: np.ndarray, r: np.ndarray, g: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, str]:
    """The shortest motion of a pattern with k more event times than equations: T minimised
    over the k free event times s (:func:`_family_split`), the others and T solved from the
    equations for every s (:func:`_newton`), dT/ds = -[G_dep^-1 G_free]_T by the implicit
    function theorem with the exact Jacobian at every accepted point (Broyden's is a few %
    off across the steps it did not take: too little for Newton's method, too much for a
    gradient that has to vanish), a BFGS model of d2T/ds2 and a backtracking line search on
    T. Stops when the model promises less than :data:`FAMILY_TOLERANCE` of T. Returns
    (z, c, Jacobian, Newton iterations, exact Jacobians, why it failed or "")."""
    dependent, free = _family_split(g, shooting.pattern.pulse)
    z, r, g, iterations, why = _newton(shooting, z, r, g, dependent)
    jacobians = 0
    if why:
        return z, r, g, iterations, jacobians, why

    def exact_gradient(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nonlocal jacobians
        jacobians += 1
        r, g = shooting.linearise(z)
        return r, g, -np.linalg.solve(g[:, dependent], g[:, free])[-1]

    r, g, grad = exact_gradient(z)
    hessian = np.eye(len(free)) * max(float(np.linalg.norm(grad)), 1e-12) / (FAMILY_FIRST_STEP * z[-1])
    for _ in range(FAMILY_MAX_STEPS):
        if time.perf_counter() > shooting.deadline:
            return z, r, g, iterations, jacobians, OUT_OF_TIME
        if without_collapsed(shooting.pattern.with_times(z[:-1]), float(z[-1])) is not None:
            return z, r, g, iterations, jacobians, "a pulse collapsed (shorter than a few command ramps)"
        step = -np.linalg.solve(hessian, grad)
        gain = -float(grad @ step)
        if gain <= FAMILY_TOLERANCE * z[-1]:
            return z, r, g, iterations, jacobians, ""
        alpha = 1.0
        while True:
            trial = z.copy()
            trial[free] += alpha * step
            if shooting.feasible(trial):
                z_new, r_new, _, its, why = _newton(shooting, trial, shooting.residual(trial), g, dependent)
                iterations += its
                if not why and z_new[-1] < z[-1]:
                    break
            alpha *= 0.5
            if alpha < 1e-3:  # no descent: converged to the noise of the solves, or lost
                return z, r, g, iterations, jacobians, "" if gain <= FAMILY_STALL * z[-1] else \
                    f"the minimum over the surplus switch times was not found ({gain / z[-1]:.1e} of T left)"
        r_new, g_new, grad_new = exact_gradient(z_new)
        s_k, y_k = z_new[free] - z[free], grad_new - grad
        if float(y_k @ s_k) > 0.0:  # BFGS
            hs = hessian @ s_k
            hessian = hessian - np.outer(hs, hs) / float(s_k @ hs) + np.outer(y_k, y_k) / float(y_k @ s_k)
        z, r, g, grad = z_new, r_new, g_new, grad_new
    return z, r, g, iterations, jacobians, f"no minimum over the surplus switch times in {FAMILY_MAX_STEPS} steps"


def _separated(z: np.ndarray) -> np.ndarray:
    """``z`` (event times, T) [s] with events closer than 3 command ramps moved apart (later
    ones later by what is missing): a coarse plan whose legs change sign between the same
    two samples gives them the same time, which no phase sequence can have."""
    z = z.copy()
    order = np.argsort(z[:-1], kind="stable")
    for a, b in zip(order[:-1], order[1:]):
        z[b] = max(z[b], z[a] + 3.0 * SWITCH_RAMP_S)
    return z


def step_counts(pattern: CommandPattern, rule: CommandRule, duration_s: float, steps_per_phase: int) -> list[int]:
    """RK4 steps of each phase of ``pattern`` in a solve with ``rule``: ``steps_per_phase``;
    under the device's limit at least one per :data:`DEVICE_STEP_S` of the phase (at T =
    ``duration_s`` [s], the guess: fixed for the solve, so its equations stay smooth)."""
    if rule.kind == "constant":
        return [steps_per_phase] * pattern.n_phases
    durations = np.maximum(pattern.phases(duration_s).durations, 0.0)
    return [max(steps_per_phase, math.ceil(d / DEVICE_STEP_S)) for d in durations]


OUT_OF_TIME = "ran out of its share of the time budget"
"""Why a solve stopped at its deadline."""


def solve_switching(model: FalconModel, problem: PlanProblem, bound: CommandBound, pattern: CommandPattern,
                    duration_guess_s: float, steps_per_phase: int = STEPS_PER_PHASE,
                    deadline_s: float = math.inf) -> SwitchingResult:
    """Solve for the switch times and duration of ``pattern`` (a guess of them) that bring
    ``model`` (with the problem's payload added) from ``problem``'s start to its goal state with
    the commands at +-(bound.tc_max - bound.reserve), and check that they are the minimum-time
    motion; never raises for failure (see ``success``). ``duration_guess_s``: T's guess [s];
    ``steps_per_phase``: RK4 steps between consecutive events; ``deadline_s``: the
    ``time.perf_counter()`` time [s] after which Newton's method and the minimisation stop
    (a failure, :data:`OUT_OF_TIME`).

    z: the event times and T. With as many unknowns as equations (5 free switches plus 2 per
    via point, the generic bang-bang optimum of this problem class): Newton's method on
    c(z) = 0 (:func:`_newton`), the Jacobian by forward sensitivities at the start and
    Broyden's update after every step (a step costs 5 us without its Jacobian, 65 us with
    it). With more (a leg switching again near a via point): T minimised over the surplus
    (:func:`_minimise_on_family`). The optimality check by one adjoint pass with the
    multipliers from Broyden's Jacobian, and from the exact one when that is in doubt."""
    t_start = time.perf_counter()
    model = payload_model(model, problem)
    rule = CommandRule.of(bound)
    z = np.append(pattern.times_s, duration_guess_s)
    iterations = jacobians = 0
    n_equations = 6 + 3 * len(problem.via_m)

    def result(success: bool, reason: str, help_: float = math.nan, g: np.ndarray | None = None,
               r: np.ndarray | None = None) -> SwitchingResult:
        error = (math.nan, math.nan) if r is None else \
            (float(np.abs(np.concatenate([r[:3], r[6:]])).max()), float(np.abs(r[3:6]).max()))
        return SwitchingResult(success, reason, pattern.with_times(z[:-1]), float(z[-1]), iterations, jacobians,
                               steps_per_phase, time.perf_counter() - t_start, help_, error, rule, g,
                               max(len(z) - n_equations, 0), shooting.reversals if shooting else (),
                               tuple(counts))

    shooting: _Shooting | None = None
    counts: list[int] = []
    if len(z) < n_equations or len(pattern.via_s) != len(problem.via_m):
        return result(False, f"a pattern with {pattern.n_switches} free switches (the planner needs at least "
                             f"{square_switches(len(problem.via_m))}: as many unknowns as equations)")
    z = _separated(z)
    counts = step_counts(pattern, rule, float(z[-1]), steps_per_phase)
    shooting = _Shooting(model, problem, pattern, rule, counts)
    shooting.deadline = deadline_s
    if not shooting.feasible(z):
        return result(False, "two switches closer than the command ramp")
    r, g = shooting.linearise(z)
    jacobians = 1
    # with a friction sign: solved again on steps graded at the legs' reversals, found on a
    # finer run of the last solution, until they stay within a width of where they were
    passes = 1 + FRICTION_REGRADINGS * has_friction_sign(model)
    for attempt in range(passes):
        if attempt:
            finder = shooting if attempt > 1 else \
                _Shooting(model, problem, pattern, rule, [REVERSAL_SEARCH_STEPS * k for k in counts])
            phases, steps = finder.plan(z)
            states, _ = finder.stepper.run(finder.x0, finder.eff, rule.level, steps.h, steps.u0, steps.u1)
            reversals = find_reversals(model, phases, steps, states)
            if attempt > 1 and _same_reversals(reversals, shooting.reversals):
                break
            shooting = _Shooting(model, problem, pattern, rule, counts, reversals)
            shooting.deadline = deadline_s
            r = shooting.residual(z)
        if len(z) == n_equations:
            z, r, g, its, why = _newton(shooting, z, r, g, np.arange(len(z)))
        else:
            z, r, g, its, extra, why = _minimise_on_family(shooting, z, r, g)
            jacobians += extra
        iterations += its
        if why:
            return result(False, why, r=r)
    # the check with Broyden's Jacobian (one adjoint pass); only when that is in doubt, with
    # the exact one (Broyden's is exact only along the steps taken: a few % off elsewhere
    # moves the figure by a few %)
    help_ = worst_help(helps := _helps(shooting, z, g))
    if help_ < -CHECK_TOLERANCE:
        r, g = shooting.linearise(z)
        jacobians += 1
        help_ = worst_help(helps := _helps(shooting, z, g))
    if help_ < -CHECK_TOLERANCE:
        hurting = _worst_step(shooting, z, helps)
        return dataclasses.replace(
            result(False, f"not optimal: some command lengthens the motion (check {help_:.3f}; a switch is "
                          "missing or an arc is singular)", help_, g, r), hurting=hurting)
    return result(True, "", help_, g, r)


def refinement(model: FalconModel, problem: PlanProblem, plan: SwitchingResult) -> tuple[float, float]:
    """The duration with twice the steps per phase [s], and the converged duration [s]
    extrapolated from the two (RK4: fourth order), for a solved ``plan`` of ``problem`` with
    ``model`` (the problem's payload added, as in :func:`solve_switching`).

    The finer solve is :meth:`_Shooting.resolved` from the plan: two passes without
    Jacobians, within a few 1e-9 s of a full solve (the full solve's own tolerance; tested)."""
    fine = _Shooting(payload_model(model, problem), problem, plan.pattern, plan.rule, [2 * k for k in plan.counts],
                     plan.reversals, 2.0)
    t_fine = float(fine.resolved(np.append(plan.pattern.times_s, plan.duration_s), plan.jacobian)[-1])
    return t_fine, t_fine + (t_fine - plan.duration_s) / (2.0 ** RK4_ORDER - 1.0)


def sample(model: FalconModel, problem: PlanProblem, plan: SwitchingResult,
           step_s: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The motion of a solved ``plan`` at nodes at most ``step_s`` [s] (default
    :data:`OUTPUT_STEP_S`; under the device's limit the solve's own steps, split where the
    limit changes, see below) apart, with a node at both
    ends of every command ramp: (t (n,), p (n, 3), v (n, 3), a (n, 3)) [s, m, m/s, m/s^2];
    a from the forward dynamics with the command at each node (``model`` with the problem's
    payload added). The last node is the goal state itself (the integration put it within
    the solve's tolerance of it)."""
    model = payload_model(model, problem)
    step_s = OUTPUT_STEP_S if step_s is None else step_s
    phases = plan.pattern.phases(plan.duration_s)
    counts = [max(1, math.ceil((d - (SWITCH_RAMP_S if j and phases.ramp[j - 1] else 0.0)) / step_s))
              for j, d in enumerate(phases.durations)]
    # The solve integrated with a few steps per phase; integrated on this finer grid its
    # events land the motion a few um off the goal, and a trajectory that jumps there would
    # give the executor's finite-difference feed-forward a spike. So the event times are
    # corrected on this grid first.
    z = np.append(plan.pattern.times_s, plan.duration_s)
    if plan.rule.kind == "constant":
        grid = _Shooting(model, problem, plan.pattern, plan.rule, counts, plan.reversals)
        t, states, a, steps = _nodes(model, problem, grid, *grid.landed(z, plan.jacobian))
        return t, states[:, :3], states[:, 3:], a
    # Under the device's limit: the solve's own steps (at most DEVICE_STEP_S), and where a
    # leg's limit is between its value at rest and the full range (it changes within a few
    # ms there) split into nodes DEVICE_OUTPUT_STEP_S apart
    grid = _Shooting(model, problem, plan.pattern, plan.rule, list(plan.counts), plan.reversals)
    _, states, a, steps = _nodes(model, problem, grid, z)
    w, rate = leg_motion(model, states[:, :3], states[:, 3:], a)
    limit = plan.rule.saturation.limit(sampled_speed(w, rate))
    moving = np.any((limit > plan.rule.saturation.static + 1e-6) & (limit < plan.rule.saturation.full - 1e-6), axis=1)
    split = np.where(moving[:-1] | moving[1:], np.ceil(steps.h / DEVICE_OUTPUT_STEP_S), 1).astype(int)
    fractions = [np.repeat(steps.share[steps.phase == j] / split[steps.phase == j], split[steps.phase == j])
                 for j in range(plan.pattern.n_phases)]
    grid = _Shooting(model, problem, plan.pattern, plan.rule, counts, grid=fractions)
    t, states, a, steps = _nodes(model, problem, grid, *grid.landed(z, plan.jacobian))
    return t, states[:, :3], states[:, 3:], a


def _nodes(model: FalconModel, problem: PlanProblem, grid: "_Shooting", z: np.ndarray,
           states: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, StepPlan]:
    """The nodes of ``grid``'s run of ``z`` (its ``states`` when already run): times (n,)
    [s], states (n, 6) (the via points and the goal set exactly) and accelerations (n, 3)
    [m/s^2] with the command at each node, and the steps."""
    phases, steps = grid.plan(z)
    if states is None:
        states, _ = grid.stepper.run(grid.x0, grid.eff, grid.rule.level, steps.h, steps.u0, steps.u1)
    for e, k in enumerate(phases.via):  # the via points and the goal themselves (within ~1e-10 m)
        if k >= 0:
            states[steps.ends[e], :3] = problem.via_m[k]
    states[-1] = np.concatenate([problem.goal_m, problem.goal_velocity_m_s])
    t = np.concatenate([[0.0], np.cumsum(steps.h)])
    t[-1] = z[-1]
    # the command at each node: its step's start command; the last node, the last step's end
    signs = np.vstack([np.asarray(steps.u0), np.asarray(steps.u1[-1])[None, :]])
    commands = grid.stepper.commands(states, signs, grid.eff, grid.rule.level)
    return t, states, np.asarray(model.forward_dynamics(states[:, :3], states[:, 3:], commands)), steps


def trajectory(model: FalconModel, problem: PlanProblem, plan: SwitchingResult, *,
               meta: dict[str, Any] | None = None) -> Trajectory:
    """The solved ``plan`` as a :class:`Trajectory` (linear acceleration between the nodes of
    :func:`sample`, commands from ``model``'s inverse dynamics with the problem's payload),
    carrying ``meta`` and the switching summary."""
    t, p, v, a = sample(model, problem, plan)
    motion = NodeMotion(float(t[-1]), p, v, a, np.diff(t))
    return nodes_to_trajectory(model, problem, motion, source="casadi",
                               meta={**(meta or {}), "n_intervals": len(t) - 1, "profile": "linear",
                                     "switching": plan.to_dict()})


__all__ = ["trajectory", "candidate_patterns", "follow_ups", "with_pulse", "without_collapsed", "CommandPattern", "SwitchingResult", "pattern_of", "not_applicable", "solve_switching", "refinement",
           "sample", "COARSE_COMMAND_POINTS", "STEPS_PER_PHASE", "SWITCH_RAMP_S", "OUTPUT_STEP_S", "COARSE_INTERVALS", "CHECK_TOLERANCE"]
