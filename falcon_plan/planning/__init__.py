"""Minimum-time planning: problems, the CasADi planner, cross-checks, the quintic reference
move. The trajectory it produces is :class:`falcon_plan.trajectory.Trajectory`.

The public names are loaded lazily (the solvers, toppra and ruckig load on first use):
``plan``, ``plan_problem``, ``warm_up`` (:mod:`.api`), ``PlanProblem``, ``PlanOptions`` and its
parts ``CommandLimits``, ``Transcription``, ``SolverSettings``, ``Checks`` (:mod:`.problem`), ``Plan``, ``PlanReport`` (:mod:`.report`).
"""
from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {"plan": "api", "plan_problem": "api", "warm_up": "api", "PlanProblem": "problem",
            "PlanOptions": "problem", "CommandLimits": "problem",
            "Transcription": "problem", "SolverSettings": "problem", "Checks": "problem", "Plan": "report", "PlanReport": "report"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
