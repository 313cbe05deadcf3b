"""Plan and PlanReport: what :func:`falcon_plan.planning.api.plan` returns.

:class:`PlanReport` is a frozen record of how a plan was made and checked; ``to_dict()`` is
JSON-ready (flat keys for the figures clients read most, nested dicts for the details) and
``summary()`` is the human-readable text the CLI prints. Durations in seconds, commands in
command units, ratios dimensionless.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from falcon_plan.trajectory import Trajectory

class PlanStatus(StrEnum):
    """How a plan ended (equal to its string value, which is what JSON carries)."""

    OPTIMAL = "optimal"
    """The optimiser's plan passed the dense re-check."""
    FALLBACK = "fallback"
    """The ruckig reference was returned instead (see ``fallback_reason``)."""
    FAILED = "failed"
    """Nothing usable (PlanningFailed)."""


class PlanMethod(StrEnum):
    """Which method produced the trajectory (equal to its string value)."""

    CASADI = "casadi"
    RUCKIG_FALLBACK = "ruckig-fallback"
    NONE = "none"


class WorkspaceHandling(StrEnum):
    """How the workspace constraints of a plan's solve were handled (the report's
    ``workspace_constraints``; equal to its string value)."""

    IMPOSED = "imposed"
    """Solved with the workspace margins from the start."""
    IMPOSED_ACTIVE = "imposed (active)"
    """The solve without them left the workspace: solved again with them."""
    IMPOSED_AFTER_FAILED_SCREENING = "imposed (screening failed)"
    """The solve without them failed: solved again with them."""
    INACTIVE_SCREENED = "inactive (screened)"
    """The solve without them stayed inside: kept (it is optimal with them too)."""
    INACTIVE_DENSE_CHECKED = "inactive (dense re-check of the plan)"
    """Left out of the solve; the dense re-check of the final plan checks the workspace."""
    IGNORED = "ignored (not checked)"
    """Left out and not checked (a coarse solve whose plan is checked later)."""
    NOT_SOLVED = ""
    """No optimiser solve made the plan (the fallback, or a failure)."""


STATUSES = tuple(s.value for s in PlanStatus)
"""The :class:`PlanStatus` values."""
METHODS = tuple(m.value for m in PlanMethod)
"""The :class:`PlanMethod` values."""


def _ratio(num: float | None, den: float | None) -> float | None:
    if num is None or den is None or den <= 0 or not math.isfinite(num):
        return None
    return num / den


