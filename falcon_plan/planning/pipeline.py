"""What runs when: the planning pipeline, one function (:func:`run`) whose steps are named
calls, each returning its stage result.

1. :func:`validate`: a zero-length move is refused with its own message ("zero_length_move":
   there is nothing to plan); the points inside the workspace (:class:`WorkspaceError` naming
   which and why), and the command bound at rest able to hold the device still against
   gravity at every waypoint (else :class:`InvalidProblemError`, "tc_max_too_small").
2. Where the switching-time solve applies (``options.transcription.switching``, and the
   bound, :func:`.shooting.not_applicable`): :func:`coarse_solve` (:mod:`.pattern`) and
   :func:`switching_plan`, the exact bang-bang plan from its pattern (:mod:`.shooting`,
   :mod:`.sampling`), densely re-checked.
3. Otherwise, or when that fails: :func:`transcription_solve` at the options' N
   (:mod:`.min_time`), :func:`dense_check`; a plan over its bound is re-solved
   (:func:`repair_of`, :func:`resolve`) at 2N (from the same motion), and one over it by a
   hair with the bound tightened; a checked plan is then polished by :func:`switching_plan`
   from its own pattern.
4. :func:`fallback` when the optimiser gave nothing usable and ``options.solver.fallback``:
   the ruckig leg-angle reference (:mod:`.fallback`), itself re-checked (workspace and
   commands); ``method`` says which was returned. Otherwise :class:`PlanningFailed` with the
   report attached. Never returns None.
5. Optional (``options``): :func:`refine` (the switching-time plan's refinement, twice the RK4
   steps; or the transcription's sequence N/2 and, when that is not conclusive, 2N, whose plan
   is returned when the N plan's gap exceeds ``options.checks.optimality_target``);
   :func:`cross_checks` (toppra on the same path and on the straight line, ruckig; the
   closed-loop run on the simulated plant).
6. :func:`report`: the plan and its :class:`~falcon_plan.planning.report.PlanReport`.

Every stage result carries its wall times [s] (``timings``), its notes and the optimiser CPU
time it used [s] (``cpu_s``); :func:`run` alone books them (:class:`Record`), in order. The
public entry is :func:`falcon_plan.planning.api.plan` (and ``plan_problem``).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from falcon_plan.errors import CrosscheckError, FalconPlanError, InvalidProblemError, PlanningFailed
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning import fallback as ruckig_fallback
from falcon_plan.planning import pattern, refinement, sampling, shooting, verify, warmstart
from falcon_plan.planning.bound import CommandBound
from falcon_plan.planning.min_time import solve_min_time
from falcon_plan.planning.problem import MAX_INTERVALS, PlanOptions, PlanProblem
from falcon_plan.planning.report import Plan, PlanReport, WorkspaceHandling
from falcon_plan.planning.transcription import MinTimeSettings, SolveResult, payload_model
from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)

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
MAX_REPAIRS = 2
"""Re-solves of a transcription plan that failed the dense re-check (:func:`repair_of`): at
2N, then with the bound tightened."""
REPAIR_MAX_EXCESS = 0.05
"""A plan that the finer grid left over its bound by at most this fraction on the dense re-check
is re-solved with the bound tightened by its overshoot (:meth:`CommandBound.tightened`) rather
than replaced by the ruckig fallback (a calibrated model with Coulomb friction: 1.1 % over)."""
COARSE_ESTIMATE_MARGIN = 0.001
"""How much lower than the target (absolute, 0.1 %) the gap estimated from the cheap N/2
partner must be for the N plan to be kept without solving at 2N. Against separate
192-interval solves of the benchmark problems that estimate was 0.19 % too low at worst
(tc_sweep_1500, whose N plan is 0.45 % above the optimum: its estimate, 0.26 %, is above the
target minus this margin, so it gets its 2N plan); the estimate from N and 2N was within
0.03 %."""


# --- the stage results ---------------------------------------------------------------------

@dataclass(frozen=True, kw_only=True)
class Stage:
    """What every stage result carries for the report: ``timings``, its wall times [s] by name;
    ``notes``; ``cpu_s``, the optimiser CPU time [s] it used (solves, switching-time attempts,
    refinement)."""

    timings: dict[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    cpu_s: float = 0.0


S = TypeVar("S", bound=Stage)


@dataclass
class Record:
    """The pipeline's book of its stages, kept by :func:`run` alone: ``timings``, wall times [s]
    (summed by name, in the order first seen); ``notes`` (in order); ``cpu_s``, the optimiser
    CPU time [s]."""

    timings: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    cpu_s: float = 0.0

    def add(self, stage: S) -> S:
        """Book ``stage`` and return it."""
        for name, seconds in stage.timings.items():
            self.timings[name] = self.timings.get(name, 0.0) + seconds
        self.notes.extend(stage.notes)
        self.cpu_s += stage.cpu_s
        return stage

    @property
    def solve_time_s(self) -> float:
        """Wall time of the optimiser's runs so far [s]: its transcription solves, switching-time
        attempts and the fallback."""
        return self.timings["optimiser"] + self.timings.get("switching", 0.0) + self.timings.get("fallback", 0.0)


@dataclass(frozen=True)
class Setup(Stage):
    """A validated request: the ``problem``, ``options``, the ``model`` planned with (friction
    sign widened to what the planner takes), the command ``bound``, the model with the
    problem's payload (``loaded``), whether the switching-time solve applies
    (``switching_applies``: the option, and the problem). ``timings``, ``notes``, ``cpu_s``: as every :class:`Stage`."""

    problem: PlanProblem
    options: PlanOptions
    model: FalconModel
    bound: CommandBound
    loaded: FalconModel
    switching_applies: bool


@dataclass(frozen=True)
class Candidate:
    """A plan the pipeline may return: its ``trajectory``, dense re-check (``check``) and N
    (``n_intervals``); how it was made (``method``: "casadi" or "ruckig-fallback"); the
    transcription solve the report's solver fields come from (``result``); the switching-time
    solve that made it (``switching``; None: the transcription did); the ruckig result it is
    (``reference``, a fallback) and why the optimiser's plan was not used
    (``fallback_reason``)."""

    trajectory: Trajectory
    check: verify.DenseCheck
    n_intervals: int
    method: str
    result: SolveResult
    switching: shooting.SwitchingResult | None = None
    reference: ruckig_fallback.RuckigResult | None = None
    fallback_reason: str = ""


@dataclass(frozen=True)
class Solved(Stage):
    """A transcription solve: its ``result``, N (``n_intervals``) and the ``bound`` it was solved
    under (tightened by a repair). ``timings``, ``notes``, ``cpu_s``: as every :class:`Stage`."""

    result: SolveResult
    n_intervals: int
    bound: CommandBound

    @property
    def trajectory(self) -> Trajectory | None:
        """The solve's plan (None when it failed)."""
        return self.result.trajectory if self.result.success else None


