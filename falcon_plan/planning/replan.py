"""Planning from a moving state: a new goal while a plan runs (issue 24, item 1).

A running plan is cut at a splice time tau [s, from its start]; the new plan starts from the
running plan's state there (position and velocity, :func:`splice_state`) and goes to a new
goal, at rest or moving, under the same command bound.

- **The fast path** (method "warm"): the exact switching-time solve
  (:func:`falcon_plan.planning.shooting.solve_switching`, Newton's method on the switch times
  and T, with Pontryagin's check) from bang-bang patterns guessed without a transcription:
  first from a model of each leg alone (:func:`leg_space_guesses`: the leg that needs longest
  sets T with one switch, the others spend it in three arcs), every guess solved and the
  shortest extremal kept (several pass the check, up to 1 % apart); then from the running
  plan's own pattern from tau on (:func:`shifted_pattern`, the switches it lost before tau
  guessed as short pulses at either end, :func:`padded_patterns`). The shortest extremal
  found is also tried with a leg in four arcs (:func:`four_arc_guesses`, within
  :data:`FOUR_ARC_SHARE` of the time taken): where the legs' coupling makes that shorter, no
  five-switch guess finds it (0.9-1.1 % longer on 3 of 60 bench replans without).
  With ``replan_search="first"`` (:class:`~falcon_plan.planning.problem.SolverSettings`) the
  first guess that makes a plan within the bound is taken instead: no search for the shortest.
- **The pipeline** (method "pipeline") when no guess made a plan: the planner's full pipeline
  (:func:`falcon_plan.planning.api.plan_problem`, whose coarse transcription finds the
  pattern), retried at N = :data:`FALLBACK_INTERVALS` when it fails (:func:`pipeline`).
- **Through the old goal** when that fails too (1 of 1000 bench replans: a reversal at
  1.5 m/s the transcription could not plan at any N): the running plan to its goal, at rest,
  then a plan from there (:func:`replan_from_rest`), joined (:func:`joined`): always a plan.
- **Fitted to the bound** (:func:`fitted`): the plan is sampled at the device's control period
  (:data:`REPLAN_OUTPUT_STEP_S`) and densely re-checked against the bound itself, no
  tolerance; over it (the command between nodes), solved again with the level lowered by the
  excess. Every replan's |Tc| is then within the bound on the dense re-check.

Nothing of the pipeline changes: this module composes it.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidProblemError, PlanningFailed
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning import sampling, shooting, verify
from falcon_plan.planning.api import default_model, plan_problem
from falcon_plan.planning.pipeline import require_holdable, require_nonzero_move
from falcon_plan.model.kinematics import inverse_kinematics
from falcon_plan.planning.bound import CommandBound, leg_motion
from falcon_plan.planning.integration import CommandRule, step_counts
from falcon_plan.planning.pattern import CommandPattern, square_switches
from falcon_plan.planning.problem import MAX_INTERVALS, PlanOptions, PlanProblem
from falcon_plan.planning.report import Plan
from falcon_plan.planning.transcription import payload_model
from falcon_plan.trajectory import Trajectory

MIN_REMAINING_S = 1e-3
"""A splice this close to the running plan's end is refused [s]: plan from its goal instead."""
PAD_S = 1e-3
"""A switch the shifted pattern lost is guessed as a pulse this long at an end [s]."""
MAX_PADDED = 4
"""Padded guesses :func:`padded_patterns` makes by default."""
FOUR_ARC_SHARE = 3.0
"""The four-arc guesses of a replan (:func:`four_arc_guesses`: T minimised over a surplus
switch, each about as long as all the five-switch solves together) stop after this multiple
of the time taken before them: on 60 bench replans 3 optima had a leg in four arcs, 0.9-1.1 %
shorter than the best five-switch extremal, and bench case 750's (0.31 % shorter) was the
second guess, found after 1.4 times that time; a four-arc guess that is not the optimum
collapses a pulse."""
MAX_TAIL_GUESSES = 2
"""Padded guesses from the running plan's pattern a replan tries when the leg-space model's
(:func:`leg_space_guesses`) made no plan."""


