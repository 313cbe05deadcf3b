"""Warm starts from solved neighbours: same optimum, fewer iterations, never across groups."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.errors import InvalidProblemError
from falcon_plan.planning.api import plan
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.transcription import NodeMotion
from falcon_plan.planning.warmstart import NEIGHBOURS, NeighbourCache

START_M = np.array([0.0, 0.0, 0.12])


def test_neighbour_warm_start_finds_the_same_optimum_in_fewer_iterations() -> None:
    NEIGHBOURS.clear()
    rng = np.random.default_rng(7)
    goals = [START_M + np.array([0.03, 0.02, 0.02]) + rng.normal(0.0, 0.004, 3) for _ in range(8)]
    cold = [plan(START_M, g, PlanOptions.fast(switching=False)).report for g in goals]
    warm = [plan(START_M, g, PlanOptions.fast(switching=False, warm_start="neighbours")).report for g in goals]
    assert "cold start" in warm[0].to_dict()["notes"][0]
    assert all("warm-started" in r.to_dict()["notes"][0] for r in warm[1:])
    for c, w in zip(cold, warm):
        assert w.duration_s == pytest.approx(c.duration_s, rel=1e-3)
    cold_iters = sum(r.to_dict()["solver_iterations"] for r in cold[1:])
    warm_iters = sum(r.to_dict()["solver_iterations"] for r in warm[1:])
    assert warm_iters < cold_iters


def test_cache_shifts_the_neighbour_onto_the_new_ends_and_respects_groups(model) -> None:
    cache = NeighbourCache(radius_m=0.02)
    old = PlanProblem(START_M, START_M + [0.02, 0.0, 0.0])
    n = 4
    p = np.linspace(old.start_m, old.goal_m, n + 1)
    cache.store(model, old, n, 2500.0, NodeMotion(0.05, p, np.zeros((n + 1, 3)), np.zeros((n, 3))))
    new = PlanProblem(START_M + [0.0, 0.001, 0.0], START_M + [0.021, 0.0, 0.0])
    warm = cache.lookup(model, new, n, 2500.0)
    assert warm is not None and warm.distance_m == pytest.approx(0.002)
    shifted = warm.guess.p
    assert warm.guess.duration_s == 0.05
    np.testing.assert_allclose(shifted[0], new.start_m, atol=1e-15)
    np.testing.assert_allclose(shifted[-1], new.goal_m, atol=1e-15)
    # another command limit, interval count or a far problem never matches
    assert cache.lookup(model, new, n, 2000.0) is None
    assert cache.lookup(model, new, n + 1, 2500.0) is None
    assert cache.lookup(model, PlanProblem(START_M, START_M + [0.0, 0.0, 0.03]), n, 2500.0) is None


def test_unknown_warm_start_mode_is_a_clear_error() -> None:
    with pytest.raises(InvalidProblemError, match="warm_start must be one of"):
        PlanOptions.of(warm_start="always")