@dataclass(frozen=True)
class PlanReport:
    """How a plan was made and checked.

    Attributes
    ----------
    status : a :class:`PlanStatus` (a plain string is converted).
    method : a :class:`PlanMethod`: "casadi" or "ruckig-fallback" ("none" when failed).
    duration_s : duration of the returned trajectory [s] (None when failed).
    solve_time_s : wall time of the optimiser runs [s]: the plan's solve, a re-solve after a
        failed dense re-check, the refinement sequence's solves (the converged-duration
        estimate), and the fallback when used. ``total_time_s`` is what the caller waited.
    solve_cpu_s : CPU time of those optimiser runs [s] (steadier than wall time on a shared
        machine).
    workspace_constraints : how the solve handled the workspace margins, a
        :class:`WorkspaceHandling` ("inactive (screened)" when the solve without them
        already stayed inside, "imposed (active)" when they had to be imposed, ...).
    total_time_s : wall time of the whole call, checks included [s].
    solver_status, solver_iterations, solver_success : IPOPT's return status, iteration count
        and success flag of the optimiser run (also when the fallback was used).
    n_intervals, hessian : the transcription's N and the Hessian choice.
    fallback_reason : why the fallback was used ("" otherwise).
    tc_max : the constant command limit option [command units] (used when the bound is
        constant).
    command_bound : the bound the plan respects, e.g. "constant 2500 - 150 reserve" or
        "device limit 2500..4096 - 150 reserve".
    worst_command_ratio : max |Tc| / bound on the dense re-check (10 points per interval).
    worst_command_time_s : where [s].
    worst_workspace_margin, worst_margin_name : the smallest of the planner's workspace
        constraint rows on the dense re-check (>= 0 inside; mixed units: radians for the leg
        angle, sines for knee and parallelogram, |det| for the forward singularity) and which.
    worst_angle_margin_deg, worst_angle_margin_name : the nearest angle limit on the dense
        re-check [deg] and which (e.g. ``leg angle, leg 2``): what the summary and the plan's
        plot show.
    forward_singularity_margin : the smallest forward-singularity measure above its floor
        on the dense re-check [unitless |det|].
    toppra_same_path_s, toppra_straight_s, ruckig_s : reference durations [s] (None when not
        computed or not applicable; see ``notes``).
    refinement_intervals : N of the other grid of the refinement sequence (N/2, or 2N when
        the N/2 estimate was not conclusive; None without refinement).
    refined_duration_s : the duration on that grid [s]; refinement_change : its relative
        change against the N plan, (T_other - T_N) / T_N.
    converged_duration_s : the duration for N -> infinity estimated from the two by
        Richardson extrapolation (the durations converge at first order in 1/N with a
        constant acceleration per interval, at second order with the linear profile) [s].
    optimality_gap : the returned plan's gap to it, (T - T_inf) / T_inf (None without
        refinement).
    switching : the switching-time solve that made the plan
        (:meth:`~falcon_plan.planning.shooting.SwitchingResult.to_dict`: starting signs and
        switch times per leg, iterations, the optimality check), or None when the plan is the
        transcription's own (then ``n_intervals`` is its N; with ``switching`` it is the N of
        the coarse transcription the pattern came from, and ``refinement_intervals`` counts
        the RK4 steps of the finer integration).
    plant : the closed-loop plant run (PlantCheck.to_dict(): tracking errors, the executed
        peak command ``max_command`` and its ratio to the device's speed-dependent limit
        ``max_command_over_limit``), or None when not run.
    problem, options : the inputs, as dicts.
    notes : anything a reader should know (skipped checks, approximations).
    timings_s : wall time per step of the call [s] ("optimiser", "dense_check", "refine",
        "fallback", "toppra", "ruckig", "plant"; only the steps that ran).
    """

    status: PlanStatus
    method: PlanMethod
    duration_s: float | None
    solve_time_s: float
    total_time_s: float
    solver_status: str
    solver_iterations: int
    solver_success: bool
    n_intervals: int
    hessian: str
    fallback_reason: str
    tc_max: float
    worst_command_ratio: float | None
    worst_command_time_s: float | None
    worst_workspace_margin: float | None
    worst_margin_name: str
    toppra_same_path_s: float | None = None
    toppra_straight_s: float | None = None
    ruckig_s: float | None = None
    refined_duration_s: float | None = None
    refinement_change: float | None = None
    refinement_intervals: int | None = None
    plant: dict[str, Any] | None = None
    problem: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", PlanStatus(self.status))
        object.__setattr__(self, "method", PlanMethod(self.method))
    timings_s: dict[str, float] = field(default_factory=dict)
    solve_cpu_s: float | None = None
    workspace_constraints: WorkspaceHandling = WorkspaceHandling.NOT_SOLVED
    command_bound: str = ""
    converged_duration_s: float | None = None
    optimality_gap: float | None = None
    switching: dict[str, Any] | None = None
    worst_angle_margin_deg: float | None = None
    worst_angle_margin_name: str = ""
    forward_singularity_margin: float | None = None

    @property
    def planner_over_toppra_same_path(self) -> float | None:
        """duration / toppra on the same path (about 1 when the optimiser converged)."""
        return _ratio(self.duration_s, self.toppra_same_path_s)

    @property
    def planner_over_toppra_straight(self) -> float | None:
        """duration / toppra on the straight line (<= 1: bending the path pays)."""
        return _ratio(self.duration_s, self.toppra_straight_s)

    @property
    def ruckig_over_planner(self) -> float | None:
        """ruckig reference / duration (> 1: the safe joint-space limits are conservative)."""
        return _ratio(self.ruckig_s, self.duration_s)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (floats, strings, lists, dicts, None)."""
        return {
            "status": self.status.value, "method": self.method.value, "duration_s": self.duration_s,
            "solve_time_s": self.solve_time_s, "solve_cpu_s": self.solve_cpu_s,
            "total_time_s": self.total_time_s,
            "solver_status": self.solver_status, "solver_iterations": self.solver_iterations,
            "solver_success": self.solver_success, "n_intervals": self.n_intervals,
            "hessian": self.hessian, "workspace_constraints": self.workspace_constraints,
            "fallback_reason": self.fallback_reason,
            "tc_max": self.tc_max, "command_bound": self.command_bound,
            "worst_command_ratio": self.worst_command_ratio,
            "worst_command_time_s": self.worst_command_time_s,
            "worst_workspace_margin": self.worst_workspace_margin,
            "worst_margin_name": self.worst_margin_name,
            "worst_angle_margin_deg": self.worst_angle_margin_deg,
            "worst_angle_margin_name": self.worst_angle_margin_name,
            "forward_singularity_margin": self.forward_singularity_margin,
            "toppra_same_path_s": self.toppra_same_path_s,
            "toppra_straight_s": self.toppra_straight_s,
            "ruckig_s": self.ruckig_s,
            "planner_over_toppra_same_path": self.planner_over_toppra_same_path,
            "planner_over_toppra_straight": self.planner_over_toppra_straight,
            "ruckig_over_planner": self.ruckig_over_planner,
            "refined_duration_s": self.refined_duration_s,
            "refinement_change": self.refinement_change,
            "refinement_intervals": self.refinement_intervals,
            "converged_duration_s": self.converged_duration_s,
            "optimality_gap": self.optimality_gap,
            "switching": self.switching,
            "plant": self.plant,
            "problem": self.problem, "options": self.options,
            "notes": list(self.notes), "timings_s": dict(self.timings_s),
        }

    def summary(self) -> str:
        """A few lines for people (the CLI's default output)."""
        def ms(x: float | None) -> str:
            return "-" if x is None else f"{1e3 * x:.2f} ms"

        def ratio(x: float | None) -> str:
            return "-" if x is None else f"{x:.4f}"

        lines = [
            f"status {self.status} ({self.method}), duration {ms(self.duration_s)}",
            f"solver {self.solver_status}, {self.solver_iterations} iterations, N={self.n_intervals}, "
            f"solve {ms(self.solve_time_s)}, total {ms(self.total_time_s)}; workspace constraints "
            f"{self.workspace_constraints or '-'}",
        ]
        if self.fallback_reason:
            lines.append(f"fallback because: {self.fallback_reason}")
        if self.switching:
            lines.append(f"bang-bang: switch times solved exactly from the N={self.n_intervals} pattern "
                         f"({self.switching['iterations']} Newton iterations, optimality check "
                         f"{self.switching['worst_help']:+.3f})")
        if self.worst_command_ratio is not None:
            margin = ("" if self.worst_angle_margin_deg is None else
                      f", nearest workspace limit {self.worst_angle_margin_deg:.1f} deg away "
                      f"({self.worst_angle_margin_name}), forward-singularity measure "
                      f"{self.forward_singularity_margin:.2f} above its floor")
            lines.append(f"dense re-check: max |Tc|/bound {self.worst_command_ratio:.4f} (bound "
                         f"{self.command_bound or self.tc_max}){margin}")
        if self.options.get("checks", {}).get("crosscheck", True):
            lines.append(f"toppra same path {ms(self.toppra_same_path_s)} (planner/toppra "
                         f"{ratio(self.planner_over_toppra_same_path)}), toppra straight "
                         f"{ms(self.toppra_straight_s)} (planner/toppra {ratio(self.planner_over_toppra_straight)}), "
                         f"ruckig {ms(self.ruckig_s)} (ruckig/planner {ratio(self.ruckig_over_planner)})")
        else:
            lines.append("cross-checks (toppra same path and straight line, ruckig): not run")
        if self.refinement_change is not None:
            lines.append(f"refinement at N={self.refinement_intervals}: {ms(self.refined_duration_s)} "
                         f"({100 * self.refinement_change:+.3f} %)")
        if self.optimality_gap is not None:
            lines.append(f"converged duration (N -> inf, extrapolated) {ms(self.converged_duration_s)}: "
                         f"this plan is {100 * self.optimality_gap:.3f} % above it")
        if self.plant is not None:
            if self.plant.get("ran"):
                err = self.plant.get("max_error_mm")
                peak, over = self.plant.get("max_command"), self.plant.get("max_command_over_limit")
                executed = "" if peak is None else f", executed peak |Tc| {peak:.0f}" + (
                    "" if over is None else f" ({over:.3f} of the device limit)")
                lines.append(f"plant run: {'passed' if self.plant.get('passed') else 'FAILED'}, max error "
                             f"{'-' if err is None else f'{err:.3f} mm'}{executed} "
                             f"{self.plant.get('note', '')}".rstrip())
            else:
                lines.append(f"plant run FAILED: {self.plant.get('note', '')}")
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


@dataclass(frozen=True)
class Plan:
    """A planned motion and how it was made: ``trajectory`` (Trajectory), ``report`` (PlanReport)."""

    trajectory: Trajectory
    report: PlanReport

    def __repr__(self) -> str:
        r = self.report
        return (f"Plan({r.method} {r.status}, {1e3 * r.duration_s:.2f} ms, planned in "
                f"{1e3 * r.total_time_s:.0f} ms, {self.trajectory!r})")

    def to_dict(self) -> dict[str, Any]:
        """{"trajectory": ..., "report": ...}, JSON-ready."""
        return {"trajectory": self.trajectory.to_dict(), "report": self.report.to_dict()}


__all__ = ["Plan", "PlanReport", "PlanStatus", "PlanMethod", "WorkspaceHandling", "STATUSES", "METHODS"]
