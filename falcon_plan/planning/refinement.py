"""The same problem solved on another grid, and the converged duration from the two.

A transcription's duration converges to the continuous optimum as its interval count N grows
(at first order in 1/N with a constant acceleration per interval, second with a linear one).
:func:`grid_refinement` solves the problem again on half or twice the plan's intervals,
warm-started from the plan itself (:func:`resampled_guess`, nested grids), and
:func:`extrapolate` gives the converged duration (N -> infinity) by Richardson extrapolation:
the plan's gap to it is what the report's optimality gap says. The pipeline
(:func:`falcon_plan.planning.api.plan_problem`) runs it as its refinement stage.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.bound import CommandBound
from falcon_plan.planning.min_time import solve_min_time
from falcon_plan.planning.transcription import DEFAULT_HESSIAN, MinTimeSettings, NodeMotion, segment_counts
from falcon_plan.trajectory import Trajectory


CONVERGENCE_ORDER = {"constant": 1, "linear": 2}
"""Order in 1/N at which the durations converge, per acceleration profile: measured over
the benchmark problems (T_N - T_inf halves from N to 2N with a constant acceleration per
interval, and drops about fourfold with a linear one); :func:`extrapolate` relies on it."""


def extrapolate(t_coarse: float, t_fine: float, order: int, ratio: float = 2.0) -> float:
    """Richardson extrapolation to N -> infinity [s] of the durations ``t_coarse`` at N
    intervals and ``t_fine`` at ``ratio`` N (> 1), converging at ``order`` in 1/N:
    T_inf = T_fine + (T_fine - T_coarse) / (ratio^order - 1)."""
    return t_fine + (t_fine - t_coarse) / (ratio ** order - 1)


@dataclass(frozen=True)
class RefinementCheck:
    """Result of :func:`grid_refinement`: the same problem solved on another grid.

    n_intervals : the other grid's N.
    duration_s : its duration [s] (None if that solve failed).
    change : its relative change against the plan, (T_other - T_plan) / T_plan.
    solver_status, solve_time_s : IPOPT's status and the wall time of that solve [s].
    converged_duration_s : the converged duration (N -> infinity) extrapolated from the two
        (:func:`extrapolate`) [s].
    gap : the plan's gap to it, (T_plan - T_inf) / T_inf.
    trajectory : the other grid's plan (None if that solve failed).
    """

    n_intervals: int
    duration_s: float | None
    change: float | None
    solver_status: str
    solve_time_s: float
    converged_duration_s: float | None = None
    gap: float | None = None
    trajectory: Trajectory | None = field(default=None, repr=False, compare=False)


def plan_segments(problem: Any, traj: Trajectory) -> tuple[int, ...]:
    """Interval counts of ``traj``'s segments between the via points of ``problem`` (from its
    ``meta``, as the planner records them; else the planner's default split of its N)."""
    if "segments" in traj.meta:
        return tuple(int(k) for k in traj.meta["segments"])
    return segment_counts(problem, len(traj.t_s) - 1)


def resampled_guess(traj: Trajectory, source: tuple[int, ...], target: tuple[int, ...]) -> NodeMotion:
    """``traj`` (segments of ``source`` intervals each) at the nodes of a grid with ``target``
    intervals per segment (equal within a segment, the segment ends kept), as a planner guess
    (a ``NodeMotion``). Exact when every target count is a multiple of its source count (each
    interval split without changing the acceleration profile); otherwise the motion sampled
    at the new nodes (for the "constant" profile, the acceleration at each new interval's start)."""
    t0 = traj.t_s[0]
    ends = traj.t_s[np.cumsum((0, *source))] - t0
    t = np.append(np.concatenate([np.linspace(ends[j], ends[j + 1], k + 1)[:-1] for j, k in enumerate(target)]),
                  ends[-1])
    pos, vel, acc = traj.at_time(t + t0)
    if traj.interpolation == "constant":
        acc = acc[:-1]
    else:
        acc[-1] = traj.acceleration_m_s2[-1]
    return NodeMotion(traj.duration_s, pos, vel, acc, np.diff(t))


def grid_refinement(model: FalconModel, problem: Any, traj: Trajectory, bound: CommandBound,
                    hessian: str = DEFAULT_HESSIAN, coarser: bool = False) -> RefinementCheck:
    """Solve ``problem`` again on another grid and estimate the converged duration from the
    two (same acceleration profile as ``traj``, the planner's result, warm-started from it;
    the same ``model`` and command ``bound``).

    ``coarser`` False (default): twice the intervals in every segment (nested grids: each
    interval split in two); True: half of them (each segment's count halved, rounded, at
    least 1), the cheap partner of a refinement sequence N/2 -> N. The extrapolation uses the
    ratio of the total interval counts. ``hessian``: IPOPT's Hessian choice, as the plan's.
    """
    source = plan_segments(problem, traj)
    target = tuple(max(1, round(k / 2)) for k in source) if coarser else tuple(2 * k for k in source)
    n, n_other = sum(source), sum(target)
    other = solve_min_time(model, problem, bound,
                           MinTimeSettings(n_other, segments=target, hessian=hessian, profile=traj.interpolation),
                           resampled_guess(traj, source, target))
    if not other.success:
        return RefinementCheck(n_other, None, None, other.solver_status, other.solve_time_s)
    order = CONVERGENCE_ORDER[traj.interpolation]
    if n_other > n:
        t_inf = extrapolate(traj.duration_s, other.duration_s, order, n_other / n)
    else:
        t_inf = extrapolate(other.duration_s, traj.duration_s, order, n / n_other)
    return RefinementCheck(n_other, other.duration_s, (other.duration_s - traj.duration_s) / traj.duration_s,
                           other.solver_status, other.solve_time_s, t_inf,
                           (traj.duration_s - t_inf) / t_inf, other.trajectory)


__all__ = ["CONVERGENCE_ORDER", "RefinementCheck", "extrapolate", "grid_refinement", "plan_segments", "resampled_guess"]
