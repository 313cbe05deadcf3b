"""The planning entry point: ``plan(start_m, goal_m, options, model) -> Plan``, and
``plan_problem`` for a ready :class:`~falcon_plan.planning.problem.PlanProblem`.

What runs when is :func:`falcon_plan.planning.pipeline.run` (validation, the coarse solve and
the switching-time plan, else the transcription at N and its repairs, the fallback, the
optional refinement, cross-checks and plant run, the report); this module gives it its
defaults (``PlanOptions()``, the nominal model) and prepares a process for fast plans
(:func:`warm_up`).

The command bound is ``options.command_bound``: tc_max or the device's speed-dependent
limit (``options.limits.limit``), minus ``options.limits.feedback_reserve`` kept free for feedback.

The service's fast path is ``PlanOptions.fast()``: no refinement, cross-checks or plant run.
"""
from __future__ import annotations

import logging
import time
from typing import Any

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning import fallback, pipeline
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.report import Plan

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


def plan_problem(problem: PlanProblem, options: PlanOptions | None = None,
                 model: FalconModel | None = None) -> Plan:
    """:func:`plan` for a ready ``problem`` (a :class:`PlanProblem`), with ``options``
    (default ``PlanOptions()``) and ``model`` (default nominal): same behaviour and errors.
    The pipeline is :func:`falcon_plan.planning.pipeline.run`."""
    return pipeline.run(problem, options or PlanOptions(), model or default_model())


def warm_up(model: FalconModel | None = None, options: PlanOptions | None = None,
            prepare_fallback: bool = True) -> float:
    """Build (and compile, first time on this machine) everything a plan with ``model``
    (default nominal) and ``options`` (default ``PlanOptions()``: the refinement, the toppra
    and ruckig cross-checks and the plant run too, as the options ask; with them left out the
    README's first full plan after a warm-up took 1.45 s instead of 0.1 s) needs, so that the
    first real query is as fast as the next ones, and with ``prepare_fallback`` the ruckig fallback too (~0.15 s more: a service needs it
    instantly; a single plan on the command line only if it falls back); returns the time
    taken [s]. A service calls it at start-up. The compiled kernels are cached on disk, so
    later processes load them in milliseconds (a fresh machine compiles for about 1.5
    minutes: 30-50 s of one core for each command rule's switching-time step on a 2-core
    machine; ``python -m falcon_plan.compiled.prepare`` builds them ahead)."""
    t0 = time.perf_counter()
    options = options or PlanOptions()
    start, goal = (0.0, 0.0, 0.12), (0.01, 0.005, 0.125)
    result = plan(start, goal, options, model)
    model = model or default_model()
    if prepare_fallback:
        fallback.ruckig_reference(model, PlanProblem(start, goal), options.command_bound(model.params).at_rest)
    log.info("planner warmed up in %.2f s (%s)", time.perf_counter() - t0, result.report.method)
    return time.perf_counter() - t0


__all__ = ["plan", "plan_problem", "default_model", "warm_up"]
