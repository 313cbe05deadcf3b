"""The minimum-time solve: the transcription (:mod:`.transcription`) solved under a policy for the
workspace margins (:attr:`MinTimeSettings.workspace`).

The margins are half of the NLP's constraints and inactive in every benchmark problem (minimum-time
paths stay away from the boundary), so by default :func:`solve_min_time` first solves without them
("screening", at most :data:`SCREEN_MAX_ITER` iterations) and imposes them only when that solution
leaves the workspace (:func:`workspace_respected`); exact either way (a solution of the relaxed
problem that satisfies them is a solution of the full one), and it halves the median solve time.
A coarse solve that only has to show the command pattern ignores them (``workspace="ignore"``,
:data:`IGNORED_MAX_ITER`); the caller then checks the motion it leads to.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.bound import CommandBound
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.planning.report import WorkspaceHandling
from falcon_plan.planning.transcription import (MAX_ITERATIONS, NODE_MARGIN, MinTimeSettings, NodeMotion,
                                                PointConstraints, SolveResult, command_row_bounds, get_nlp,
                                                initial_guess, model_constraints, nodes_to_trajectory, payload_model,
                                                points_per_interval, segment_counts, solve_transcription)

SCREEN_MAX_ITER = 60
"""Iteration limit of the screening solve without workspace margins (then the full NLP)."""
IGNORED_MAX_ITER = 150
"""Iteration limit of a solve without workspace margins that no solve with them follows
(``workspace="ignore"``, the switching-time plan's coarse solve): the device-limit coarse
solve of via_two_points needed 67 iterations, past the screening limit."""

def workspace_respected(model: FalconModel, nodes: NodeMotion) -> bool:
    """True when ``nodes``, a solution of the screening solve, satisfies what the full NLP
    imposes on ``model``'s workspace: margins >= NODE_MARGIN at the interior nodes, and >= 0
    at the interval midpoints."""
    p, mid = nodes.p, nodes.midpoints()
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(mid))):
        return False
    inner = model.workspace_margins(p[1:-1]) if len(p) > 2 else np.zeros((0, 1))
    return bool(np.all(inner >= NODE_MARGIN) and np.all(model.workspace_margins(mid) >= 0.0))

def solve_min_time(model: FalconModel, problem: PlanProblem, bound: CommandBound, settings: MinTimeSettings,
                   guess: NodeMotion | None = None) -> SolveResult:
    """Solve the minimum-time problem; never raises for solver failure (see ``success``).

    Parameters
    ----------
    model : the dynamics; its effects (plus ``problem.payload_kg``) are the NLP parameter.
    problem : start, goal, end velocities, via points, payload.
    bound : the command bound (constant or the device's limit, minus the feedback reserve).
    settings : the grid, the NLP's choices, the budget and the workspace handling.
    guess : initial guess at the nodes (N intervals); default :func:`initial_guess`, and for a
        moving end, when the solve from it fails, the straight line's without the end speeds
        (IPOPT ran out of iterations from either on some fast moving starts the other solved;
        the first failure is returned when both fail).
    """
    n_intervals, hessian, profile = settings.n_intervals, settings.hessian, settings.profile
    segments = segment_counts(problem, n_intervals) if settings.segments is None else settings.segments
    if sum(segments) != n_intervals or len(segments) != len(problem.via_m) + 1:
        raise InvalidProblemError(f"segments {segments} do not split {n_intervals} intervals at "
                                  f"{len(problem.via_m)} via points")
    via_nodes = list(np.cumsum(segments)[:-1])
    row_lower, row_upper = command_row_bounds(bound)
    eff = payload_model(model, problem).effect_vector

    def constraints(imposed: bool) -> PointConstraints:
        return model_constraints(model, hessian, imposed, bound.kind)

    points = points_per_interval(bound.kind) if settings.command_points is None else int(settings.command_points)
    wall_time_s = settings.wall_time_s
    # Build (and, the first time on a machine, compile) the NLPs before the clock starts:
    # the time budget is for solving, not for a one-off compilation.
    stages = {"screen": ((False, SCREEN_MAX_ITER), (True, MAX_ITERATIONS)), "impose": ((True, MAX_ITERATIONS),),
              "ignore": ((False, IGNORED_MAX_ITER),)}[settings.workspace]
    for imposed, max_iter in stages:
        get_nlp(constraints(imposed), segments, hessian, max_iter, not imposed, profile, points, wall_time_s)
    t_start = time.perf_counter()

    def attempt(start: NodeMotion) -> SolveResult:
        """The solve from ``start`` under the workspace policy (the budget counted from t_start)."""

        def solve(imposed: bool, max_iter: int) -> SolveResult:
            left = dataclasses.replace(settings, segments=segments, command_points=points,
                                       time_budget_s=settings.time_budget_s - (time.perf_counter() - t_start))
            return solve_transcription(constraints(imposed), problem, left, row_lower=row_lower, row_upper=row_upper,
                                       eff=eff, guess=start, max_iter=max_iter, fast_start=not imposed)

        if settings.workspace == "impose":
            return solve(True, MAX_ITERATIONS)
        if settings.workspace == "ignore":
            return dataclasses.replace(solve(False, IGNORED_MAX_ITER), workspace=WorkspaceHandling.IGNORED)
        # The workspace margins are half the NLP's constraints and are inactive in every
        # benchmark problem (minimum-time paths stay away from the boundary): solve without
        # them first; keep that solution if it stays inside (then it is also optimal with
        # them), else solve with them, from the same guess.
        first = solve(False, SCREEN_MAX_ITER)
        if first.success and workspace_respected(model, first.nodes):
            return dataclasses.replace(first, workspace=WorkspaceHandling.INACTIVE_SCREENED)
        if first.timed_out:
            return first
        return _summed(first, solve(True, MAX_ITERATIONS),
                       workspace=WorkspaceHandling.IMPOSED_ACTIVE if first.success
                       else WorkspaceHandling.IMPOSED_AFTER_FAILED_SCREENING)

    def settled(r: SolveResult) -> bool:
        return r.success or r.timed_out

    if guess is not None:
        result = attempt(guess)
    else:
        result = attempt(initial_guess(model, problem, n_intervals, bound.at_rest, via_nodes))
        if not settled(result) and not problem.is_rest_to_rest:
            retry = attempt(initial_guess(model, problem, n_intervals, bound.at_rest, via_nodes, carry_speeds=False))
            result = _summed(result, retry) if settled(retry) else _summed(retry, result)
    sol = result.nodes
    traj = None
    if all(np.all(np.isfinite(x)) for x in (sol.p, sol.v, sol.a)) and sol.duration_s > 0:
        try:
            traj = nodes_to_trajectory(model, problem, sol, source="casadi",
                                       meta={"n_intervals": n_intervals, "segments": list(segments),
                                             "profile": profile, "solver_status": result.solver_status})
        except InvalidProblemError:   # a failed solve's iterate the model cannot evaluate (points out of reach)
            if result.success:
                raise
    return dataclasses.replace(result, trajectory=traj)


def _summed(earlier: SolveResult, later: SolveResult, **changes: Any) -> SolveResult:
    """``later`` (and ``changes``) with ``earlier``'s iterations and solve times added: the cost
    of a solve made in two attempts."""
    return dataclasses.replace(later, iterations=earlier.iterations + later.iterations,
                               solve_time_s=earlier.solve_time_s + later.solve_time_s,
                               solve_cpu_s=earlier.solve_cpu_s + later.solve_cpu_s, **changes)


__all__ = ["IGNORED_MAX_ITER", "SCREEN_MAX_ITER", "solve_min_time", "workspace_respected"]