@dataclass(frozen=True)
class Checked(Stage):
    """A transcription solve densely re-checked: the solve (``solved``), the ``check`` (None when
    the solve gave no plan), and the ``reason`` its plan cannot be used ("" when it can). ``timings``, ``notes``, ``cpu_s``: as every :class:`Stage`."""

    solved: Solved
    check: verify.DenseCheck | None
    reason: str

    @property
    def plan(self) -> Candidate | None:
        """The checked plan as a candidate (None when it cannot be used)."""
        if self.reason or self.check is None or self.solved.trajectory is None:
            return None
        return Candidate(self.solved.trajectory, self.check, self.solved.n_intervals, "casadi", self.solved.result)


@dataclass(frozen=True)
class Switched(Stage):
    """A switching-time attempt: its ``plan`` (None when it failed; the note says why). ``timings``, ``notes``, ``cpu_s``: as every :class:`Stage`."""

    plan: Candidate | None


@dataclass(frozen=True)
class Repair:
    """How a plan over its bound is re-solved: the ``segments``' interval counts, the ``bound``,
    the time budget left (``budget_s`` [s]) and the ``note`` saying so."""

    segments: tuple[int, ...]
    bound: CommandBound
    budget_s: float
    note: str


@dataclass(frozen=True)
class FellBack(Stage):
    """The ruckig fallback as the ``plan``. ``timings``, ``notes``, ``cpu_s``: as every :class:`Stage`."""

    plan: Candidate


@dataclass(frozen=True)
class Refined(Stage):
    """The refinement: the plan to return (its ``trajectory``, dense re-check ``check`` and
    ``n_intervals``; the 2N plan when the sequence returned it); the ``estimate`` of the
    converged duration and the returned plan's gap, with the other grid of the sequence (None
    when no solve of the sequence succeeded); the wall time of its solves (``solve_time_s``
    [s]). ``timings``, ``notes``, ``cpu_s``: as every :class:`Stage`."""

    trajectory: Trajectory
    check: verify.DenseCheck
    n_intervals: int
    estimate: refinement.RefinementCheck | None
    solve_time_s: float


