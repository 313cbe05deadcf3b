"""The planning entry point: ``plan(start_m, goal_m, options, model) -> Plan``.

Steps (each reported in :class:`~falcon_plan.planning.report.PlanReport`):

1. Validate: a zero-length move is refused with its own message ("zero_length_move": there
   is nothing to plan); the points inside the workspace (:class:`WorkspaceError` naming
   which and why), and the command bound at rest able to hold the device still against
   gravity at every waypoint (else :class:`InvalidProblemError`, "tc_max_too_small").
2. Minimum-time OCP (:mod:`.transcription`, :mod:`.min_time`) within ``options.solver.time_budget_s``.
3. Dense re-check of the result (:func:`.verify.dense_check`, 10 points per interval).
4. If the optimiser failed, ran out of time or its plan failed the re-check, and
   ``options.solver.fallback``: the ruckig leg-angle reference (:mod:`.fallback`), itself
   re-checked (workspace and commands); ``method`` says which was returned. Otherwise
   :class:`PlanningFailed` with the report attached. Never returns None.
5. Optional (``options``): the refinement sequence (:func:`_refine`): the duration at N/2
   (a cheap partner warm-started from the plan) and, only when that estimate is not
   conclusive, at 2N, with the converged duration extrapolated and the plan's gap to it
   (when the N plan's gap exceeds ``options.checks.optimality_target``, the 2N plan is returned
   instead: mesh refinement from the coarse solution); cross-checks (toppra on the same path
   and on the straight line, ruckig); a closed-loop run on the simulated plant (with the executed peak command against
   the device's limit).

The command bound is ``options.command_bound``: tc_max or the device's speed-dependent
limit (``options.limits.limit``), minus ``options.limits.feedback_reserve`` kept free for feedback.

The service's fast path is ``PlanOptions.fast()``: steps 1-4 only.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from falcon_plan.errors import CrosscheckError, FalconPlanError, InvalidProblemError, PlanningFailed
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning import fallback, pattern, refinement, sampling, shooting, verify, warmstart
from falcon_plan.planning.bound import CommandBound
from falcon_plan.planning.min_time import solve_min_time
from falcon_plan.planning.problem import MAX_INTERVALS, PlanOptions, PlanProblem
from falcon_plan.planning.report import Plan, PlanReport, WorkspaceHandling
from falcon_plan.planning.transcription import MinTimeSettings, SolveResult, payload_model
from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)

_default_model: FalconModel | None = None


def default_model() -> FalconModel:
    """The nominal model (acra2009, default limits), built once."""
    global _default_model
    if _default_model is None:
        _default_model = FalconModel()
    return _default_model


def plan(start_m: Any, goal_m: Any, options: PlanOptions | None = None, model: FalconModel | None = None,
         *, start_velocity_m_s: Any = (0.0, 0.0, 0.0), goal_velocity_m_s: Any = (0.0, 0.0, 0.0),
         via_m: Any = (), payload_kg: float = 0.0) -> Plan:
    """Plan a minimum-time motion of the end effector from ``start_m`` to ``goal_m`` [m].

    Parameters
    ----------
    start_m, goal_m : points (x, y, z) [m], base frame.
    options : :class:`PlanOptions` (default: everything checked; ``PlanOptions.fast()`` for
        latency-critical use).
    model : the dynamics (default: nominal acra2009).
    start_velocity_m_s, goal_velocity_m_s : end velocities [m/s] (default rest).
    via_m : points to pass through, in order [m].
    payload_kg : extra mass at the end effector [kg].

    Returns
    -------
    Plan : ``trajectory`` and ``report``.

    Raises
    ------
    InvalidProblemError, WorkspaceError : bad input (before any solving).
    PlanningFailed : neither the optimiser nor the fallback gave a verified plan (``.report``).
    """
    problem = PlanProblem(start_m, goal_m, start_velocity_m_s, goal_velocity_m_s, via_m, payload_kg)
    return plan_problem(problem, options, model)


def warm_up(model: FalconModel | None = None, options: PlanOptions | None = None,
            prepare_fallback: bool = True) -> float:
    """Build (and compile, first time on this machine) everything a plan with ``model``
    (default nominal) and ``options`` (default ``PlanOptions()``; its refinement, cross-checks
    and plant run are left out) needs, so that the first real query is as fast as the next
    ones, and with ``prepare_fallback`` the ruckig fallback too (~0.15 s more: a service needs it
    instantly; a single plan on the command line only if it falls back); returns the time
    taken [s]. A service calls it at start-up. The compiled kernels are cached on disk, so
    later processes load them in milliseconds (a fresh machine compiles for minutes: about
    3 minutes of one core for each command rule's switching-time step on a 2-core machine;
    ``python -m falcon_plan.compiled.prepare`` builds them ahead)."""
    t0 = time.perf_counter()
    options = (options or PlanOptions()).replace(crosscheck=False, refine=False, plant_check=False)
    start, goal = (0.0, 0.0, 0.12), (0.01, 0.005, 0.125)
    result = plan(start, goal, options, model)
    model = model or default_model()
    if prepare_fallback:
        fallback.ruckig_reference(model, PlanProblem(start, goal), options.command_bound(model.params).at_rest)
    log.info("planner warmed up in %.2f s (%s)", time.perf_counter() - t0, result.report.method)
    return time.perf_counter() - t0


def require_holdable(model: FalconModel, problem: PlanProblem, bound: CommandBound) -> None:
    """Raise InvalidProblemError ("tc_max_too_small") when holding ``model``'s device still
    against gravity at a waypoint of ``problem`` (its payload included) needs more than
    ``bound`` allows at rest."""
    holding = payload_model(model, problem).holding_commands(problem.waypoints_m)
    worst = np.abs(holding).max(axis=1)
    if np.any(worst > bound.at_rest):
        i = int(np.argmax(worst))
        raise InvalidProblemError(
            f"tc_max_too_small: holding still at {problem.waypoints_m[i].tolist()} m against gravity "
            f"(payload {problem.payload_kg} kg) needs |Tc| = {worst[i]:.0f} > {bound.at_rest:g} allowed at "
            f"rest ({bound.describe()})")


def require_nonzero_move(problem: PlanProblem) -> None:
    """Raise InvalidProblemError ("zero_length_move") when ``problem`` is a rest-to-rest move
    that goes nowhere: the device is already at the goal, there is no motion to plan."""
    if problem.is_zero_length:
        raise InvalidProblemError(
            f"zero_length_move: start and goal are the same point {list(problem.start_m)} m, at rest: "
            "nothing to plan (the device is already there); give a goal at least 1 um away")


SWITCHING_BUDGET_SHARE = 0.8
"""Share of the optimiser's time budget after which the switching-time attempts stop (a
pattern the shooting cannot solve can take many Newton iterations: the attempt running then
stops too, :func:`.shooting.solve_switching`'s deadline), so that the transcription keeps
the rest. Under the device's limit the follow-ups of a failed attempt
(:data:`FOLLOW_UP_DEPTH`) are worth most of it: on a loaded machine (load 6 on 2 cores)
via_two_points took 3.4 s for two patterns, where the transcription at N = 24 did not
converge in the whole 5 s budget, and a calibrated Coulomb + payload model 2.5-2.8 s (three
gradings at the legs' reversals, T minimised over two surplus switches)."""


PATTERN_SOURCE_STOPS = ("Maximum_Iterations_Exceeded",)
"""IPOPT statuses of a coarse solve stopped early (besides running out of time) whose last
iterate a pattern is still read from (the switching-time solve, Pontryagin's check and the
dense re-check verify whatever comes of it): under the device's limit via_two_points' coarse
solve needed 67 iterations, and on a loaded machine the coarse solve's wall-time limit
(0.5 s) stopped it on a benchmark problem whose plan then fell back to ruckig
(edge_left_to_bottom, once in three)."""
FOLLOW_UP_DEPTH = 3
"""How many times in a row a failed switching-time attempt's own follow-ups are tried
(:func:`.shooting.follow_ups`: a collapsed pulse removed, a missed pulse added)."""


@dataclass
class _Ledger:
    """What the stages add to the report, kept by the caller of the stages alone: their wall
    times [s] (summed by name, in the order first seen) and their notes (in order)."""

    timings: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    def add(self, stage: Any) -> Any:
        """Book ``stage`` (any stage result: ``timings`` and ``notes``) and return it."""
        for name, seconds in stage.timings.items():
            self.timings[name] = self.timings.get(name, 0.0) + seconds
        self.notes.extend(stage.notes)
        return stage


@dataclass(frozen=True)
class _Setup:
    """A validated request: the problem, options, the model planned with (friction sign
    widened to what the planner takes), the command bound, the model with the problem's
    payload, whether the switching-time solve applies (the option, and the problem), and the
    notes validation makes."""

    problem: PlanProblem
    options: PlanOptions
    model: FalconModel
    bound: CommandBound
    loaded: FalconModel
    switching_applies: bool
    notes: tuple[str, ...]
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class _Outcome:
    """What the optimiser stage produced (mutable while :func:`_optimise` works), with the
    wall times [s] and notes of its steps."""

    result: SolveResult
    trajectory: Trajectory | None
    check: verify.DenseCheck | None
    n_intervals: int
    cpu_s: float
    fallback_reason: str = ""
    switching: shooting.SwitchingResult | None = None
    """The switching-time solve that made ``trajectory`` (None: the transcription made it)."""
    timings: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class _Switched:
    """What a switching-time attempt produced: the plan (None when it failed), the wall time
    [s] and the note saying why it failed."""

    outcome: _Outcome | None
    timings: dict[str, float]
    notes: tuple[str, ...] = ()


@dataclass(frozen=True)
class _Solved:
    """A transcription solve of the optimiser stage: the result and its wall time [s]."""

    result: SolveResult
    timings: dict[str, float]
    notes: tuple[str, ...] = ()


def _switching_plan(setup: _Setup, result: SolveResult, t_start: float) -> _Switched:
    """The exact bang-bang plan from the pattern of the transcription's ``result``
    (:mod:`.pattern`, :mod:`.shooting`, :mod:`.sampling`), densely re-checked; no plan (with a note) when it fails. No further
    pattern is tried once :data:`SWITCHING_BUDGET_SHARE` of the time budget is spent since
    ``t_start`` (perf_counter [s]): the transcription gets the rest."""
    model, problem, options, loaded, bound = setup.model, setup.problem, setup.options, setup.loaded, setup.bound
    if result.trajectory is None or not (result.success or result.timed_out or result.solver_status in PATTERN_SOURCE_STOPS):
        return _Switched(None, {})
    t0, c0 = time.perf_counter(), time.process_time()
    solved = traj = check = None
    coarse = result.trajectory
    allowed = bound.allowed(loaded, coarse.position_m, coarse.velocity_m_s, coarse.acceleration_m_s2)
    # (pattern, duration guess [s], follow-up depth), most likely first
    queue = [(candidate, result.duration_s, 0)
             for candidate in pattern.candidate_patterns(coarse, allowed, pattern.via_times(problem, coarse))]
    deadline = t_start + SWITCHING_BUDGET_SHARE * options.solver.time_budget_s
    while queue:
        if solved is not None and time.perf_counter() > deadline:
            break
        candidate, guess, depth = queue.pop(0)
        solved = shooting.solve_switching(model, problem, bound, candidate, guess, deadline_s=deadline)
        if solved.success:
            break
        if depth < FOLLOW_UP_DEPTH:  # what this attempt ended with says what to try next
            queue[:0] = [(p, solved.duration_s, depth + 1) for p in shooting.follow_ups(solved)]
    if solved is not None and solved.success:
        try:
            traj = sampling.trajectory(model, problem, solved, meta={"solver_status": result.solver_status,
                                                                      "pattern_from_n_intervals": result.n_intervals})
        except InvalidProblemError as exc:  # its output grid could not be sampled
            solved = dataclasses.replace(solved, success=False, reason=f"its motion could not be sampled ({exc})")
        else:
            check = verify.dense_check(loaded, traj, bound, options.checks.dense_factor)
    timings = {"switching": time.perf_counter() - t0}
    why = ("no bang-bang pattern" if solved is None else solved.reason if not solved.success else
           "" if check is not None and check.within(options.checks.command_tolerance) else
           f"its plan failed the dense re-check (|Tc|/bound {check.worst_command_ratio:.4f})")
    if why:
        return _Switched(None, timings, (f"switching-time solve from the N={result.n_intervals} pattern: {why}",))
    # the coarse solve may have ignored the workspace margins: the dense re-check held them
    result = dataclasses.replace(result, workspace=WorkspaceHandling.INACTIVE_DENSE_CHECKED)
    return _Switched(_Outcome(result, traj, check, result.n_intervals,
                              result.solve_cpu_s + time.process_time() - c0, switching=solved), timings)


def _coarse_solve(setup: _Setup) -> _Solved:
    """The coarse transcription the switching-time plan reads its pattern from."""
    options = setup.options
    coarse = pattern.coarse_solve(setup.model, setup.problem, setup.bound, time_budget_s=options.solver.time_budget_s,
                                    hessian=options.solver.hessian, profile=options.transcription.profile)
    return _Solved(coarse, {"optimiser": coarse.solve_time_s})


def _transcription_solve(setup: _Setup, t_start: float) -> _Solved:
    """The transcription at the options' N (warm-started from a solved neighbour when the
    options say so), within what is left of the time budget since ``t_start``."""
    model, problem, options, bound = setup.model, setup.problem, setup.options, setup.bound
    n_intervals = options.intervals_for(problem)
    notes: list[str] = []
    warm = None
    cache_key = (bound, options.transcription.profile)
    if options.solver.warm_start == "neighbours":
        warm = warmstart.NEIGHBOURS.lookup(model, problem, n_intervals, cache_key)
        notes.append(f"warm-started from a solved neighbour {1e3 * warm.distance_m:.1f} mm away"
                     if warm else "no solved neighbour to warm-start from; cold start")
    # the budget covers the whole optimiser stage: what the coarse solve and the
    # switching-time attempt left of it (as for the 2N re-solve below)
    settings = MinTimeSettings.of(options, n_intervals,
                                  time_budget_s=options.solver.time_budget_s - (time.perf_counter() - t_start))
    result = solve_min_time(model, problem, bound, settings, warm.guess if warm else None)
    if options.solver.warm_start == "neighbours" and result.success:
        warmstart.NEIGHBOURS.store(model, problem, n_intervals, cache_key, result.nodes)
    return _Solved(result, {"optimiser": result.solve_time_s}, tuple(notes))


def _optimise(setup: _Setup, t_start: float) -> _Outcome:
    """The optimiser stage, in order: with the switching-time solve (where it applies) the
    coarse transcription and the exact plan from its pattern; otherwise, or when that fails,
    the transcription at N, densely re-checked; a plan over its bound re-solved once at 2N
    (warm-started from the same motion, within the remaining time budget), and one over it by
    a hair with the bound tightened; the switching-time plan from the checked plan's pattern.
    Says why when nothing usable came out (``fallback_reason``)."""
    model, problem, options, loaded, bound = setup.model, setup.problem, setup.options, setup.loaded, setup.bound
    ledger = _Ledger()
    spent_cpu = 0.0
    if setup.switching_applies:
        coarse = ledger.add(_coarse_solve(setup)).result
        spent_cpu = coarse.solve_cpu_s
        done = ledger.add(_switching_plan(setup, coarse, t_start)).outcome
        if done is not None:
            return dataclasses.replace(done, timings=ledger.timings, notes=ledger.notes)
    result = ledger.add(_transcription_solve(setup, t_start)).result
    out = _Outcome(result, result.trajectory if result.success else None, None, options.intervals_for(problem),
                   spent_cpu + result.solve_cpu_s)

    def finished(outcome: _Outcome) -> _Outcome:
        return dataclasses.replace(outcome, timings=ledger.timings, notes=ledger.notes)

    solve_bound = bound
    for attempt in range(3):
        if out.trajectory is None:
            out.fallback_reason = (f"optimiser ran out of its time budget ({options.solver.time_budget_s:g} s)"
                                   if out.result.timed_out else
                                   f"optimiser failed at N={out.n_intervals}: {out.result.solver_status}")
            return finished(out)
        t0 = time.perf_counter()
        out.check = verify.dense_check(loaded, out.trajectory, bound, options.checks.dense_factor)
        ledger.add(_Solved(out.result, {"dense_check": time.perf_counter() - t0}))
        if out.check.within(options.checks.command_tolerance):
            polished = ledger.add(_switching_plan(setup, out.result, t_start)).outcome if setup.switching_applies else None
            return finished(out if polished is None else dataclasses.replace(polished, cpu_s=out.cpu_s + polished.cpu_s))
        left = options.solver.time_budget_s - (time.perf_counter() - t_start)
        ratio = out.check.worst_command_ratio
        finer = attempt == 0 and 2 * out.n_intervals <= MAX_INTERVALS
        if attempt == 2 or left <= 0 or not (finer or ratio <= 1.0 + REPAIR_MAX_EXCESS):
            break
        source = refinement.plan_segments(problem, out.trajectory)
        if finer:
            # between the nodes the command can exceed the limit where the acceleration changes
            # fast (e.g. at via points): halve the intervals, starting from the same motion
            note = (f"N={out.n_intervals} plan exceeded the dense re-check (|Tc|/bound {ratio:.4f}); "
                    f"re-solved with N={2 * out.n_intervals}")
            target = tuple(2 * k for k in source)
        else:
            # what a finer grid did not cure (a friction torque changing sign within ~0.1 ms
            # where a leg reverses) is repaired by imposing a bound tightened by the overshoot
            solve_bound = solve_bound.tightened(ratio)
            note = (f"N={out.n_intervals} plan exceeded the dense re-check (|Tc|/bound {ratio:.4f}); "
                    f"re-solved with the bound tightened by {solve_bound.reserve - bound.reserve:.0f} units")
            target = source
        out.result = solve_min_time(model, problem, solve_bound,
                                    MinTimeSettings.of(options, sum(target), time_budget_s=left, segments=target),
                                    refinement.resampled_guess(out.trajectory, source, target))
        ledger.add(_Solved(out.result, {"optimiser": out.result.solve_time_s}, (note,)))
        out.cpu_s += out.result.solve_cpu_s
        out.n_intervals = sum(target)
        out.trajectory = out.result.trajectory if out.result.success else None
    out.fallback_reason = (f"optimiser's plan failed the dense re-check (|Tc|/bound "
                           f"{out.check.worst_command_ratio:.4f}, margin {out.check.worst_margin:.3g})")
    out.trajectory = None
    return finished(out)


REPAIR_MAX_EXCESS = 0.05
"""A plan that the finer grid left over its bound by at most this fraction on the dense re-check
is re-solved with the bound tightened by its overshoot (:meth:`CommandBound.tightened`) rather
than replaced by the ruckig fallback (a calibrated model with Coulomb friction: 1.1 % over)."""


@dataclass(frozen=True)
class _Candidate:
    """The plan a stage hands on: its trajectory, dense re-check and N, how it was made
    (``method``: "casadi" or "ruckig-fallback"), the ruckig result it is (a fallback), and the
    wall times [s], optimiser time [s] and notes of the stage that made it."""

    trajectory: Trajectory
    check: verify.DenseCheck
    n_intervals: int
    method: str
    timings: dict[str, float]
    solve_time_s: float
    notes: tuple[str, ...] = ()
    reference: fallback.RuckigResult | None = None


def _fallback(setup: _Setup, out: _Outcome, t_start: float) -> _Candidate:
    """The ruckig reference as the plan, re-checked; PlanningFailed when disabled or unusable."""
    loaded, problem, options = setup.loaded, setup.problem, setup.options
    t0 = time.perf_counter()

    def fail(why: str, cause: Exception | None = None) -> PlanningFailed:
        return PlanningFailed(f"planning failed: {why}",
                              _failed_report(problem, options, out.result, why, t_start))

    if not options.solver.fallback:
        raise fail(f"{out.fallback_reason} (fallback disabled)")
    bound = options.command_bound(loaded.params)
    try:
        reference = fallback.ruckig_reference(loaded, problem, bound.at_rest)
    except CrosscheckError as exc:
        raise fail(f"{out.fallback_reason}; the ruckig fallback failed: {exc}") from exc
    check = verify.dense_check(loaded, reference.trajectory, bound, 2)
    if not reference.inside_workspace:
        raise fail(f"{out.fallback_reason}; the ruckig fallback leaves the workspace")
    if not check.within(options.checks.command_tolerance):
        raise fail(f"{out.fallback_reason}; the ruckig fallback reaches |Tc|/bound "
                   f"{check.worst_command_ratio:.4f}")
    # the report says so (method, fallback_reason): a log line only for who asks for them
    log.info("returning the ruckig fallback: %s", out.fallback_reason)
    spent = time.perf_counter() - t0
    return _Candidate(reference.trajectory, check, out.n_intervals, "ruckig-fallback", {"fallback": spent},
                      _optimiser_time(out) + spent, (reference.note,) if reference.note else (), reference)


def _optimised(out: _Outcome) -> _Candidate:
    """The optimiser stage's plan as the candidate (its timings and notes already booked)."""
    assert out.trajectory is not None and out.check is not None
    return _Candidate(out.trajectory, out.check, out.n_intervals, "casadi", {}, _optimiser_time(out))


def _optimiser_time(out: _Outcome) -> float:
    """The optimiser stage's solving time [s]: its transcription solves and switching-time
    attempts."""
    return out.timings["optimiser"] + out.timings.get("switching", 0.0)


COARSE_ESTIMATE_MARGIN = 0.001
"""How much lower than the target (absolute, 0.1 %) the gap estimated from the cheap N/2
partner must be for the N plan to be kept without solving at 2N. Against separate
192-interval solves of the benchmark problems that estimate was 0.19 % too low at worst
(tc_sweep_1500, whose N plan is 0.45 % above the optimum: its estimate, 0.26 %, is above the
target minus this margin, so it gets its 2N plan); the estimate from N and 2N was within
0.03 %."""


@dataclass(frozen=True)
class _Refined:
    """What :func:`_refine` returns: the plan to return (and its dense re-check and N); the
    estimate of the converged duration and the returned plan's gap, with the other grid of
    the sequence (None when no solve of the sequence succeeded); the wall time of the extra
    solves and the process CPU time of the whole step [s]."""

    trajectory: Trajectory
    check: verify.DenseCheck
    n_intervals: int
    estimate: refinement.RefinementCheck | None
    solve_time_s: float
    solve_cpu_s: float
    timings: dict[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()


def _refinement(setup: _Setup, plan: _Candidate, out: _Outcome) -> _Refined:
    """The refinement stage: the switching-time plan's (:func:`_refine_switching`) or the
    transcription's (:func:`_refine`) sequence, timed."""
    t0 = time.perf_counter()
    refined = (_refine_switching(setup.model, setup.problem, out.switching, plan.trajectory, plan.check,
                                 plan.n_intervals)
               if out.switching is not None else
               _refine(setup.model, setup.problem, setup.options, setup.bound, setup.loaded, plan.trajectory,
                       plan.check, plan.n_intervals))
    return dataclasses.replace(refined, timings={"refine": time.perf_counter() - t0})


def _refine(model: FalconModel, problem: PlanProblem, options: PlanOptions, bound: CommandBound,
            loaded: FalconModel, traj: Trajectory, check: verify.DenseCheck, n_intervals: int) -> _Refined:
    """The refinement sequence behind the report's converged duration and gap.

    1. The N/2 partner (warm-started from the plan, about half the cost of the plan's own
       solve): Richardson from N/2 and N. When it puts the plan's gap below
       ``options.checks.optimality_target`` minus :data:`COARSE_ESTIMATE_MARGIN`, the N plan is kept.
    2. Otherwise (or when the partner failed) the 2N solve: Richardson from N and 2N (the
       finer, more accurate estimate); if the plan's gap exceeds the target, the 2N plan is
       returned (after its own dense re-check) with its gap to the same estimate, the N plan
       then being the sequence's other grid.
    """
    t_cpu = time.process_time()
    spent = 0.0
    estimate = None
    notes: list[str] = []
    if n_intervals >= 8:
        estimate = refinement.grid_refinement(model, problem, traj, bound, options.solver.hessian, coarser=True)
        spent += estimate.solve_time_s
        if estimate.gap is None:
            notes.append(f"refinement at N={estimate.n_intervals} did not converge: {estimate.solver_status}")
            estimate = None
    keep = estimate is not None and estimate.gap <= options.checks.optimality_target - COARSE_ESTIMATE_MARGIN
    if not keep and 2 * n_intervals <= MAX_INTERVALS:
        fine = refinement.grid_refinement(model, problem, traj, bound, options.solver.hessian)
        spent += fine.solve_time_s
        if fine.gap is None:
            notes.append(f"refinement at 2N={fine.n_intervals} did not converge: {fine.solver_status}")
        else:
            estimate = fine
            if fine.gap > options.checks.optimality_target and fine.trajectory is not None:
                fine_check = verify.dense_check(loaded, fine.trajectory, bound, options.checks.dense_factor)
                if fine_check.within(options.checks.command_tolerance):
                    notes.append(f"the N={n_intervals} plan was {100 * fine.gap:.3f} % above the converged "
                                 f"duration (target {100 * options.checks.optimality_target:g} %): returned the "
                                 f"N={fine.n_intervals} plan")
                    t_inf, t_fine = fine.converged_duration_s, fine.duration_s
                    estimate = dataclasses.replace(
                        fine, n_intervals=n_intervals, duration_s=traj.duration_s,
                        change=(traj.duration_s - t_fine) / t_fine, gap=(t_fine - t_inf) / t_inf, trajectory=None)
                    return _Refined(fine.trajectory, fine_check, fine.n_intervals, estimate, spent,
                                    time.process_time() - t_cpu, notes=tuple(notes))
    return _Refined(traj, check, n_intervals, estimate, spent, time.process_time() - t_cpu, notes=tuple(notes))


def _refine_switching(model: FalconModel, problem: PlanProblem, solved: shooting.SwitchingResult,
                      traj: Trajectory, check: verify.DenseCheck, n_intervals: int) -> _Refined:
    """The refinement sequence of a switching-time plan: the same solve with twice the RK4
    steps per phase (:func:`.shooting.refinement`), extrapolated at fourth order."""
    t0, c0 = time.perf_counter(), time.process_time()
    t_fine, t_inf = shooting.refinement(model, problem, solved)
    spent = time.perf_counter() - t0
    steps = 2 * sum(solved.counts)
    estimate = refinement.RefinementCheck(steps, t_fine, (t_fine - traj.duration_s) / traj.duration_s,
                                      "switching-time refinement", spent, t_inf,
                                      (traj.duration_s - t_inf) / t_inf)
    return _Refined(traj, check, n_intervals, estimate, spent, time.process_time() - c0)


def plan_problem(problem: PlanProblem, options: PlanOptions | None = None,
                 model: FalconModel | None = None) -> Plan:
    """:func:`plan` for a ready ``problem`` (a :class:`PlanProblem`), with ``options``
    (default ``PlanOptions()``) and ``model`` (default nominal): same behaviour and errors.

    The pipeline, each step a stage returning its result (its wall times and notes booked
    here, in order): validate -> optimise (coarse solve -> switching-time plan, else N -> 2N
    or tightened repair -> switching from the N plan's pattern) -> fallback (only when the
    optimiser gave nothing usable) -> refinement (optional) -> cross-checks and the plant run
    (optional) -> the report."""
    t_start = time.perf_counter()
    ledger = _Ledger()
    setup = ledger.add(_setup(problem, options or PlanOptions(), model or default_model()))
    out = ledger.add(_optimise(setup, t_start))
    chosen = _optimised(out) if out.trajectory is not None else ledger.add(_fallback(setup, out, t_start))
    refined = ledger.add(_refinement(setup, chosen, out)) \
        if setup.options.checks.refine and chosen.method == "casadi" else None
    checks = ledger.add(_checks(setup, chosen, refined))
    return _plan(setup, out, chosen, refined, checks, ledger, t_start)


def _setup(problem: PlanProblem, options: PlanOptions, model: FalconModel) -> _Setup:
    """Validate the request (:func:`require_nonzero_move`, the workspace,
    :func:`require_holdable`; each raises) and prepare what the stages share."""
    from falcon_plan.model.modelfile import planning_effects, unplannable_effect_notes

    notes_effects, planned = model.effects, planning_effects(model.effects)
    if planned is not model.effects:  # a friction sign sharper than the planner takes
        model = model.with_effects(planned)
    model.prepare_small_batches()  # compiled single points (built once; a few us after that)
    require_nonzero_move(problem)
    problem.require_in_workspace(model)
    bound = options.command_bound(model.params)
    require_holdable(model, problem, bound)
    notes: list[str] = []
    saturation = model.params.command_saturation
    if options.limits.limit == "constant" and options.limits.tc_max > saturation:
        # The planner bounds |Tc| by tc_max alone; the device (and the simulated plant) give
        # more than the static saturation only once the legs move (the paper, Section 4).
        notes.append(f"tc_max {options.limits.tc_max:g} exceeds the static saturation {saturation}: "
                     f"from rest the device delivers at most {saturation}, so the first "
                     "milliseconds of this plan may not be tracked exactly")
    notes.extend(unplannable_effect_notes(notes_effects, model.params))
    polish = options.transcription.switching and shooting.not_applicable(problem, bound) is None
    return _Setup(problem, options, model, bound, payload_model(model, problem), polish, tuple(notes))


@dataclass(frozen=True)
class _Checks:
    """The optional checks of a plan: toppra's durations on the plan's path and on the
    straight line, ruckig's [s], the closed-loop plant run (a dict), their wall times [s] and
    notes."""

    same_s: float | None
    straight_s: float | None
    ruckig_s: float | None
    plant: dict[str, Any] | None
    timings: dict[str, float]
    notes: tuple[str, ...]


def _checks(setup: _Setup, plan: _Candidate, refined: _Refined | None) -> _Checks:
    """The cross-checks (toppra on the same path and on the straight line, ruckig) and the
    plant run of the plan to return, as ``setup.options`` ask."""
    options, problem, loaded, bound = setup.options, setup.problem, setup.loaded, setup.bound
    traj = refined.trajectory if refined is not None else plan.trajectory
    notes: list[str] = []
    timings: dict[str, float] = {}
    same_s = straight_s = ruckig_s = None
    if options.checks.crosscheck:
        from falcon_plan.planning import crosscheck  # toppra (and the matplotlib it imports): ~0.3 s, only here

        # the references take a constant limit: the plan's own (tc_max - reserve), or for the
        # device's limit its value at rest (a lower bound of L(w); their durations are then
        # upper bounds of the device-limit optimum)
        ref_limit = bound.at_rest
        if options.limits.limit == "device":
            notes.append(f"toppra and ruckig references use the limit at rest ({ref_limit:g}), not the "
                         "speed-dependent device limit")
        t0 = time.perf_counter()
        if plan.method == "casadi":
            same_s, said = _reference("toppra same path", lambda: crosscheck.toppra_same_path(loaded, traj, ref_limit))
            notes.extend(said)
        straight_s, said = _reference("toppra straight", lambda: crosscheck.toppra_straight(loaded, problem, ref_limit))
        notes.extend(said)
        timings["toppra"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        reference = plan.reference
        if reference is None:
            reference, said = _reference_or_note("ruckig reference",
                                                 lambda: fallback.ruckig_reference(loaded, problem, ref_limit))
            notes.extend(said)
        if reference is not None:
            ruckig_s = reference.duration_s
            if not reference.inside_workspace:
                notes.append("ruckig reference leaves the workspace (duration reported anyway)")
        timings["ruckig"] = time.perf_counter() - t0
    plant = None
    if options.checks.plant_check:
        t0 = time.perf_counter()
        plant = verify.plant_check(loaded, traj).to_dict()
        timings["plant"] = time.perf_counter() - t0
    return _Checks(same_s, straight_s, ruckig_s, plant, timings, tuple(notes))


def _plan(setup: _Setup, out: _Outcome, chosen: _Candidate, refined: _Refined | None, checks: _Checks,
          ledger: _Ledger, t_start: float) -> Plan:
    """The returned plan: the trajectory (refined, when the refinement returned its 2N plan)
    with its metadata, and the report of every stage."""
    options, problem, bound = setup.options, setup.problem, setup.bound
    method = chosen.method
    traj, check, n_returned = chosen.trajectory, chosen.check, chosen.n_intervals
    solve_time, cpu_s = chosen.solve_time_s, out.cpu_s
    refinement = None
    if refined is not None:
        solve_time += refined.solve_time_s
        cpu_s += refined.solve_cpu_s
        traj, check, n_returned, refinement = refined.trajectory, refined.check, refined.n_intervals, refined.estimate
    report = PlanReport(
        status="optimal" if method == "casadi" else "fallback", method=method,
        duration_s=traj.duration_s, solve_time_s=solve_time,
        total_time_s=time.perf_counter() - t_start, solver_status=out.result.solver_status,
        solver_iterations=out.result.iterations, solver_success=out.result.success,
        n_intervals=n_returned, hessian=options.solver.hessian, fallback_reason=out.fallback_reason,
        tc_max=options.limits.tc_max, worst_command_ratio=check.worst_command_ratio,
        worst_command_time_s=check.worst_command_time_s, worst_workspace_margin=check.worst_margin,
        worst_margin_name=check.worst_margin_name, worst_angle_margin_deg=check.worst_angle_margin_deg,
        worst_angle_margin_name=check.worst_angle_margin_name,
        forward_singularity_margin=check.forward_singularity_margin, toppra_same_path_s=checks.same_s,
        toppra_straight_s=checks.straight_s, ruckig_s=checks.ruckig_s,
        refined_duration_s=refinement.duration_s if refinement else None,
        refinement_change=refinement.change if refinement else None,
        refinement_intervals=refinement.n_intervals if refinement else None, plant=checks.plant,
        problem=problem.to_dict(), options=options.to_dict(),
        notes=tuple(ledger.notes), timings_s=ledger.timings, solve_cpu_s=cpu_s,
        workspace_constraints=out.result.workspace if method == "casadi" else WorkspaceHandling.NOT_SOLVED,
        command_bound=bound.describe(),
        converged_duration_s=refinement.converged_duration_s if refinement else None,
        optimality_gap=refinement.gap if refinement else None,
        switching=out.switching.to_dict() if out.switching is not None and method == "casadi" else None)
    traj = Trajectory(traj.t_s, traj.position_m, traj.velocity_m_s, traj.acceleration_m_s2, traj.commands,
                      traj.params_name, traj.source,
                      {**traj.meta, "method": method, "tc_max": options.limits.tc_max, "limit": options.limits.limit,
                       "feedback_reserve": options.limits.feedback_reserve, "duration_s": traj.duration_s},
                      traj.interpolation)
    return Plan(traj, report)


def _reference_or_note(name: str, compute: Any) -> tuple[Any, tuple[str, ...]]:
    """Run a reference computation: (its result, no note), or (None, a note saying why) when
    it fails, never a planning error. Ours raise :class:`CrosscheckError`; toppra itself
    signals an unusable path with ValueError, AssertionError or arithmetic errors, which are
    notes too."""
    try:
        return compute(), ()
    except (FalconPlanError, ValueError, ArithmeticError, AssertionError) as exc:
        return None, (f"{name}: failed ({type(exc).__name__}: {exc})",)


def _reference(name: str, compute: Any) -> tuple[float | None, tuple[str, ...]]:
    """A toppra reference's duration [s] (or None) and the notes it makes (why not, its own)."""
    result, notes = _reference_or_note(name, compute)
    if result is None:
        return None, notes
    return result.duration_s, (f"{name}: {result.note}",) if result.note else ()


def _failed_report(problem: PlanProblem, options: PlanOptions, result: SolveResult, reason: str,
                   t_start: float) -> PlanReport:
    return PlanReport(
        status="failed", method="none", duration_s=None, solve_time_s=result.solve_time_s,
        total_time_s=time.perf_counter() - t_start, solver_status=result.solver_status,
        solver_iterations=result.iterations, solver_success=result.success,
        n_intervals=options.intervals_for(problem), hessian=options.solver.hessian, fallback_reason=reason,
        tc_max=options.limits.tc_max, worst_command_ratio=None, worst_command_time_s=None,
        worst_workspace_margin=None, worst_margin_name="", problem=problem.to_dict(),
        options=options.to_dict())


__all__ = ["plan", "plan_problem", "require_holdable", "require_nonzero_move", "default_model", "warm_up"]
