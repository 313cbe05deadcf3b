"""Exact bang-bang minimum-time motions: shooting on the switching times of a command pattern.

The pattern (:mod:`.pattern`, read off a coarse transcription) fixes the motion up to a
handful of numbers; this module solves for them with the exact forward dynamics:

- **unknowns** z = (every switch time, T) [s]; **equations** (:class:`Shooting`): the state
  at T, integrated with RK4 through the model's forward dynamics (:mod:`.integration`,
  ``steps_per_phase`` steps between consecutive switches of any leg), equals the goal state.
  As many unknowns as equations (six without via points): Newton's method solves them in 2-7
  iterations, the Jacobian of the final state with respect to the phase durations coming from
  forward differences of the compiled RK4 run at the start (:meth:`Shooting.linearise`: each
  phase lengthened, only the steps from it on run again) and from Broyden's update after that;
- **optimality check** (Pontryagin's principle): with the multipliers lam of the terminal
  equations (grad T = G^T lam), more command on leg i over step j changes T by
  -lam^T dx(T)/du_ij per unit. The pattern is optimal only if more command in its own
  direction never lengthens the motion on any step (:data:`CHECK_TOLERANCE`); a missed
  switch or a singular arc shows as steps that hurt, and the pattern is rejected; what a
  failed attempt ended with says what to try next (:func:`follow_ups`);
- **converged duration**: the same solve with twice the steps per phase, extrapolated at the
  fourth order of RK4 (:func:`refinement`).

It applies to a constant limit and to the device's speed-dependent limit (:class:`CommandRule`:
there each leg's command rides +-(L(w_s) - reserve), the limit the device allows at the leg
speed the control period samples, solved inside the RK4 step, with steps of at most
:data:`~falcon_plan.planning.integration.DEVICE_STEP_S`; Pontryagin's check is the same, the
multipliers of the mixed command-state constraint entering through the adjoint of that
closed-loop step), with or without via points (their pass times are unknowns too, and a leg
may switch exactly at one). With via points a pattern can have more switches than equations
(two of the three benchmark via problems: 1 and 4 more): T is then minimised over the surplus
switch times, the others solved from the equations for each (:func:`_minimise_on_family`).
Everywhere else, and whenever the shooting fails, the check rejects the pattern or the plan
fails the dense re-check, the planner keeps the transcription and its own refinement
sequence. With a friction sign the steps are graded where a leg reverses
(:func:`~falcon_plan.planning.integration.find_reversals`) and the solve repeated on them.
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.bound import CommandBound
from falcon_plan.planning.integration import (CommandRule, Reversal, StepPlan, compiled_step, find_reversals,
                                              has_friction_sign, phase_grid, same_reversals, step_counts, step_plan)
from falcon_plan.planning.pattern import (COLLAPSE_S, SWITCH_RAMP_S, CommandPattern, Phases, square_switches,
                                          without_collapsed)
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.planning.transcription import payload_model


STEPS_PER_PHASE = 2
"""RK4 steps between consecutive switches in the plan's solve (the refinement doubles it).
On the benchmark problems 2 steps take the same Newton iterations as 3 and pass the same
optimality checks, the extrapolated durations from 2 and 4 steps agree with those from 3 and
6 within 2e-5 (relative), and a solve costs a third less; with 1 step three problems fail the
check (issue 12). The returned motion is re-solved on the output grid anyway (:func:`.sampling.sample`)."""
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
POSITION_TOLERANCE_M = 1e-7
"""Largest position error at T [m] of a converged shooting solve."""
VELOCITY_TOLERANCE_M_S = 1e-5
"""Largest velocity error at T [m/s] of a converged shooting solve."""
FRICTION_REGRADINGS = 2
"""With a friction sign, the solve is repeated at most this many times on steps graded around
the legs' reversals (:func:`find_reversals`): first found on a run with
:data:`REVERSAL_SEARCH_STEPS` times the steps, then again on the graded run itself, solved
once more only if one of them moved by more than its width."""
REVERSAL_SEARCH_STEPS = 4
"""Steps per phase of the run the reversals are first found on, per step of the solve."""

RK4_ORDER = 4
"""Convergence order of the duration in the step length (for the extrapolation)."""
JACOBIAN_STEP_S = 1e-9
"""The forward difference of :meth:`Shooting.linearise` [s of a phase's duration]: the
terminal Jacobian of the benchmark problems' solved patterns is then within 2e-7 (constant
rule) and 1e-6 (device rule, whose L(w_s) has kinks) of the compiled AD Jacobian it replaced,
relative to each row's largest entry; at 1e-8 s 10 times further off, at 1e-7 s 100 times."""