@dataclass(frozen=True)
class Checks(Stage):
    """The optional checks of a plan: toppra's durations on the plan's path (``same_s``) and
    on the straight line (``straight_s``), ruckig's (``ruckig_s``) [s], the closed-loop
    ``plant`` run (a dict). ``timings``, ``notes``, ``cpu_s``: as every :class:`Stage`."""

    same_s: float | None
    straight_s: float | None
    ruckig_s: float | None
    plant: dict[str, Any] | None


# --- the pipeline --------------------------------------------------------------------------

def run(problem: PlanProblem, options: PlanOptions, model: FalconModel) -> Plan:
    """Plan ``problem`` with ``options`` for ``model``: the pipeline (module docstring), each
    step a named call returning its stage result, booked here in order. Raises as
    :func:`falcon_plan.planning.api.plan`."""
    t_start = time.perf_counter()
    record = Record()
    setup = record.add(validate(problem, options, model))
    chosen = None
    if setup.switching_applies:                      # the exact bang-bang plan from a coarse pattern
        coarse = record.add(coarse_solve(setup))
        chosen = record.add(switching_plan(setup, coarse, t_start)).plan
    if chosen is None:                               # the transcription at N; 2N or tightened when over
        solved = record.add(transcription_solve(setup, t_start))
        checked = record.add(dense_check(setup, solved))
        for first in (True, False)[:MAX_REPAIRS]:
            repair = repair_of(setup, checked, first, t_start)
            if repair is None:
                break
            solved = record.add(resolve(setup, solved, repair))
            checked = record.add(dense_check(setup, solved))
        polished = record.add(switching_plan(setup, solved, t_start)).plan \
            if checked.plan is not None and setup.switching_applies else None
        chosen = polished or checked.plan or record.add(fallback(setup, checked, t_start)).plan
    refined = record.add(refine(setup, chosen)) \
        if options.checks.refine and chosen.method == "casadi" else None
    checks = record.add(cross_checks(setup, chosen, refined))
    return report(setup, record, chosen, refined, checks, t_start)


# --- the stages ----------------------------------------------------------------------------

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


def validate(problem: PlanProblem, options: PlanOptions, model: FalconModel) -> Setup:
    """Validate the request for ``problem`` with ``options`` and ``model``
    (:func:`require_nonzero_move`, the workspace, :func:`require_holdable`; each raises) and
    prepare what the stages share."""
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
    return Setup(problem, options, model, bound, payload_model(model, problem), polish, notes=tuple(notes))


def coarse_solve(setup: Setup) -> Solved:
    """The coarse transcription of ``setup``'s problem the switching-time plan reads its
    pattern from (:func:`.pattern.coarse_solve`)."""
    options = setup.options
    coarse = pattern.coarse_solve(setup.model, setup.problem, setup.bound, time_budget_s=options.solver.time_budget_s,
                                  hessian=options.solver.hessian, profile=options.transcription.profile)
    return Solved(coarse, coarse.n_intervals, setup.bound, timings={"optimiser": coarse.solve_time_s},
                  cpu_s=coarse.solve_cpu_s)


def switching_plan(setup: Setup, source: Solved, t_start: float) -> Switched:
    """The exact bang-bang plan of ``setup``'s problem from the pattern of the transcription ``source``
    (:mod:`.pattern`, :mod:`.shooting`, :mod:`.sampling`), densely re-checked; no plan (with a
    note) when it fails. No further pattern is tried once :data:`SWITCHING_BUDGET_SHARE` of the
    time budget is spent since ``t_start`` (perf_counter [s]): the transcription gets the rest."""
    model, problem, options, loaded, bound = setup.model, setup.problem, setup.options, setup.loaded, setup.bound
    result = source.result
    if result.trajectory is None or not (result.success or result.timed_out or result.solver_status in PATTERN_SOURCE_STOPS):
        return Switched(None)
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
    spent = {"switching": time.perf_counter() - t0}
    cpu_s = time.process_time() - c0
    why = ("no bang-bang pattern" if solved is None else solved.reason if not solved.success else
           "" if check is not None and check.within(options.checks.command_tolerance) else
           f"its plan failed the dense re-check (|Tc|/bound {check.worst_command_ratio:.4f})")
    if why:
        return Switched(None, timings=spent, cpu_s=cpu_s,
                        notes=(f"switching-time solve from the N={result.n_intervals} pattern: {why}",))
    assert traj is not None and check is not None
    # the coarse solve may have ignored the workspace margins: the dense re-check held them
    result = dataclasses.replace(result, workspace=WorkspaceHandling.INACTIVE_DENSE_CHECKED)
    return Switched(Candidate(traj, check, result.n_intervals, "casadi", result, switching=solved),
                    timings=spent, cpu_s=cpu_s)


