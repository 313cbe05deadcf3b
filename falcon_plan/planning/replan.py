"""Planning from a moving state: a new goal while a plan runs (issue 24, item 1).

A running plan is cut at a splice time tau [s, from its start]; the new plan starts from the
running plan's state there (position and velocity, :func:`splice_state`) and goes to a new
goal, at rest or moving, under the same command bound. The first attempt is warm-started from
the running plan itself: its bang-bang pattern from tau on (each leg's command sign at tau and
its later switches, shifted by -tau: :func:`shifted_pattern`; the switches it lost before tau
guessed as short pulses at either end, :func:`padded_patterns`) and its remaining duration
T - tau are the guess of the exact switching-time solve (:func:`falcon_plan.planning.shooting.solve_switching`,
which also checks Pontryagin's condition), its plan then densely re-checked. A new goal near
the old one keeps the pattern and Newton converges in a few steps; a goal that needs another
pattern (a reversal) fails that solve, and the planner's full pipeline
(:func:`falcon_plan.planning.api.plan_problem`, whose coarse transcription finds the pattern)
plans from the moving state instead. Nothing of the pipeline changes: this module only
composes it.
"""
from __future__ import annotations

import itertools
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning import sampling, shooting, verify
from falcon_plan.planning.api import default_model, plan_problem
from falcon_plan.planning.pattern import CommandPattern, square_switches
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.report import Plan
from falcon_plan.planning.transcription import payload_model
from falcon_plan.trajectory import Trajectory

MIN_REMAINING_S = 1e-3
"""A splice this close to the running plan's end is refused [s]: plan from its goal instead."""
PAD_S = 1e-3
"""A switch the shifted pattern lost is guessed as a pulse this long at an end [s]."""
MAX_PADDED = 4
"""Padded guesses tried before the pipeline plans instead."""


@dataclass(frozen=True)
class Replan:
    """A plan from a running plan's state to a new goal.

    Attributes
    ----------
    trajectory : the new motion, from the splice state (its t = 0 is the splice).
    problem : the problem solved (start position and velocity from the running plan).
    splice_s : the splice time in the running plan [s].
    method : "warm" (the running plan's pattern, solved exactly and densely re-checked) or
        "pipeline" (the planner's full pipeline from the moving state); from rest where the
        running plan ended (:func:`replan_from_rest`): "warm from rest" or "from rest".
    duration_s : the new motion's length [s].
    worst_command_ratio : the dense re-check's max |Tc| / bound.
    solve_time_s : wall time of the replan [s].
    notes : why the warm start did not serve, etc.
    plan : the pipeline's Plan (its report) when method is "pipeline", else None.
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
    pattern = running.pattern if isinstance(running, Replan) else running_pattern(running)
    guesses = (None if pattern is None else
               padded_patterns(shifted_pattern(pattern, splice_s), duration - splice_s, square_switches(0)))
    return _warm_or_pipeline(problem, guesses, duration - splice_s, float(splice_s), ("warm", "pipeline"), options, model, t0,
                             "the running plan has no bang-bang pattern")


def warm_solve(problem: PlanProblem, guesses: list[CommandPattern], duration_s: float,
               options: PlanOptions, model: FalconModel) -> tuple[Trajectory, float, CommandPattern] | str:
    """The exact switching-time solve of ``problem`` for ``model`` under the command bound of
    ``options``, from each of the patterns ``guesses`` lasting ``duration_s`` [s] in turn, its
    plan densely re-checked: (trajectory, its worst |Tc| / bound, its pattern) of the first
    that passes, else why the last failed."""
    bound = options.command_bound(model.params)
    why = shooting.not_applicable(problem, bound)
    if why is not None:
        return why
    why = "no pattern to start from"
    for guess in guesses:
        solved = shooting.solve_switching(model, problem, bound, guess, duration_s)
        if not solved.success:
            why = solved.reason
            continue
        try:
            traj = sampling.trajectory(model, problem, solved)
        except InvalidProblemError as exc:  # e.g. a pad that collapsed to a zero-length phase
            why = f"its plan could not be sampled ({exc})"
            continue
        check = verify.dense_check(payload_model(model, problem), traj, bound, options.checks.dense_factor)
        if check.within(options.checks.command_tolerance):
            return traj, check.worst_command_ratio, solved.pattern
        why = f"its plan failed the dense re-check (|Tc|/bound {check.worst_command_ratio:.4f})"
    return why


def _warm_or_pipeline(problem: PlanProblem, guesses: list[CommandPattern] | None, duration_s: float,
                      splice_s: float, methods: tuple[str, str], options: PlanOptions, model: FalconModel, t0: float,
                      no_pattern: str) -> Replan:
    """:func:`warm_solve` from ``guesses`` (None: the running plan had no pattern, ``no_pattern``
    says why), method ``methods[0]``; else the pipeline, method ``methods[1]``; ``t0`` the replan's
    start [s, perf_counter]."""
    made = no_pattern if guesses is None else warm_solve(problem, guesses, duration_s, options, model)
    if not isinstance(made, str):
        traj, ratio, pattern = made
        return Replan(traj, problem, splice_s, methods[0], traj.duration_s, ratio, time.perf_counter() - t0,
                      pattern=pattern)
    notes = (f"warm start from the running plan: {made}; planned by the pipeline",)
    plan = plan_problem(problem, options, model)
    return Replan(plan.trajectory, problem, splice_s, methods[1], plan.report.duration_s,
                  plan.report.worst_command_ratio, time.perf_counter() - t0, notes, plan, running_pattern(plan))


def replan_from_rest(running: Plan | Replan, position_m: Any, goal_m: Any, goal_velocity_m_s: Any = (0.0, 0.0, 0.0),
                     splice_s: float = math.inf, options: PlanOptions | None = None,
                     model: FalconModel | None = None) -> Replan:
    """Plan from rest at ``position_m`` [m] (where the ``running`` plan ended and holds; the
    splice at ``splice_s`` [s in its time], past its end) to ``goal_m`` [m] with
    ``goal_velocity_m_s`` [m/s]; ``options`` and ``model`` as for :func:`replan`. Warm-started
    from the running plan's whole pattern and length (goals that follow one another, e.g. a
    moving target's, keep the pattern of the last step: method "warm from rest"), else the
    pipeline (method "from rest")."""
    t0 = time.perf_counter()
    options = options or PlanOptions.fast()
    model = model or default_model()
    problem = PlanProblem(tuple(float(x) for x in np.asarray(position_m, float).reshape(3)),
                          tuple(float(x) for x in np.asarray(goal_m, float).reshape(3)),
                          goal_velocity_m_s=tuple(float(x) for x in np.asarray(goal_velocity_m_s, float).reshape(3)),
                          payload_kg=_payload_kg(running))
    pattern = running.pattern if isinstance(running, Replan) else running_pattern(running)
    guesses = None if pattern is None or pattern.via_s else [pattern]
    return _warm_or_pipeline(problem, guesses, running.trajectory.duration_s, float(splice_s), ("warm from rest", "from rest"), options,
                             model, t0, "the running plan has no bang-bang pattern")


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


__all__ = ["Replan", "replan", "replan_from_rest", "warm_solve", "moving_planner", "goal_state", "pattern_of_report", "splice_state", "shifted_pattern", "padded_patterns", "running_pattern",
           "MIN_REMAINING_S", "PAD_S", "MAX_PADDED"]