@dataclass(frozen=True)
class Replan:
    """A plan from a running plan's state to a new goal.

    Attributes
    ----------
    trajectory : the new motion, from the splice state (its t = 0 is the splice).
    problem : the problem solved (start position and velocity from the running plan).
    splice_s : the splice time in the running plan [s].
    method : "warm" (a guessed pattern solved exactly, no transcription: the module
        docstring's fast path) or "pipeline" (the planner's full pipeline from the moving
        state); "through the old goal" when neither made a plan (the running plan to its goal,
        at rest, then on from there: :func:`joined`); from rest where the running plan ended
        (:func:`replan_from_rest`): "warm from rest" or "from rest".
    duration_s : the new motion's length [s].
    worst_command_ratio : the dense re-check's max |Tc| / bound (<= 1 but for a transcription
        plan :func:`pipeline` could not bring within it).
    solve_time_s : wall time of the replan [s].
    notes : why the warm start did not serve, etc.
    plan : the pipeline's Plan (its report; the trajectory is its plan fitted to the bound,
        :func:`pipeline`) when method is "pipeline", else None.
    pattern : its bang-bang pattern (for the next replan from it), None when unknown.
    """

    trajectory: Trajectory
    problem: PlanProblem
    splice_s: float
    method: str
    duration_s: float
    worst_command_ratio: float
    solve_time_s: float
    notes: tuple[str, ...] = ()
    plan: Plan | None = field(default=None, repr=False)
    pattern: CommandPattern | None = field(default=None, repr=False)
    """The new motion's bang-bang pattern (the next replan's warm start), None when unknown."""

    @classmethod
    def of_report(cls, trajectory: Trajectory, problem: PlanProblem, report: dict[str, Any] | None) -> "Replan":
        """A plan known by its ``trajectory``, its ``problem`` and its report's JSON ``report``
        (e.g. a service's goal) as a Replan (its pattern from the report's switching summary)."""
        report = report or {}
        ratio = report.get("worst_command_ratio")
        return cls(trajectory, problem, 0.0, "plan", trajectory.duration_s, float(ratio) if ratio is not None else math.nan,
                   float(report.get("solve_time_s", 0.0)), pattern=pattern_of_report(report.get("switching")))

    @classmethod
    def of_plan(cls, plan: Plan, method: str = "pipeline", splice_s: float = 0.0,
                notes: tuple[str, ...] = (), solve_time_s: float | None = None) -> "Replan":
        """A pipeline ``plan`` as a Replan (e.g. the first plan of a run that will be replanned)."""
        return cls(plan.trajectory, PlanProblem.from_dict(plan.report.problem), float(splice_s), method,
                   plan.report.duration_s, plan.report.worst_command_ratio,
                   plan.report.solve_time_s if solve_time_s is None else solve_time_s, notes, plan,
                   running_pattern(plan))