def transcription_solve(setup: Setup, t_start: float) -> Solved:
    """The transcription of ``setup``'s problem at the options' N (warm-started from a solved
    neighbour when the options say so), within what is left of the time budget since
    ``t_start`` (perf_counter [s])."""
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
    # switching-time attempt left of it (as for a re-solve, :func:`repair_of`)
    settings = MinTimeSettings.of(options, n_intervals,
                                  time_budget_s=options.solver.time_budget_s - (time.perf_counter() - t_start))
    result = solve_min_time(model, problem, bound, settings, warm.guess if warm else None)
    if options.solver.warm_start == "neighbours" and result.success:
        warmstart.NEIGHBOURS.store(model, problem, n_intervals, cache_key, result.nodes)
    return Solved(result, n_intervals, bound, timings={"optimiser": result.solve_time_s}, notes=tuple(notes),
                  cpu_s=result.solve_cpu_s)


def dense_check(setup: Setup, solved: Solved) -> Checked:
    """``solved``'s plan densely re-checked against ``setup``'s bound and command tolerance
    (and the workspace); the reason it cannot be used when the solve failed or the check did."""
    options = setup.options
    if solved.trajectory is None:
        reason = (f"optimiser ran out of its time budget ({options.solver.time_budget_s:g} s)"
                  if solved.result.timed_out else
                  f"optimiser failed at N={solved.n_intervals}: {solved.result.solver_status}")
        return Checked(solved, None, reason)
    t0 = time.perf_counter()
    check = verify.dense_check(setup.loaded, solved.trajectory, setup.bound, options.checks.dense_factor)
    reason = "" if check.within(options.checks.command_tolerance) else \
        (f"optimiser's plan failed the dense re-check (|Tc|/bound {check.worst_command_ratio:.4f}, "
         f"margin {check.worst_margin:.3g})")
    return Checked(solved, check, reason, timings={"dense_check": time.perf_counter() - t0})


def repair_of(setup: Setup, checked: Checked, first: bool, t_start: float) -> Repair | None:
    """How to re-solve a plan of ``setup``'s problem that failed the dense re-check
    (``checked``; None when it passed,
    has no plan, or cannot be repaired within what is left of the time budget since
    ``t_start``): on the ``first`` repair at 2N (between the nodes the command can exceed the
    limit where the acceleration changes fast, e.g. at via points), else (or when 2N would pass
    :data:`~falcon_plan.planning.problem.MAX_INTERVALS`) with the bound tightened by the
    overshoot when that is at most :data:`REPAIR_MAX_EXCESS` (a friction torque changing sign
    within ~0.1 ms where a leg reverses, which a finer grid does not cure)."""
    options, solved, check = setup.options, checked.solved, checked.check
    if not checked.reason or check is None or solved.trajectory is None:
        return None
    left = options.solver.time_budget_s - (time.perf_counter() - t_start)
    ratio = check.worst_command_ratio
    finer = first and 2 * solved.n_intervals <= MAX_INTERVALS
    if left <= 0 or not (finer or ratio <= 1.0 + REPAIR_MAX_EXCESS):
        return None
    source = refinement.plan_segments(setup.problem, solved.trajectory)
    said = f"N={solved.n_intervals} plan exceeded the dense re-check (|Tc|/bound {ratio:.4f}); "
    if finer:
        return Repair(tuple(2 * k for k in source), solved.bound, left, said + f"re-solved with N={2 * solved.n_intervals}")
    tightened = solved.bound.tightened(ratio)
    return Repair(source, tightened, left, said + f"re-solved with the bound tightened by "
                                                  f"{tightened.reserve - setup.bound.reserve:.0f} units")


