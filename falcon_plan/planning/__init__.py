"""Minimum-time planning: problems, the CasADi planner, cross-checks, trajectories.

The public names are loaded lazily, so ``import falcon_plan.planning.trajectory`` (what an
executor needs) does not pull in CasADi's solvers, toppra or ruckig:

``plan``, ``plan_problem``, ``warm_up`` (:mod:`.api`), ``PlanProblem``, ``PlanOptions``
(:mod:`.problem`), ``Plan``, ``PlanReport`` (:mod:`.report`), ``Trajectory`` (:mod:`.trajectory`).
"""
from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {"plan": "api", "plan_problem": "api", "warm_up": "api", "PlanProblem": "problem",
            "PlanOptions": "problem", "Plan": "report", "PlanReport": "report", "Trajectory": "trajectory"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
