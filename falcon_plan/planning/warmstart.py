"""Warm starts for repeated queries: a cache of solved neighbours.

With ``PlanOptions.of(warm_start="neighbours")`` the planner looks for the solved problem
nearest to the new one (same model, command bound and acceleration profile, interval count,
payload and number of via points; distance = |start - start'| + |goal - goal'| below :data:`DEFAULT_RADIUS_M`) and
starts IPOPT from that solution, shifted so that it joins the new start and goal: node k of
N moves by (1 - k/N) (start - start') + (k/N) (goal - goal'), the duration is kept, and the
end velocities are set to the new problem's. Only the starting point changes; the solver and
its convergence test are the same, so the plan is the same optimum to the solver's tolerance
(a test checks the durations agree to 0.1 %), only found in fewer iterations.

It is off by default (``warm_start="none"``) so that a plan never depends on the history of
queries unless the caller asks for it; the service and batch users who send streams of nearby
goals switch it on. The cache is per process, bounded (least recently stored out first) and
thread-safe.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Hashable

import numpy as np

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.transcription import NodeMotion
from falcon_plan.planning.problem import PlanProblem

DEFAULT_RADIUS_M = 0.04
"""Neighbours farther than this (sum of start and goal distances) are not used [m]."""
DEFAULT_CAPACITY = 512
"""Solved problems kept per process."""



@dataclass(frozen=True)
class _Entry:
    start_m: np.ndarray
    goal_m: np.ndarray
    guess: NodeMotion


@dataclass(frozen=True)
class WarmStart:
    """A ``guess`` (a ``NodeMotion``) taken from a neighbour, and ``distance_m``, how far that
    neighbour was (sum of the start and goal distances) [m]."""

    guess: NodeMotion
    distance_m: float


class NeighbourCache:
    """Solved plans, grouped by what must match for a solution to be a good starting point
    (model, interval count, the caller's ``setting``, payload, number of via points).

    ``capacity``: solved problems kept (least recently stored out first); ``radius_m``:
    neighbours farther than this (sum of start and goal distances) are not used [m].
    """

    def __init__(self, capacity: int = DEFAULT_CAPACITY, radius_m: float = DEFAULT_RADIUS_M) -> None:
        self.capacity = capacity
        self.radius_m = radius_m
        self._entries: OrderedDict[tuple[Hashable, tuple[float, ...], tuple[float, ...]], _Entry] = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def _group(model: FalconModel, problem: PlanProblem, n_intervals: int, setting: Hashable) -> Hashable:
        return (model.params, model.effects, model.limits, n_intervals, setting,
                round(float(problem.payload_kg), 9), len(problem.via_m))

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        """Forget every stored solution."""
        with self._lock:
            self._entries.clear()

    def store(self, model: FalconModel, problem: PlanProblem, n_intervals: int, setting: Hashable,
              guess: NodeMotion) -> None:
        """Keep ``guess``, the node solution of ``problem`` solved with ``model`` on
        ``n_intervals`` intervals under ``setting`` (hashable: the command bound and profile),
        for later queries."""
        group = self._group(model, problem, n_intervals, setting)
        key = (group, tuple(np.round(problem.start_m, 9)), tuple(np.round(problem.goal_m, 9)))
        entry = _Entry(np.array(problem.start_m, float), np.array(problem.goal_m, float), guess)
        with self._lock:
            self._entries.pop(key, None)
            self._entries[key] = entry
            while len(self._entries) > self.capacity:
                self._entries.popitem(last=False)

    def lookup(self, model: FalconModel, problem: PlanProblem, n_intervals: int,
               setting: Hashable) -> WarmStart | None:
        """The nearest stored neighbour's solution (same ``model``, ``n_intervals`` and
        ``setting`` as stored) shifted onto ``problem``, or None."""
        group = self._group(model, problem, n_intervals, setting)
        start, goal = np.asarray(problem.start_m, float), np.asarray(problem.goal_m, float)
        best: _Entry | None = None
        best_distance = self.radius_m
        with self._lock:
            for (g, _, _), entry in self._entries.items():
                if g != group:
                    continue
                distance = float(np.linalg.norm(entry.start_m - start) + np.linalg.norm(entry.goal_m - goal))
                if distance <= best_distance:
                    best, best_distance = entry, distance
        if best is None:
            return None
        old = best.guess
        s = np.linspace(0.0, 1.0, old.p.shape[0])[:, None]
        shifted = old.p + (1.0 - s) * (start - best.start_m) + s * (goal - best.goal_m)
        v = np.array(old.v, float)
        v[0], v[-1] = problem.start_velocity_m_s, problem.goal_velocity_m_s
        return WarmStart(NodeMotion(old.duration_s, shifted, v, np.array(old.a, float)), best_distance)


NEIGHBOURS = NeighbourCache()
"""The process-wide cache the planning API uses for ``warm_start="neighbours"``."""