def resolve(setup: Setup, solved: Solved, repair: Repair) -> Solved:
    """``setup``'s problem solved again as ``repair`` says, starting from the motion of
    ``solved``."""
    assert solved.trajectory is not None
    source = refinement.plan_segments(setup.problem, solved.trajectory)
    n_intervals = sum(repair.segments)
    result = solve_min_time(setup.model, setup.problem, repair.bound,
                            MinTimeSettings.of(setup.options, n_intervals, time_budget_s=repair.budget_s,
                                               segments=repair.segments),
                            refinement.resampled_guess(solved.trajectory, source, repair.segments))
    return Solved(result, n_intervals, repair.bound, timings={"optimiser": result.solve_time_s}, notes=(repair.note,),
                  cpu_s=result.solve_cpu_s)


def fallback(setup: Setup, checked: Checked, t_start: float) -> FellBack:
    """The ruckig reference of ``setup``'s problem as the plan, re-checked, when the optimiser's
    last plan (``checked``) cannot be used; PlanningFailed (its report's total time counted
    from ``t_start``, perf_counter [s]) when disabled or unusable."""
    loaded, problem, options = setup.loaded, setup.problem, setup.options
    why, last = checked.reason, checked.solved
    t0 = time.perf_counter()

    def fail(said: str) -> PlanningFailed:
        speeds = [float(np.linalg.norm(v)) for v in (problem.start_velocity_m_s, problem.goal_velocity_m_s)]
        if max(speeds) > 0.0:   # what the user can change: an end speed the device may not reach or leave
            said += (f" (the motion starts at {speeds[0]:g} m/s and ends at {speeds[1]:g} m/s: an end speed may be "
                     "more than the device can reach, or brake from, within the workspace and its command limit)")
        return PlanningFailed(f"planning failed: {said}", _failed_report(problem, options, last.result, said, t_start))

    if not options.solver.fallback:
        raise fail(f"{why} (fallback disabled)")
    bound = options.command_bound(loaded.params)
    try:
        reference = ruckig_fallback.ruckig_reference(loaded, problem, bound.at_rest)
    except CrosscheckError as exc:
        raise fail(f"{why}; the ruckig fallback failed: {exc}") from exc
    check = verify.dense_check(loaded, reference.trajectory, bound, 2)
    if not reference.inside_workspace:
        raise fail(f"{why}; the ruckig fallback leaves the workspace")
    if not check.within(options.checks.command_tolerance):
        raise fail(f"{why}; the ruckig fallback reaches |Tc|/bound {check.worst_command_ratio:.4f}")
    # the report says so (method, fallback_reason): a log line only for who asks for them
    log.info("returning the ruckig fallback: %s", why)
    plan = Candidate(reference.trajectory, check, last.n_intervals, "ruckig-fallback", last.result,
                     reference=reference, fallback_reason=why)
    return FellBack(plan, timings={"fallback": time.perf_counter() - t0},
                    notes=(reference.note,) if reference.note else ())


def refine(setup: Setup, plan: Candidate) -> Refined:
    """The refinement stage of ``plan`` (of ``setup``'s problem): the switching-time plan's (:func:`refine_switching`)
    or the transcription's (:func:`refine_transcription`) sequence, timed."""
    t0 = time.perf_counter()
    refined = refine_switching(setup, plan) if plan.switching is not None else refine_transcription(setup, plan)
    return dataclasses.replace(refined, timings={"refine": time.perf_counter() - t0})


def refine_transcription(setup: Setup, plan: Candidate) -> Refined:
    """The refinement sequence of ``plan`` (of ``setup``'s problem) behind the report's
    converged duration and gap.

    1. The N/2 partner (warm-started from the plan, about half the cost of the plan's own
       solve): Richardson from N/2 and N. When it puts the plan's gap below
       ``options.checks.optimality_target`` minus :data:`COARSE_ESTIMATE_MARGIN`, the N plan is kept.
    2. Otherwise (or when the partner failed) the 2N solve: Richardson from N and 2N (the
       finer, more accurate estimate); if the plan's gap exceeds the target, the 2N plan is
       returned (after its own dense re-check) with its gap to the same estimate, the N plan
       then being the sequence's other grid.
    """
    model, problem, options, bound, loaded = setup.model, setup.problem, setup.options, setup.bound, setup.loaded
    traj, check, n_intervals = plan.trajectory, plan.check, plan.n_intervals
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
                    return Refined(fine.trajectory, fine_check, fine.n_intervals, estimate, spent,
                                   cpu_s=time.process_time() - t_cpu, notes=tuple(notes))
    return Refined(traj, check, n_intervals, estimate, spent, cpu_s=time.process_time() - t_cpu, notes=tuple(notes))


