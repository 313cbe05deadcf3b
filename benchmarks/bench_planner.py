"""Speed, optimality and trackability of the minimum-time planner over the benchmark problems.

Planner configurations, measured in the same run (the machine is shared: compare ratios,
not absolute times):

- ``reference``: the configuration before issue 12 (piecewise-constant acceleration, N = 24,
  constant limit tc_max, no feedback reserve, no refinement: no statement of optimality);
- ``transcription``: the default before the switching-time solve (``switching=False``): the
  linear-profile transcription at N = 24 plus its refinement sequence (the N/2 partner, and
  the 2N solve and plan when that is not conclusive);
- ``fast``: ``PlanOptions.fast()`` (the service's fast path: the switching-time plan from
  the coarse transcription where it applies, tc_max minus the default feedback reserve; no
  refinement, so no gap estimate);
- ``default``: ``PlanOptions()`` without its optional cross-checks and plant run: the plan
  plus the refinement estimate behind the report's converged duration and gap (for a
  switching-time plan twice the RK4 steps; else the transcription's sequence);
- ``device``: ``PlanOptions.fast(limit="device")`` (the device's speed-dependent limit minus
  the reserve; timed like the others since issue 23).

What is timed (per problem, the timed configurations in turn, ``--repeat`` times each so that
all see the same load; median and p95 over the suite and their ratios to ``reference``; each
problem counts once, with the median of its repeats: counted per repeat, the p95 of 37
problems would depend on the number of repeats, two slow problems being 5.4 % of the suite,
so the figures over every repeat are reported beside as ``*_all_repeats``):

- ``wait``: the wall time of the whole ``plan_problem`` call, i.e. what a user waits for the
  plan: validation, the optimiser, the dense re-check, for ``default`` the refinement solves
  (and the 2N plan's re-check), and building the trajectory and report. This is the figure
  the issue's targets are about;
- ``solve``: the optimiser runs only (``PlanReport.solve_time_s``: the plan's solve plus, for
  ``default``, the refinement solves), wall and process CPU.

The full default (``PlanOptions()``: also toppra and ruckig cross-checks and the closed-loop
plant run) is timed once per problem and reported beside, as ``full_default_wait_ms``.

For every solvable problem in ``problems/*.json`` it also reports:

- the gap of each configuration's duration to a separate high-resolution solve of the same
  problem (``--hires`` intervals, linear profile, whose own error is below 0.01 %), and the
  report's own estimate of the gap (``default``), with the grid of the refinement partner;
- the duration with the device limit over the duration at the constant 2500 (same reserve);
- the executed peak command over the device's speed-dependent limit: each plan executed by
  the :class:`~falcon_plan.execution.executor.Executor` on the simulated device (nominal
  model), its logged commands against L(w) at the motion they act on
  (:func:`falcon_plan.planning.verify.log_limit_ratio`); rest-to-rest problems only (the
  executor holds the start before the motion and the goal after it, so a moving end starts
  or stops with a jump), summarised separately for tc_max <= 2500 (a constant limit above
  the static 2500 cannot be within the device's limit at rest, by design).

Refusal problems are checked to be refused (WorkspaceError / InvalidProblemError).

With ``--split`` it instead reports where one ``fast`` solve's time goes, per problem and
summed over the suite: IPOPT's own work (KKT factorisations and solves, the barrier update,
line search), CasADi's evaluation of the constraint Jacobian and the constraints (the
compiled per-point kernels mapped over the points, plus the MX graph around them), and the
Python deadline callback, from CasADi's per-function wall-time statistics of the last solver
call (the screening solve when the workspace constraints were inactive).

Usage: ``python benchmarks/bench_planner.py [--problems DIR] [--repeat 3] [--hires 192]
[--only NAME,NAME] [--json OUT] [--split]``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidProblemError, WorkspaceError
from falcon_plan.falconlog import read_log
from falcon_plan.planning.api import default_model, plan_problem
from falcon_plan.planning.min_time import SCREEN_MAX_ITER, solve_min_time
from falcon_plan.planning.transcription import (MinTimeSettings, get_nlp, model_constraints, payload_model,
                                                points_per_interval, segment_counts)
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.trajectory import Trajectory
from falcon_plan.planning.verify import log_limit_ratio

PROBLEM_KEYS = ("start_m", "goal_m", "start_velocity_m_s", "goal_velocity_m_s", "via_m", "payload_kg")
CONFIGS = {
    "reference": {"profile": "constant", "n_intervals": 24, "feedback_reserve": 0.0, "switching": False},
    "transcription": {"refine": True, "switching": False},
    "fast": {},
    "default": {"refine": True},
    "device": {"limit": "device"},
}
"""PlanOptions.fast() changes of each configuration (on top of the problem's tc_max)."""
TIMED = ("reference", "transcription", "fast", "default", "device")
"""Configurations whose waiting and solve times are measured."""
EXECUTED = ("reference", "default", "device")
"""Configurations whose plans are executed on the simulated device."""
PREROLL_S = 0.5
"""The executor's hold at the start before the motion [s]."""


def load_problems(folder: Path, only: list[str] | None) -> list[dict[str, Any]]:
    specs = [json.loads(f.read_text()) for f in sorted(folder.glob("*.json"))]
    return [s for s in specs if not only or s["name"] in only]


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def options_for(config: str, tc_max: float, **changes: Any) -> PlanOptions:
    return PlanOptions.fast(tc_max=tc_max, **{**CONFIGS[config], **changes})


def executed_ratio(model: Any, traj: Trajectory, problem: PlanProblem) -> tuple[float, float]:
    """(peak |Tc| / L(w), RMS tracking error [mm]) of ``traj`` run by the executor on the
    simulated device (the problem's payload, nominal otherwise)."""
    from falcon_plan.devices.sim_device import SimDevice
    from falcon_plan.execution.executor import Executor

    loaded = payload_model(model, problem)
    with tempfile.TemporaryDirectory() as tmp, \
            SimDevice(model=loaded, seed=0, start_position_m=np.asarray(problem.start_m)) as device:
        device.home()
        path = Path(tmp) / "run.csv"
        report = Executor(device, loaded, log_path=path, preroll_s=PREROLL_S).run(traj)
        ratio = log_limit_ratio(loaded, traj, read_log(path), PREROLL_S)
    return ratio, report.tracking.norm_rms_mm if report.tracking else float("nan")


def run(specs: list[dict[str, Any]], repeat: int, hires: int) -> dict[str, Any]:
    model = default_model()
    rows: list[dict[str, Any]] = []
    waits: dict[str, list[float]] = {c: [] for c in TIMED}        # per problem: the median of its repeats
    all_waits: dict[str, list[float]] = {c: [] for c in TIMED}    # every repeat
    times: dict[str, list[float]] = {c: [] for c in TIMED}
    cpus: dict[str, list[float]] = {c: [] for c in TIMED}
    full: list[float] = []
    refusals = refused = 0
    for spec in specs:
        problem = PlanProblem(**{k: spec[k] for k in PROBLEM_KEYS if k in spec})
        tc_max = float(spec["tc_max"])
        if spec.get("expect", {}).get("status") == "refused":
            refusals += 1
            try:
                plan_problem(problem, options_for("default", tc_max), model)
                print(f"{spec['name']:24s} NOT REFUSED", flush=True)
            except (WorkspaceError, InvalidProblemError) as exc:
                refused += 1
                print(f"{spec['name']:24s} refused: {str(exc)[:70]}", flush=True)
            continue
        row: dict[str, Any] = {"name": spec["name"], "tc_max": tc_max}
        plans = {}
        repeats: dict[str, list[list[float]]] = {c: [[], [], []] for c in TIMED}  # wait, solve, cpu
        # the whole plan_problem call, the configurations in turn
        for _ in range(repeat):
            for c in TIMED:
                t0 = time.perf_counter()
                plans[c] = plan_problem(problem, options_for(c, tc_max), model)
                wait = time.perf_counter() - t0
                all_waits[c].append(wait)
                for values, value in zip(repeats[c], (wait, plans[c].report.solve_time_s,
                                                       plans[c].report.solve_cpu_s)):
                    values.append(value)
                row.setdefault(f"{c}_wait_ms", []).append(1e3 * wait)
                row.setdefault(f"{c}_solve_ms", []).append(1e3 * plans[c].report.solve_time_s)
        for c in TIMED:
            for values, per_problem in zip(repeats[c], (waits[c], times[c], cpus[c])):
                per_problem.append(float(np.median(values)))
        t0 = time.perf_counter()
        plan_problem(problem, PlanOptions.of(tc_max=tc_max), model)
        full.append(time.perf_counter() - t0)
        row["full_default_wait_ms"] = 1e3 * full[-1]
        for c, result in plans.items():
            rep = result.report
            opts = options_for(c, tc_max)
            fine = solve_min_time(model, problem, opts.command_bound(model.params), MinTimeSettings(hires))
            row[f"{c}_method"] = rep.method
            row[f"{c}_n_intervals"] = rep.n_intervals
            row[f"{c}_duration_ms"] = 1e3 * rep.duration_s
            row[f"{c}_gap"] = (rep.duration_s - fine.duration_s) / fine.duration_s if fine.success else None
            row[f"{c}_dense_ratio"] = rep.worst_command_ratio
            if problem.is_rest_to_rest and c in EXECUTED:
                row[f"{c}_executed_over_limit"], row[f"{c}_track_rms_mm"] = executed_ratio(
                    model, result.trajectory, problem)
        row["default_switching"] = plans["default"].report.switching is not None
        row["device_switching"] = plans["device"].report.switching is not None
        row["default_estimated_gap"] = plans["default"].report.optimality_gap
        row["default_refinement_intervals"] = plans["default"].report.refinement_intervals
        if row["default_estimated_gap"] is not None and row["default_gap"] is not None:
            row["default_estimate_error"] = row["default_estimated_gap"] - row["default_gap"]
        at_2500 = plans["fast"] if tc_max == 2500.0 else plan_problem(problem, options_for("fast", 2500.0), model)
        row["device_over_2500"] = plans["device"].report.duration_s / at_2500.report.duration_s
        rows.append(row)

        def pct(key: str) -> str:
            return "   -   " if row.get(key) is None else f"{100 * row[key]:+.3f}"

        def num(key: str) -> str:
            return "  -  " if row.get(key) is None else f"{row[key]:.3f}"

        print(f"{spec['name']:22s} wait ms ref/transcription/fast/default/device " + "/".join(
            f"{np.median(row[c + '_wait_ms']):.1f}" for c in TIMED)
            + f" (full {row['full_default_wait_ms']:.0f})"
            + f" | gap % ref {pct('reference_gap')} fast {pct('fast_gap')} default {pct('default_gap')}"
            f" (N={row['default_n_intervals']}{' switching' if row['default_switching'] else ''}, est "
            f"{pct('default_estimated_gap')} from {row['default_refinement_intervals']}) transcription "
            f"{pct('transcription_gap')} device {pct('device_gap')} ({row['device_method']}"
            f"{' switching' if row['device_switching'] else ''})"
            f" | device/2500 {row['device_over_2500']:.4f}"
            f" | executed/limit ref {num('reference_executed_over_limit')} default {num('default_executed_over_limit')}"
            f" device {num('device_executed_over_limit')}", flush=True)

    def col(key: str) -> list[float]:
        return [r[key] for r in rows if r.get(key) is not None]

    def spread(key: str) -> dict[str, float]:
        vals = col(key)
        return {"min": float(np.min(vals)), "median": float(np.median(vals)), "max": float(np.max(vals))} if vals else {}

    def stats(values: list[float]) -> dict[str, float]:
        return {"median": 1e3 * float(np.median(values)), "p95": 1e3 * percentile(values, 95)}

    def ratios(ref: list[float], new: list[float]) -> dict[str, float]:
        return {"median": float(np.median(ref) / np.median(new)), "p95": percentile(ref, 95) / percentile(new, 95)}

    summary: dict[str, Any] = {
        "problems_solved": len(rows), "refusals_as_expected": f"{refused}/{refusals}",
        "fallbacks": {c: sum(r[f"{c}_method"] != "casadi" for r in rows) for c in CONFIGS},
        "what_is_timed": "wait = the whole plan_problem call; solve = its optimiser runs (for default incl. "
                         "the refinement solves); median and p95 over the problem suite, each problem "
                         "counted once (the median of its repeats; *_all_repeats: every repeat counted); "
                         "ratios = reference / configuration (> 1: faster)",
    }
    for c in TIMED:
        summary[f"{c}_wait_ms"] = stats(waits[c])
        summary[f"{c}_wait_ms_all_repeats"] = stats(all_waits[c])
        summary[f"{c}_solve_ms"] = {**stats(times[c]), **{f"cpu_{k}": v for k, v in stats(cpus[c]).items()}}
        summary[f"speed_ratio_reference_over_{c}"] = {
            "wait": ratios(waits["reference"], waits[c]), "solve": ratios(times["reference"], times[c]),
            "solve_cpu": ratios(cpus["reference"], cpus[c])}
    summary["full_default_wait_ms"] = stats(full)
    low = [r for r in rows if r["tc_max"] <= 2500.0]
    for c in CONFIGS:
        summary[f"{c}_gap"] = spread(f"{c}_gap")
        summary[f"{c}_dense_ratio"] = spread(f"{c}_dense_ratio")
        if c in EXECUTED:
            summary[f"{c}_executed_over_limit"] = spread(f"{c}_executed_over_limit")
            vals = [r[f"{c}_executed_over_limit"] for r in low if r.get(f"{c}_executed_over_limit") is not None]
            summary[f"{c}_executed_over_limit_tc_max_le_2500"] = {"max": max(vals), "problems": len(vals)} if vals else {}
    summary["default_estimated_gap"] = spread("default_estimated_gap")
    summary["default_estimate_error"] = spread("default_estimate_error")
    summary["default_switching_plans"] = sum(r["default_switching"] for r in rows)
    summary["device_switching_plans"] = sum(r["device_switching"] for r in rows)
    summary["default_returned_2n"] = sum(r["default_n_intervals"] > r["fast_n_intervals"] for r in rows)
    summary["device_over_2500"] = spread("device_over_2500")
    return {"rows": rows, "summary": summary}


SPLIT_PARTS = {"jac_g": "nlp_jac_g", "g": "nlp_g", "callback": "callback_fun"}
"""CasADi statistics (``t_wall_<name>``) split out of a solve; the rest is IPOPT's own work."""


def time_split(specs: list[dict[str, Any]], repeat: int) -> dict[str, Any]:
    """Where the ``fast`` configuration's solve time goes (see the module docstring): the
    fastest of ``repeat`` solves per problem, its parts [ms] and iterations."""
    model = default_model()
    rows = []
    for spec in specs:
        if spec.get("expect", {}).get("status") == "refused":
            continue
        problem = PlanProblem(**{k: spec[k] for k in PROBLEM_KEYS if k in spec})
        opts = options_for("fast", float(spec["tc_max"]))
        n, bound = opts.intervals_for(problem), opts.command_bound(model.params)
        best: dict[str, Any] | None = None
        for _ in range(repeat):
            r = solve_min_time(model, problem, bound, MinTimeSettings(n, profile=opts.transcription.profile))
            screened = r.workspace.startswith("inactive")
            nlp = get_nlp(model_constraints(model, opts.solver.hessian, not screened, bound.kind),
                          segment_counts(problem, n), opts.solver.hessian, SCREEN_MAX_ITER if screened else 400,
                          screened, opts.transcription.profile, points_per_interval(bound.kind))
            stats = nlp.solver.stats()
            split = {k: 1e3 * stats.get(f"t_wall_{v}", 0.0) for k, v in SPLIT_PARTS.items()}
            split["total"] = 1e3 * stats["t_wall_total"]
            split["ipopt"] = split["total"] - sum(split[k] for k in SPLIT_PARTS)
            row = {"name": spec["name"], "iterations": int(stats["iter_count"]), "points": nlp.n_points,
                   "variables": nlp.n_w, "constraints": nlp.n_g, **split}
            if best is None or row["total"] < best["total"]:
                best = row
        assert best is not None
        rows.append(best)
        print(f"{best['name']:22s} {best['iterations']:3d} it, {best['points']} points, {best['total']:6.1f} ms: "
              + ", ".join(f"{k} {best[k]:.1f}" for k in ("ipopt", *SPLIT_PARTS))
              + f" | {best['total'] / best['iterations']:.2f} ms/it", flush=True)
    total = {k: float(sum(r[k] for r in rows)) for k in ("total", "ipopt", *SPLIT_PARTS)}
    iters = sum(r["iterations"] for r in rows)
    summary = {"problems": len(rows), "median_ms": float(np.median([r["total"] for r in rows])),
               "share": {k: total[k] / total["total"] for k in ("ipopt", *SPLIT_PARTS)},
               "ms_per_iteration": {k: total[k] / iters for k in ("total", "ipopt", *SPLIT_PARTS)},
               "iterations": {"median": float(np.median([r["iterations"] for r in rows])),
                              "max": max(r["iterations"] for r in rows)}}
    return {"rows": rows, "summary": summary}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=Path, default=Path(__file__).resolve().parents[1] / "problems")
    parser.add_argument("--repeat", type=int, default=3, help="timed solves per problem and configuration")
    parser.add_argument("--hires", type=int, default=192, help="intervals of the high-resolution solve (>= 192)")
    parser.add_argument("--only", type=lambda s: s.split(","), default=None, help="problem names, comma-separated")
    parser.add_argument("--json", type=Path, help="write rows and summary here")
    parser.add_argument("--split", action="store_true",
                        help="only report where the default solve's time goes (IPOPT vs evaluations)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    load_before = os.getloadavg()
    # build and warm every NLP once (not part of the timing)
    warm = PlanProblem((0, 0, 0.12), (0.01, 0, 0.12))
    for c in CONFIGS:
        plan_problem(warm, options_for(c, 2500.0, refine=True), default_model())
    plan_problem(warm, PlanOptions(), default_model())
    specs = load_problems(args.problems, args.only)
    out = time_split(specs, args.repeat) if args.split else run(specs, args.repeat, args.hires)
    out["summary"]["wall_s"] = time.perf_counter() - t0
    out["summary"]["load_average_before_after"] = [list(load_before), list(os.getloadavg())]
    out["summary"]["cpus"] = os.cpu_count()
    print(json.dumps(out["summary"], indent=2))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