def splice_state(trajectory: Trajectory, splice_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,) [m], velocity (3,) [m/s]) of ``trajectory`` at ``splice_s`` [s from its
    start], exactly as its interpolation gives them (what the executor follows)."""
    p, v, _ = trajectory.at_time(np.array([trajectory.t_s[0] + splice_s]))
    return p[0], v[0]


def shifted_pattern(pattern: CommandPattern, splice_s: float) -> CommandPattern:
    """``pattern`` (without via points) from ``splice_s`` [s] on: each leg's sign at the splice
    (flipped once per switch before it) and its later switch times less ``splice_s``."""
    if pattern.via_s:
        raise InvalidProblemError("a pattern with via points cannot be shifted (replan from the last via point)")
    signs, switches = [], []
    for sign, times in zip(pattern.signs, pattern.switches_s):
        passed = sum(1 for t in times if t <= splice_s)
        signs.append(float(sign) * (-1.0) ** passed)
        switches.append(tuple(t - splice_s for t in times if t > splice_s))
    return CommandPattern(tuple(signs), tuple(switches))  # type: ignore[arg-type]


def padded_patterns(pattern: CommandPattern, duration_s: float, needed: int,
                    limit: int = MAX_PADDED) -> list[CommandPattern]:
    """Guesses with ``needed`` free switches from ``pattern`` (a shifted one, which lost the
    switches before the splice) lasting ``duration_s`` [s]: the missing switches as short
    pulses, at the start (the leg's sign reversed, switching back after :data:`PAD_S`) or
    before the end (a switch :data:`PAD_S` before ``duration_s``), on the legs with the fewest
    switches first; at most ``limit`` guesses."""
    missing = needed - pattern.n_switches
    if missing <= 0:
        return [pattern]
    legs = sorted(range(3), key=lambda i: pattern.counts[i])
    places = [(leg, where) for leg in legs for where in ("start", "end")]
    out: list[CommandPattern] = []
    for combo in itertools.combinations(places, missing):
        if len({leg for leg, _ in combo}) < missing:  # one pad per leg
            continue
        signs, switches = list(pattern.signs), [list(t) for t in pattern.switches_s]
        for leg, where in combo:
            if where == "start":
                signs[leg] = -signs[leg]
                switches[leg].insert(0, PAD_S)
            else:
                switches[leg].append(duration_s - PAD_S)
        out.append(CommandPattern(tuple(signs), tuple(tuple(t) for t in switches)))  # type: ignore[arg-type]
        if len(out) >= limit:
            break
    return out


LEG_SCAN = 200
"""First-switch times scanned for a leg that spends its time in three arcs (:func:`leg_space_guesses`)."""
MAX_GUESSES = 4
"""Patterns solved for a moving start before the pipeline plans instead."""


def _one_switch(x0: float, w0: float, xf: float, wf: float, accel: dict[int, float]) -> tuple[float, int, float] | None:
    """The shortest bang-bang motion of a double integrator from angle ``x0`` [rad] and speed
    ``w0`` [rad/s] to ``xf``, ``wf`` with the acceleration ``accel[s]`` [rad/s^2] under the
    command sign s: (T [s], first sign, switch time [s]), None when neither order reaches it."""
    best = None
    for first in (1, -1):
        a1, a2 = accel[first], accel[-first]
        if a1 * a2 >= 0.0:
            continue
        k = 1.0 / (2.0 * a1) - 1.0 / (2.0 * a2)
        peak2 = (xf - x0 + w0 * w0 / (2.0 * a1) - wf * wf / (2.0 * a2)) / k
        if peak2 < 0.0:
            continue
        peak = math.copysign(math.sqrt(peak2), a1)
        t1, t2 = (peak - w0) / a1, (wf - peak) / a2
        if t1 >= -1e-12 and t2 >= -1e-12 and (best is None or t1 + t2 < best[0]):
            best = (t1 + t2, first, max(t1, 0.0))
    return best


def _three_arcs(x0: float, w0: float, xf: float, wf: float, accel: dict[int, float], duration_s: float,
                first: int) -> list[tuple[float, float]]:
    """The two switch times [s] of the motions of the double integrator of :func:`_one_switch`
    in three arcs (signs ``first``, -``first``, ``first``) that reach ``xf``, ``wf`` at exactly
    ``duration_s`` [s]: the first switch scanned (:data:`LEG_SCAN` samples), the second from the
    end speed, the end angle's zero crossings interpolated."""
    a1, a2 = accel[first], accel[-first]
    if a1 == a2:
        return []
    t1 = np.linspace(0.0, duration_s, LEG_SCAN)
    w1 = w0 + a1 * t1
    rest = duration_s - t1
    t2 = (wf - w1 - a1 * rest) / (a2 - a1)
    t3 = rest - t2
    w2 = w1 + a2 * t2
    miss = x0 + w0 * t1 + 0.5 * a1 * t1 ** 2 + w1 * t2 + 0.5 * a2 * t2 ** 2 + w2 * t3 + 0.5 * a1 * t3 ** 2 - xf
    ok = (t2 >= 0.0) & (t3 >= 0.0)
    out = []
    for k in np.nonzero(ok[:-1] & ok[1:] & (miss[:-1] * miss[1:] <= 0.0) & (miss[:-1] != miss[1:]))[0]:
        f = miss[k] / (miss[k] - miss[k + 1])
        s1 = t1[k] + f * (t1[k + 1] - t1[k])
        out.append((float(s1), float(s1 + t2[k] + f * (t2[k + 1] - t2[k]))))
    return out


def _four_arcs(x0: float, w0: float, xf: float, wf: float, accel: dict[int, float], duration_s: float,
               first: int) -> list[tuple[float, float, float]]:
    """The three switch times [s] of the motions of the double integrator of :func:`_one_switch`
    in four arcs (signs ``first``, -``first``, ``first``, -``first``), the first and the last
    as long, that reach ``xf``, ``wf`` at exactly ``duration_s`` [s] (scanned as in
    :func:`_three_arcs`): the shape of a leg that spends its time so where the legs' coupling
    makes that shorter (on 3 of 60 bench replans the optimum, 0.9-1.1 % shorter than with
    three arcs)."""
    a1, a2 = accel[first], accel[-first]
    if a1 == a2:
        return []
    t1 = np.linspace(0.0, duration_s / 2.0, LEG_SCAN)
    w1 = w0 + a1 * t1
    middle = duration_s - 2.0 * t1
    # the middle two arcs (a2 for t2, a1 for middle - t2), then a2 for t1, end at wf
    t2 = (wf - w1 - a1 * middle - a2 * t1) / (a2 - a1)
    t3 = middle - t2
    w2 = w1 + a2 * t2
    w3 = w2 + a1 * t3
    miss = (x0 + w0 * t1 + 0.5 * a1 * t1 ** 2 + w1 * t2 + 0.5 * a2 * t2 ** 2 + w2 * t3 + 0.5 * a1 * t3 ** 2
            + w3 * t1 + 0.5 * a2 * t1 ** 2 - xf)
    ok = (t2 >= 0.0) & (t3 >= 0.0) & (t1 > 0.0)
    out = []
    for k in np.nonzero(ok[:-1] & ok[1:] & (miss[:-1] * miss[1:] <= 0.0) & (miss[:-1] != miss[1:]))[0]:
        f = miss[k] / (miss[k] - miss[k + 1])
        s1 = t1[k] + f * (t1[k + 1] - t1[k])
        s2 = s1 + t2[k] + f * (t2[k + 1] - t2[k])
        out.append((float(s1), float(s2), float(duration_s - s1)))
    return out


def _leg_space(model: FalconModel, problem: PlanProblem, bound: CommandBound
               ) -> tuple[np.ndarray, np.ndarray, list[dict[int, float]]]:
    """The leg-space model of :func:`leg_space_guesses`: the legs' angles (2, 3) [rad] and speeds
    (2, 3) [rad/s] at the start and the goal, and per leg its acceleration [rad/s^2] under
    either command sign (``model`` with the problem's payload, at the level of ``bound``)."""
    loaded = payload_model(model, problem)
    level = CommandRule.of(bound).level
    ends = np.array([problem.start_m, problem.goal_m], float)
    speeds = np.array([problem.start_velocity_m_s, problem.goal_velocity_m_s], float)
    theta = inverse_kinematics(ends, model.params).theta1
    w = leg_motion(loaded, ends, speeds, np.zeros_like(ends))[0]
    signs = np.array(list(itertools.product((1.0, -1.0), repeat=3)))
    p, v = np.repeat(ends, len(signs), axis=0), np.repeat(speeds, len(signs), axis=0)
    sign_of = np.tile(signs, (2, 1))
    rate = leg_motion(loaded, p, v, np.asarray(loaded.forward_dynamics(p, v, sign_of * level)))[1]
    return theta, w, [{s: float(rate[sign_of[:, leg] == s, leg].mean()) for s in (1, -1)} for leg in range(3)]


def leg_space_guesses(model: FalconModel, problem: PlanProblem, bound: CommandBound,
                      limit: int = MAX_GUESSES) -> list[tuple[CommandPattern, float]]:
    """Bang-bang patterns (pattern, T [s]) for ``problem`` (a start at rest or moving, no via
    points) from a model of each leg alone: its angle a double integrator whose acceleration
    under either command sign is the leg's mean over the other legs' signs, at the start and at
    the goal (``model`` with the problem's payload, at the level of ``bound``). The leg that
    needs longest (its shortest motion, one switch) sets T and keeps its one switch; each other
    leg reaches its goal at that T in three arcs (two switches), starting with either sign:
    up to ``limit`` combinations (the generic optimum has these five switches: Newton's method
    on the full dynamics, :func:`~falcon_plan.planning.shooting.solve_switching`, then places
    them, and Pontryagin's check rejects the wrong ones)."""
    theta, w, accel = _leg_space(model, problem, bound)
    alone = [_one_switch(theta[0, leg], w[0, leg], theta[1, leg], w[1, leg], accel[leg]) for leg in range(3)]
    if any(a is None for a in alone):
        return []
    critical = int(np.argmax([a[0] for a in alone]))  # type: ignore[index]
    duration, first, switch = alone[critical]  # type: ignore[misc]
    options: list[list[tuple[float, tuple[float, ...]]]] = []
    for leg in range(3):
        if leg == critical:
            options.append([(float(first), (switch,))])
            continue
        options.append([(float(s), times) for s in (1, -1)
                        for times in _three_arcs(theta[0, leg], w[0, leg], theta[1, leg], w[1, leg], accel[leg],
                                                 duration, s)])
    out = []
    for combo in itertools.product(*options):
        out.append((CommandPattern(tuple(s for s, _ in combo),  # type: ignore[arg-type]
                                   tuple(t for _, t in combo)), float(duration)))  # type: ignore[arg-type]
        if len(out) >= limit:
            break
    return out


def four_arc_guesses(model: FalconModel, problem: PlanProblem, bound: CommandBound, solved: CommandPattern,
                     duration_s: float) -> list[tuple[CommandPattern, float]]:
    """Guesses (pattern, T [s]) with one more switch than ``solved`` (a five-switch plan of
    ``problem`` for ``model`` under ``bound`` lasting ``duration_s`` [s]): each leg with two
    switches in turn spends its time in
    four arcs instead (:func:`_four_arcs`, in the leg-space model of :func:`leg_space_guesses`),
    starting with the leg's own sign, then with the other (bench case 750: a pulse against the
    leg's three-arc sign first, 0.31 % shorter), the other legs' switches kept (the optima of
    four bench replans were the first or second guess). Solved with T
    minimised over the surplus switch."""
    theta, w, accel = _leg_space(model, problem, bound)
    out = []
    for leg, times in enumerate(solved.switches_s):
        if len(times) != 2:
            continue
        for own in (True, False):
            first = int(solved.signs[leg]) * (1 if own else -1)
            for four in _four_arcs(theta[0, leg], w[0, leg], theta[1, leg], w[1, leg], accel[leg], duration_s,
                                   first)[:1]:
                signs, switches = list(solved.signs), list(solved.switches_s)
                signs[leg], switches[leg] = float(first), four
                out.append((CommandPattern(tuple(signs), tuple(switches)), duration_s))  # type: ignore[arg-type]
    return out


def running_pattern(plan: Plan) -> CommandPattern | None:
    """The bang-bang pattern of a pipeline ``plan`` (its report's switching summary), None when
    the switching-time solve did not make it (or it has via points)."""
    return pattern_of_report(plan.report.switching)


def pattern_of_report(sw: dict[str, Any] | None) -> CommandPattern | None:
    """The bang-bang pattern in a plan report's ``switching`` summary ``sw`` (a dict, as in the
    report's JSON), None when there is none (or it has via points)."""
    if not sw or not sw.get("success") or sw.get("via_s"):
        return None
    return CommandPattern(tuple(float(s) for s in sw["signs"]),  # type: ignore[arg-type]
                                    tuple(tuple(float(t) for t in leg) for leg in sw["switches_s"]))


def replan(running: Plan | Replan, splice_s: float, goal_m: Any, goal_velocity_m_s: Any = (0.0, 0.0, 0.0),
           options: PlanOptions | None = None, model: FalconModel | None = None) -> Replan:
    """Plan from the state of the ``running`` plan at ``splice_s`` [s from its start] to
    ``goal_m`` [m] with ``goal_velocity_m_s`` [m/s], under ``options`` (default
    ``PlanOptions.fast()``: the plan and its dense re-check) and ``model`` (default nominal;
    it must be the running plan's). ``running`` may be an earlier :class:`Replan` (a chain of
    splices). Warm-started from the running plan (module docstring); raises as
    :func:`plan_problem` does when no plan can be made."""
    t0 = time.perf_counter()
    options = options or PlanOptions.fast()
    model = model or default_model()
    duration = running.trajectory.duration_s
    if not (math.isfinite(splice_s) and 0.0 <= splice_s <= duration - MIN_REMAINING_S):
        raise InvalidProblemError(f"splice_s must be in [0, {duration - MIN_REMAINING_S:.4f}] s (the running "
                                  f"plan's length less {MIN_REMAINING_S:g} s), got {splice_s!r}")
    p, v = splice_state(running.trajectory, splice_s)
    problem = PlanProblem(tuple(p), tuple(float(x) for x in np.asarray(goal_m, float).reshape(3)), tuple(v),
                          tuple(float(x) for x in np.asarray(goal_velocity_m_s, float).reshape(3)),
                          payload_kg=_payload_kg(running))
    bound = options.command_bound(model.params)
    require_nonzero_move(problem)
    problem.require_in_workspace(model)
    require_holdable(model, problem, bound)
    guesses = [leg_space_guesses(model, problem, bound)]
    pattern = running.pattern if isinstance(running, Replan) else running_pattern(running)
    if pattern is not None:
        tail = duration - splice_s
        guesses.append([(p, tail) for p in padded_patterns(shifted_pattern(pattern, splice_s), tail, square_switches(0),
                                                           MAX_TAIL_GUESSES)])
    try:
        return _warm_or_pipeline(problem, guesses, float(splice_s), ("warm", "pipeline"), options, model, t0,
                                 extra_switch=True)
    except PlanningFailed as exc:
        if np.any(running.trajectory.velocity_m_s[-1]) or running.trajectory.interpolation != "linear":
            raise  # the running plan does not end at rest (or its motion cannot be joined)
        failed = exc
    # the running plan to its goal, at rest, then on from there: always a plan (a slow one)
    old_goal = running.trajectory.position_m[-1]
    on = replan_from_rest(running, old_goal, goal_m, goal_velocity_m_s, duration, options, model)
    traj = joined(running.trajectory, splice_s, on.trajectory, payload_model(model, problem))
    check = verify.dense_check(payload_model(model, problem), traj, bound, options.checks.dense_factor)
    return Replan(traj, problem, float(splice_s), "through the old goal", traj.duration_s, check.worst_command_ratio,
                  time.perf_counter() - t0, (f"no plan from the moving state ({failed}): the running plan to its "
                                             f"goal, then {on.method} from there",), on.plan)


JOIN_S = 2e-5
"""The interval [s] over which a joined trajectory's acceleration turns from the first motion's
last to the second's first (:func:`joined`; a switching-time plan's command ramp): both are at
rest there, and the interval moves the point by ~1e-9 m and its speed by ~1e-4 m/s."""


def joined(first: Trajectory, from_s: float, second: Trajectory, model: FalconModel) -> Trajectory:
    """``first`` from ``from_s`` [s] on (its state there a node: the motion's t = 0), then
    ``second`` (which starts where and as ``first`` ends, at rest) :data:`JOIN_S` after its end;
    the commands at the added node from ``model``'s inverse dynamics."""
    keep = first.t_s > first.t_s[0] + from_s + 1e-9
    p0, v0, a0 = first.at_time(np.array([first.t_s[0] + from_s]))
    c0 = model.inverse_dynamics(p0, v0, a0)
    t1 = np.concatenate([[0.0], first.t_s[keep] - first.t_s[0] - from_s])
    t = np.concatenate([t1, t1[-1] + JOIN_S + second.t_s - second.t_s[0]])
    stack = lambda a, b, head: np.vstack([head, a[keep], b])  # noqa: E731
    return Trajectory(t, stack(first.position_m, second.position_m, p0), stack(first.velocity_m_s, second.velocity_m_s, v0),
                      stack(first.acceleration_m_s2, second.acceleration_m_s2, a0),
                      stack(first.commands, second.commands, c0), second.params_name, second.source,
                      {**second.meta, "joined_at_s": float(t1[-1])}, "linear")


def warm_solve(problem: PlanProblem, guesses: list[list[tuple[CommandPattern, float]]],
               options: PlanOptions, model: FalconModel, extra_switch: bool = False
               ) -> tuple[Trajectory, float, CommandPattern] | str:
    """The exact switching-time solve of ``problem`` for ``model`` under the command bound of
    ``options`` from the ``guesses`` (pattern, T [s]), in groups: every guess of a group is
    solved and, the solves that pass Pontryagin's check being extremals that can differ in T, the
    shortest is fitted to the bound (:func:`fitted`), else the next; the next group only when
    none of a group's made a plan. With ``extra_switch``, the shortest of a group is also tried
    with a leg in four arcs (:func:`four_arc_guesses`) within :data:`FOUR_ARC_SHARE` of the time
    the group took. With ``options.solver.replan_search`` "first", the first guess whose solve
    is fitted makes the plan (no four-arc guesses). Returns (trajectory, its worst |Tc| / bound,
    its pattern), else why the last attempt failed."""
    bound = options.command_bound(model.params)
    why = shooting.not_applicable(problem, bound)
    if why is not None:
        return why
    why = "no pattern to start from"
    solve_bound = lowered(bound, PRE_FIT)
    first = options.solver.replan_search == "first"
    t0 = time.perf_counter()
    for group in guesses:
        solved_ones = []
        for guess, duration_s in group:
            solved = shooting.solve_switching(model, problem, solve_bound, guess, duration_s)
            if not solved.success:
                why = solved.reason
            elif first:
                made = fitted(model, problem, bound, solved, options, solve_bound)
                if not isinstance(made, str):
                    return made
                why = made
            else:
                solved_ones.append(solved)
        if solved_ones and extra_switch:
            best = min(solved_ones, key=lambda s: s.duration_s)
            deadline = time.perf_counter() + FOUR_ARC_SHARE * (time.perf_counter() - t0)
            shortest = best.duration_s
            for guess, duration_s in four_arc_guesses(model, problem, bound, best.pattern, best.duration_s):
                solved = shooting.solve_switching(model, problem, solve_bound, guess, duration_s, deadline_s=deadline,
                                                  beat_s=shortest)
                if solved.success:
                    solved_ones.append(solved)
                    shortest = min(shortest, solved.duration_s)
        for solved in sorted(solved_ones, key=lambda s: s.duration_s):
            made = fitted(model, problem, bound, solved, options, solve_bound)
            if not isinstance(made, str):
                return made
            why = made
    return why


REPLAN_OUTPUT_STEP_S = 1e-3
"""Longest interval of a replan's trajectory [s] (:func:`~falcon_plan.planning.sampling.sample`;
the device's control period): the command between nodes leaves the bound by the square of the
spacing, e.g. 0.144 %, 0.036 % and 0.009 % at 4, 2 and 1 ms on a mid-motion replan, and the fit
to the bound (:func:`fitted`) takes that off the command level, which lengthened that motion
by 3.4 times as much (0.03 % at 1 ms, 0.12 % at 2 ms)."""
PRE_FIT = 3e-4
"""Replans are solved with the command level lowered by this fraction of the bound from the
start (:func:`lowered`): above the excess between 1 ms nodes (1-2.1e-4 on 12 bench replans),
so that the first dense re-check passes (a solve, a sampling and a check fewer), for about
0.03 % of the duration."""
FIT_MARGIN = 5e-5
"""A plan over its bound on the dense re-check is solved again with the command level lowered
by its excess plus this fraction of the bound (the between-node excess stays about the same)."""
MAX_FITS = 2
"""Re-solves with a lowered level before a plan is given up as over its bound."""


def lowered(bound: CommandBound, fraction: float) -> CommandBound:
    """``bound`` with its reserve raised by ``fraction`` of its value at rest (a lower command level)."""
    return dataclasses.replace(bound, reserve=bound.reserve + fraction * bound.at_rest)


def fitted(model: FalconModel, problem: PlanProblem, bound: CommandBound, solved: shooting.SwitchingResult,
           options: PlanOptions, solve_bound: CommandBound | None = None) -> tuple[Trajectory, float, CommandPattern] | str:
    """The switching-time plan ``solved`` (of ``problem`` for ``model``, solved under
    ``solve_bound``, default ``bound``) as a trajectory with nodes :data:`REPLAN_OUTPUT_STEP_S`
    apart, densely re-checked (``options.checks.dense_factor``) against ``bound`` itself: every
    |Tc| within the bound (no tolerance) and the workspace margins >= 0. Over the bound, solved
    again from its own pattern with the reserve raised by the excess (:data:`FIT_MARGIN`,
    :data:`MAX_FITS`): (trajectory, worst |Tc| / bound, pattern), else why not."""
    loaded = payload_model(model, problem)
    solve_bound = solve_bound or bound
    for attempt in range(MAX_FITS + 1):
        try:
            traj = sampling.trajectory(model, problem, solved, step_s=REPLAN_OUTPUT_STEP_S)
        except InvalidProblemError as exc:  # e.g. a pulse that collapsed to a zero-length phase
            return f"its plan could not be sampled ({exc})"
        check = verify.dense_check(loaded, traj, bound, options.checks.dense_factor)
        if check.worst_margin < -1e-6:
            return f"its plan leaves the workspace ({check.worst_margin_name}, {check.worst_margin:.3g})"
        ratio = check.worst_command_ratio
        if ratio <= 1.0:
            return traj, ratio, solved.pattern
        if attempt == MAX_FITS:
            break
        solve_bound = lowered(solve_bound, ratio - 1.0 + FIT_MARGIN)
        solved = shooting.solve_switching(model, problem, solve_bound, solved.pattern, solved.duration_s)
        if not solved.success:
            return f"its re-solve under a lowered command level failed: {solved.reason}"
    return f"its plan stays over the bound on the dense re-check (|Tc|/bound {ratio:.5f})"


MAX_DOUBLINGS = 2
"""Times a transcription plan over its bound on the dense re-check is planned again at twice
its N before the reserve is raised instead. Where a leg rides its workspace limit the excess
falls slowly with N (a mid-motion replan at N = 24, 48, 96: 0.44, 0.43, 0.12 % over), and
raising the reserve by the excess at N = 48 had left that plan 0.54 % longer than the
converged optimum, at N = 96 0.1 %."""
FALLBACK_INTERVALS = (16, 12)
"""N of the pipeline's further attempts, in turn, when it fails from a moving start (at the
default N = 24, and at 20 and 32, IPOPT ran out of iterations on 4 of 150 random mid-motion
replans; at 16 three of them were planned, the fourth at 12)."""


def pipeline(problem: PlanProblem, options: PlanOptions, model: FalconModel) -> tuple[Plan, Trajectory, float, tuple[str, ...]]:
    """The planner's full pipeline for ``problem`` (a moving start) with ``options`` and
    ``model``, its plan fitted to the bound:
    a switching-time plan by :func:`fitted` from its own pattern; a transcription's over the
    bound planned again at twice its N (:data:`MAX_DOUBLINGS` times), then with the reserve
    raised by its excess (:data:`MAX_FITS` times at most). A solve that fails after a plan over
    the bound: the latest such plan not yet tried so, its reserve raised; a failure before any
    plan: retried at each N of :data:`FALLBACK_INTERVALS` in turn. Returns (plan, trajectory,
    worst |Tc| / bound, notes); raises as :func:`plan_problem` when no plan is made."""
    notes: list[str] = []
    bound = options.command_bound(model.params)
    planned = options
    fallbacks = list(FALLBACK_INTERVALS)
    doublings = 0
    over: list[tuple[PlanOptions, float, int]] = []   # (options, |Tc|/bound, N) of each plan over the bound
    raised: set[int] = set()                          # which of them were planned again with a raised reserve

    def reserve_raised(k: int) -> PlanOptions:
        raised.add(k)
        over_options, ratio, n = over[k]
        excess = (ratio - 1.0 + FIT_MARGIN) * bound.at_rest
        notes.append(f"its plan at N={n} was over the bound (|Tc|/bound {ratio:.5f}); "
                     f"planned again with the reserve raised by {excess:.1f}")
        return over_options.replace(feedback_reserve=over_options.limits.feedback_reserve + excess)

    for attempt in range(MAX_FITS + 1 + MAX_DOUBLINGS):
        while True:
            try:
                plan = plan_problem(problem, planned, model)
                break
            except PlanningFailed as exc:
                # after a plan over the bound: the latest such plan not yet tried so, its reserve raised
                left = [k for k in reversed(range(len(over))) if k not in raised]
                if left:
                    notes.append(f"the pipeline failed ({exc})")
                    planned = reserve_raised(left[0])
                    continue
                if not fallbacks:
                    raise
                notes.append(f"the pipeline failed ({exc}); planned again at N={fallbacks[0]}")
                planned = planned.replace(n_intervals=fallbacks.pop(0))
        pattern = running_pattern(plan)
        if pattern is not None:
            solve_bound = lowered(bound, PRE_FIT)
            solved = shooting.solve_switching(model, problem, solve_bound, pattern, plan.report.duration_s)
            made = fitted(model, problem, bound, solved, options, solve_bound) if solved.success else solved.reason
            if not isinstance(made, str):
                return plan, made[0], made[1], tuple(notes)
            notes.append(f"its switching-time plan could not be fitted to the bound: {made}")
        check = verify.dense_check(payload_model(model, problem), plan.trajectory, bound, options.checks.dense_factor)
        ratio = check.worst_command_ratio
        if ratio <= 1.0 or attempt == MAX_FITS + MAX_DOUBLINGS:
            break
        over.append((planned, ratio, plan.report.n_intervals))
        if doublings < MAX_DOUBLINGS and 2 * plan.report.n_intervals <= MAX_INTERVALS:
            doublings += 1
            # an excess between nodes falls to about a quarter on twice the nodes (one where a
            # leg rides its workspace limit, more slowly), and the plan comes nearer the
            # optimum (a bound lowered by the whole excess had cost 0.8 %)
            notes.append(f"its plan was over the bound (|Tc|/bound {ratio:.5f}); planned again at "
                         f"N={2 * plan.report.n_intervals}")
            planned = planned.replace(n_intervals=2 * plan.report.n_intervals)
            continue
        planned = reserve_raised(len(over) - 1)
    return plan, plan.trajectory, ratio, tuple(notes)


def _warm_or_pipeline(problem: PlanProblem, guesses: list[list[tuple[CommandPattern, float]]],
                      splice_s: float, methods: tuple[str, str], options: PlanOptions, model: FalconModel, t0: float,
                      extra_switch: bool = False) -> Replan:
    """:func:`warm_solve` from the groups of ``guesses`` (none: no pattern to start from),
    method ``methods[0]``; else :func:`pipeline`, method ``methods[1]``; ``t0`` the replan's
    start [s, perf_counter]."""
    made = warm_solve(problem, guesses, options, model, extra_switch)
    if not isinstance(made, str):
        traj, ratio, pattern = made
        return Replan(traj, problem, splice_s, methods[0], traj.duration_s, ratio, time.perf_counter() - t0,
                      pattern=pattern)
    plan, traj, ratio, notes = pipeline(problem, options, model)
    notes = (f"warm start from the running plan: {made}; planned by the pipeline", *notes)
    return Replan(traj, problem, splice_s, methods[1], traj.duration_s, ratio, time.perf_counter() - t0, notes, plan,
                  running_pattern(plan))


def replan_from_rest(running: Plan | Replan, position_m: Any, goal_m: Any, goal_velocity_m_s: Any = (0.0, 0.0, 0.0),
                     splice_s: float = math.inf, options: PlanOptions | None = None,
                     model: FalconModel | None = None) -> Replan:
    """Plan from rest at ``position_m`` [m] (where the ``running`` plan ended and holds; the
    splice at ``splice_s`` [s in its time], past its end) to ``goal_m`` [m] with
    ``goal_velocity_m_s`` [m/s]; ``options`` and ``model`` as for :func:`replan`. Warm-started
    from the running plan's whole pattern and length (goals that follow one another, e.g. a
    moving target's, keep the pattern of the last step), then from the leg-space model's
    (:func:`leg_space_guesses`: on 79 steps of 2.5-3 mm round a 20 mm circle the running
    pattern made 58 plans, the two together 75, and the 90th percentile of the replan times
    fell from 35 to 14 ms with ``replan_search="first"``): method "warm from rest"; else the
    pipeline (method "from rest")."""
    t0 = time.perf_counter()
    options = options or PlanOptions.fast()
    model = model or default_model()
    problem = PlanProblem(tuple(float(x) for x in np.asarray(position_m, float).reshape(3)),
                          tuple(float(x) for x in np.asarray(goal_m, float).reshape(3)),
                          goal_velocity_m_s=tuple(float(x) for x in np.asarray(goal_velocity_m_s, float).reshape(3)),
                          payload_kg=_payload_kg(running))
    pattern = running.pattern if isinstance(running, Replan) else running_pattern(running)
    guesses = [] if pattern is None or pattern.via_s else [[(pattern, running.trajectory.duration_s)]]
    guesses.append(leg_space_guesses(model, problem, options.command_bound(model.params)))
    return _warm_or_pipeline(problem, guesses, float(splice_s), ("warm from rest", "from rest"), options, model, t0)


def _payload_kg(running: Plan | Replan) -> float:
    if isinstance(running, Replan):
        return running.problem.payload_kg
    return float(running.report.problem.get("payload_kg", 0.0))


def goal_state(goal: Any) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,) [m], velocity (3,) [m/s]) of a goal given as a point (3,) [m] (at rest)
    or a mapping with ``position_m`` and optionally ``velocity_m_s``."""
    if isinstance(goal, dict):
        return (np.asarray(goal["position_m"], dtype=float).reshape(3),
                np.asarray(goal.get("velocity_m_s", (0.0, 0.0, 0.0)), dtype=float).reshape(3))
    return np.asarray(goal, dtype=float).reshape(3), np.zeros(3)


def moving_planner(options: PlanOptions | None = None, model: FalconModel | None = None):
    """The planner a :class:`~falcon_plan.execution.splice.SpliceCoordinator` calls:
    ``planner(start, goal) -> (trajectory, Replan)`` plans from the running plan's state at the
    splice (:func:`replan`, warm-started from it) to ``goal`` (:func:`goal_state`), or, when
    the running plan has ended and holds its goal, from rest there (:func:`replan_from_rest`,
    warm-started from its pattern too); under
    ``options`` (default ``PlanOptions.fast()``) and ``model`` (default nominal)."""
    options = options or PlanOptions.fast()
    model = model or default_model()

    def plan(start: Any, goal: Any) -> tuple[Trajectory, Replan]:
        running = start.plan
        goal_m, goal_v = goal_state(goal)
        if start.plan_s <= running.trajectory.duration_s - MIN_REMAINING_S:
            made = replan(running, start.plan_s, goal_m, goal_v, options, model)
        else:
            made = replan_from_rest(running, start.position_m, goal_m, goal_v, start.plan_s, options, model)
        return made.trajectory, made

    return plan


__all__ = ["Replan", "replan", "replan_from_rest", "warm_solve", "fitted", "pipeline", "joined", "lowered",
           "leg_space_guesses", "four_arc_guesses", "moving_planner", "goal_state", "pattern_of_report", "splice_state",
           "shifted_pattern", "padded_patterns", "running_pattern", "MIN_REMAINING_S", "PAD_S", "MAX_PADDED",
           "REPLAN_OUTPUT_STEP_S", "PRE_FIT", "FIT_MARGIN", "MAX_FITS", "MAX_DOUBLINGS", "FALLBACK_INTERVALS", "FOUR_ARC_SHARE", "JOIN_S"]