def refine_switching(setup: Setup, plan: Candidate) -> Refined:
    """The refinement sequence of a switching-time ``plan`` (of ``setup``'s problem): the same solve with twice the RK4
    steps per phase (:func:`.shooting.refinement`), extrapolated at fourth order."""
    solved, traj = plan.switching, plan.trajectory
    assert solved is not None
    t0, c0 = time.perf_counter(), time.process_time()
    t_fine, t_inf = shooting.refinement(setup.model, setup.problem, solved)
    spent = time.perf_counter() - t0
    steps = 2 * sum(solved.counts)
    estimate = refinement.RefinementCheck(steps, t_fine, (t_fine - traj.duration_s) / traj.duration_s,
                                          "switching-time refinement", spent, t_inf,
                                          (traj.duration_s - t_inf) / t_inf)
    return Refined(traj, plan.check, plan.n_intervals, estimate, spent, cpu_s=time.process_time() - c0)


def cross_checks(setup: Setup, plan: Candidate, refined: Refined | None) -> Checks:
    """The cross-checks (toppra on the same path and on the straight line, ruckig) and the
    plant run of the plan to return (``refined``'s when there is one, else ``plan``), as
    ``setup.options`` ask."""
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
            reference, said = _reference_or_note(
                "ruckig reference", lambda: ruckig_fallback.ruckig_reference(loaded, problem, ref_limit))
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
    return Checks(same_s, straight_s, ruckig_s, plant, timings=timings, notes=tuple(notes))


def report(setup: Setup, record: Record, plan: Candidate, refined: Refined | None, checks: Checks,
           t_start: float) -> Plan:
    """The returned plan of ``setup``'s problem: the trajectory (``refined``'s when the refinement returned its 2N
    plan, else ``plan``'s) with its metadata, and the report of every stage booked in
    ``record`` since ``t_start`` (perf_counter [s]), with ``checks``."""
    options, problem, bound = setup.options, setup.problem, setup.bound
    method, result = plan.method, plan.result
    traj, check, n_returned = plan.trajectory, plan.check, plan.n_intervals
    solve_time = record.solve_time_s
    estimate = None
    if refined is not None:
        solve_time += refined.solve_time_s
        traj, check, n_returned, estimate = refined.trajectory, refined.check, refined.n_intervals, refined.estimate
    report = PlanReport(
        status="optimal" if method == "casadi" else "fallback", method=method,
        duration_s=traj.duration_s, solve_time_s=solve_time,
        total_time_s=time.perf_counter() - t_start, solver_status=result.solver_status,
        solver_iterations=result.iterations, solver_success=result.success,
        n_intervals=n_returned, hessian=options.solver.hessian, fallback_reason=plan.fallback_reason,
        tc_max=options.limits.tc_max, worst_command_ratio=check.worst_command_ratio,
        worst_command_time_s=check.worst_command_time_s, worst_workspace_margin=check.worst_margin,
        worst_margin_name=check.worst_margin_name, worst_angle_margin_deg=check.worst_angle_margin_deg,
        worst_angle_margin_name=check.worst_angle_margin_name,
        forward_singularity_margin=check.forward_singularity_margin, toppra_same_path_s=checks.same_s,
        toppra_straight_s=checks.straight_s, ruckig_s=checks.ruckig_s,
        refined_duration_s=estimate.duration_s if estimate else None,
        refinement_change=estimate.change if estimate else None,
        refinement_intervals=estimate.n_intervals if estimate else None, plant=checks.plant,
        problem=problem.to_dict(), options=options.to_dict(),
        notes=tuple(record.notes), timings_s=record.timings, solve_cpu_s=record.cpu_s,
        workspace_constraints=result.workspace if method == "casadi" else WorkspaceHandling.NOT_SOLVED,
        command_bound=bound.describe(),
        converged_duration_s=estimate.converged_duration_s if estimate else None,
        optimality_gap=estimate.gap if estimate else None,
        switching=plan.switching.to_dict() if plan.switching is not None and method == "casadi" else None)
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


__all__ = ["run", "validate", "coarse_solve", "switching_plan", "transcription_solve", "dense_check", "repair_of",
           "resolve", "fallback", "refine", "cross_checks", "report", "require_holdable", "require_nonzero_move",
           "Stage", "Record", "Setup", "Candidate", "Solved", "Checked", "Switched", "Repair", "FellBack",
           "Refined", "Checks"]