def not_applicable(problem: PlanProblem, bound: CommandBound) -> str | None:
    """Why the switching-time solve does not apply to ``problem`` under ``bound`` (None when it
    does): it applies to both kinds of bound (under the device's limit the commands ride
    L(w_s) - reserve, :class:`CommandRule`), with or without via points."""
    if bound.kind not in ("constant", "device"):
        return f"a command bound of kind {bound.kind!r}"
    return None


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


class Shooting:
    """The equations c(z) = 0 of a pattern, z = (event times, T) [s] (:attr:`CommandPattern.times_s`):
    the state at T minus the goal state (6), then each via point's position when it is
    passed minus the via point (3 each)."""

    def __init__(self, model: FalconModel, problem: PlanProblem, pattern: CommandPattern, rule: CommandRule,
                 steps_per_phase: int | list[int], reversals: tuple[Reversal, ...] = (),
                 fineness: float = 1.0, grid: list[np.ndarray] | None = None) -> None:
        """The equations of ``pattern`` for ``model`` (its payload already added) from
        ``problem``'s start to its goal (and via points), the commands set by ``rule``.
        ``steps_per_phase``: RK4 steps of every phase, or a list of them per phase, plus the
        graded steps around ``reversals`` (their spacing divided by ``fineness``,
        :func:`phase_grid`); or ``grid``, each phase's steps as fractions of it."""
        self.stepper = compiled_step(model, rule)
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
        states = self.stepper.run(self.x0, self.eff, self.rule.level, steps.h, steps.u0, steps.u1)
        return self._equations(states, phases, steps)

    def linearise(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(c(z), dc/dz (n_c, n_z)) at ``z``. The Jacobian by forward differences of the run
        in each phase's duration (:data:`JACOBIAN_STEP_S`): a phase lengthened stretches its own
        regular steps by their shares, so only the steps from that phase on are run again (about
        half a run a phase); an event time ends one phase and starts the next. Checked against
        central differences of whole runs (tested to 1e-5), and 2.7-4 times faster than the
        compiled AD Jacobian of the step it replaced (12-20 steps' time a call, and most of the
        step's compile time)."""
        phases, steps = self.plan(z)
        states = self.stepper.run(self.x0, self.eff, self.rule.level, steps.h, steps.u0, steps.u1)
        n_phases = self.pattern.n_phases
        sens = np.zeros((6, n_phases))                       # d x(T) / d (phase durations)
        passed = [e for e in np.argsort(phases.via) if phases.via[e] >= 0]
        at_via = np.zeros((len(passed), 3, n_phases))       # d p(via point) / d (phase durations)
        for j in range(n_phases):
            mine = np.flatnonzero(steps.phase == j)
            first = int(mine[0])
            h = steps.h[first:].copy()
            h[mine - first] += JACOBIAN_STEP_S * steps.share[mine]
            moved = self.stepper.run(states[first], self.eff, self.rule.level, h, steps.u0[first:], steps.u1[first:])
            sens[:, j] = (moved[-1] - states[-1]) / JACOBIAN_STEP_S
            for row, e in enumerate(passed):
                end = int(steps.ends[e])
                if end >= first:
                    at_via[row, :, j] = (moved[end - first, :3] - states[end, :3]) / JACOBIAN_STEP_S

        def columns(rows: np.ndarray) -> np.ndarray:
            g = np.zeros((rows.shape[0], len(z)))
            g[:, phases.order] = rows[:, :-1] - rows[:, 1:]  # an event ends one phase, starts the next
            g[:, -1] = rows[:, -1]
            return g

        g = np.vstack([columns(sens)] + [columns(rows) for rows in at_via])
        return self._equations(states, phases, steps), g

    def landed(self, z: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``z`` re-solved on this grid as by :meth:`resolved` (with ``g``, the Jacobian of a
        nearby grid), stopping as soon as its run
        lands within the solve's own tolerance of the goal and via points (:func:`_converged`:
        one pass on the benchmark problems, 3e-9 to 7e-8 m and 2e-7 to 2e-6 m/s off, where the
        second pass of :meth:`resolved` reached ~1e-10 m; two at most; every step kept
        feasible): (z, the states of its run), one run fewer on the output grid."""
        phases, steps = self.plan(z)
        states = self.stepper.run(self.x0, self.eff, self.rule.level, steps.h, steps.u0, steps.u1)
        for _ in range(2):
            r = self._equations(states, phases, steps)
            if _converged(r):
                break
            trial = z + np.linalg.lstsq(g, -r, rcond=None)[0]
            if not self.feasible(trial):
                break
            z = trial
            phases, steps = self.plan(z)
            states = self.stepper.run(self.x0, self.eff, self.rule.level, steps.h, steps.u0, steps.u1)
        return z, states

    def resolved(self, z: np.ndarray, g: np.ndarray) -> np.ndarray:
        """``z``, solved on this shooting's grid by two Newton passes with the Jacobian ``g``
        of a nearby grid (a solve's own: they differ by the integration error, and Broyden's
        by a few %, so the passes land within ~1e-9 s of a full solve)."""
        for _ in range(2):  # (with surplus event times: the least-norm step)
            z = z + np.linalg.lstsq(g, -self.residual(z), rcond=None)[0]
        return z


def _helps(shooting: "Shooting", z: np.ndarray, g: np.ndarray) -> np.ndarray:
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
    states = shooting.stepper.run(shooting.x0, shooting.eff, level, steps.h, steps.u0, steps.u1)
    jumps = {steps.ends[e]: lam[6 + 3 * k: 9 + 3 * k] for e, k in enumerate(phases.via) if k >= 0}
    more = shooting.stepper.adjoint_pass(states, shooting.eff, level, steps.h, steps.u0, steps.u1, lam[:6], jumps)
    return np.array([phases.signs[:, j] * d for d, j in zip(more, steps.phase) if j >= 0])


def worst_help(helps: np.ndarray) -> float:
    """The optimality check's figure: the smallest entry of ``helps`` as a fraction of the
    largest (>= -CHECK_TOLERANCE passes; -inf when they are not finite)."""
    if not np.all(np.isfinite(helps)):
        return -math.inf
    return float(helps.min() / max(helps.max(), 1e-300))


def _worst_step(shooting: "Shooting", z: np.ndarray, helps: np.ndarray) -> tuple[int, float, float] | None:
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


def _newton(shooting: "Shooting", z: np.ndarray, r: np.ndarray, g: np.ndarray,
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


def _minimise_on_family(shooting: "Shooting", z: np.ndarray, r: np.ndarray, g: np.ndarray, beat_s: float = math.inf
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, str]:
    """The shortest motion of a pattern with k more event times than equations: T minimised
    over the k free event times s (:func:`_family_split`), the others and T solved from the
    equations for every s (:func:`_newton`), dT/ds = -[G_dep^-1 G_free]_T by the implicit
    function theorem with the exact Jacobian at every accepted point (Broyden's is a few %
    off across the steps it did not take: too little for Newton's method, too much for a
    gradient that has to vanish), a BFGS model of d2T/ds2 and a backtracking line search on
    T. Stops when the model promises less than :data:`FAMILY_TOLERANCE` of T. Returns
    (z, c, Jacobian, Newton iterations, exact Jacobians, why it failed or "")."""
    if not np.all(np.isfinite(g)):
        return z, r, g, 0, 0, NOT_FINITE
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
    for k in range(FAMILY_MAX_STEPS):
        if time.perf_counter() > shooting.deadline:
            return z, r, g, iterations, jacobians, OUT_OF_TIME
        if without_collapsed(shooting.pattern.with_times(z[:-1]), float(z[-1])) is not None:
            return z, r, g, iterations, jacobians, "a pulse collapsed (shorter than a few command ramps)"
        step = -np.linalg.solve(hessian, grad)
        gain = -float(grad @ step)
        if gain <= FAMILY_TOLERANCE * z[-1]:
            return z, r, g, iterations, jacobians, ""
        if k >= 1 and z[-1] - BEAT_REACH * gain > beat_s:   # (the first step's model is a guess)
            return z, r, g, iterations, jacobians, CANNOT_BEAT
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

NOT_FINITE = "its motion is not finite (the integration left the model's reach)"
"""Why a solve stopped on a residual or Jacobian with an inf or NaN (a guess that drives the
device through a singular configuration)."""
OUT_OF_TIME = "ran out of its share of the time budget"
"""Why a solve stopped at its deadline."""
CANNOT_BEAT = "it would not beat the motion it was asked to beat"
"""Why a minimisation over surplus switch times gave up (``beat_s`` of :func:`solve_switching`)."""
BEAT_REACH = 3.0
"""A minimisation over surplus switch times with a ``beat_s`` gives up when T less this many
times the decrease its quasi-Newton model promises (half of it is the model's own minimum)
stays above ``beat_s``."""


def solve_switching(model: FalconModel, problem: PlanProblem, bound: CommandBound, pattern: CommandPattern,
                    duration_guess_s: float, steps_per_phase: int = STEPS_PER_PHASE,
                    deadline_s: float = math.inf, beat_s: float = math.inf) -> SwitchingResult:
    """Solve for the switch times and duration of ``pattern`` (a guess of them) that bring
    ``model`` (with the problem's payload added) from ``problem``'s start to its goal state with
    the commands at +-(bound.tc_max - bound.reserve), and check that they are the minimum-time
    motion; never raises for failure (see ``success``). ``duration_guess_s``: T's guess [s];
    ``steps_per_phase``: RK4 steps between consecutive events; ``deadline_s``: the
    ``time.perf_counter()`` time [s] after which Newton's method and the minimisation stop
    (a failure, :data:`OUT_OF_TIME`); ``beat_s``: a T [s] the solve is only wanted below (a
    minimisation over surplus switch times that will not reach it gives up early,
    :data:`CANNOT_BEAT`).

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

    shooting: Shooting | None = None
    counts: list[int] = []
    if len(z) < n_equations or len(pattern.via_s) != len(problem.via_m):
        return result(False, f"a pattern with {pattern.n_switches} free switches (the planner needs at least "
                             f"{square_switches(len(problem.via_m))}: as many unknowns as equations)")
    z = _separated(z)
    counts = step_counts(pattern, rule, float(z[-1]), steps_per_phase)
    shooting = Shooting(model, problem, pattern, rule, counts)
    shooting.deadline = deadline_s
    if not shooting.feasible(z):
        return result(False, "two switches closer than the command ramp")
    r, g = shooting.linearise(z)
    jacobians = 1
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(g))):
        return result(False, NOT_FINITE)
    # with a friction sign: solved again on steps graded at the legs' reversals, found on a
    # finer run of the last solution, until they stay within a width of where they were
    passes = 1 + FRICTION_REGRADINGS * has_friction_sign(model)
    for attempt in range(passes):
        if attempt:
            finder = shooting if attempt > 1 else \
                Shooting(model, problem, pattern, rule, [REVERSAL_SEARCH_STEPS * k for k in counts])
            phases, steps = finder.plan(z)
            states = finder.stepper.run(finder.x0, finder.eff, rule.level, steps.h, steps.u0, steps.u1)
            reversals = find_reversals(model, phases, steps, states)
            if attempt > 1 and same_reversals(reversals, shooting.reversals):
                break
            shooting = Shooting(model, problem, pattern, rule, counts, reversals)
            shooting.deadline = deadline_s
            r = shooting.residual(z)
        if len(z) == n_equations:
            z, r, g, its, why = _newton(shooting, z, r, g, np.arange(len(z)))
        else:
            z, r, g, its, extra, why = _minimise_on_family(shooting, z, r, g, beat_s)
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

    The finer solve is :meth:`Shooting.resolved` from the plan: two passes without
    Jacobians, within a few 1e-9 s of a full solve (the full solve's own tolerance; tested)."""
    fine = Shooting(payload_model(model, problem), problem, plan.pattern, plan.rule, [2 * k for k in plan.counts],
                     plan.reversals, 2.0)
    t_fine = float(fine.resolved(np.append(plan.pattern.times_s, plan.duration_s), plan.jacobian)[-1])
    return t_fine, t_fine + (t_fine - plan.duration_s) / (2.0 ** RK4_ORDER - 1.0)


__all__ = ["Shooting", "SwitchingResult", "solve_switching", "refinement", "not_applicable", "follow_ups", "CANNOT_BEAT",
           "with_pulse", "worst_help", "STEPS_PER_PHASE", "CHECK_TOLERANCE", "OUT_OF_TIME"]
