"""Speed and quality of the minimum-time planner over the benchmark problems.

For every solvable problem in ``problems/*.json`` (or a built-in list when that folder is
missing) it plans with the given options (default: the service's fast path plus the
cross-checks), repeats the solve ``--repeat`` times for timing, and prints:

- the optimiser's solve time: median and p95 over all solves [ms], wall clock and CPU time
  of the process (on a shared machine the CPU time is the steadier figure);
- duration ratios: planner / toppra on the same path (~1: converged), planner / toppra on
  the straight line (<= 1: bending pays), ruckig / planner (> 1: the safe joint-space
  reference is slower);
- how many plans fell back to ruckig, and the worst dense command ratio |Tc| / tc_max;
- speed against two references measured in the same run: toppra (its two cross-check
  parametrisations of the same problem, timed inside the plan) and a *naive* configuration of
  the same transcription on the first ``--naive`` problems (CasADi's virtual machine instead
  of the compiled kernels, exact Hessian, no workspace screening: what PLANNING-NOTES'
  prototype did). Ratios > 1 mean the reference is slower.

Refusal problems are checked to be refused (WorkspaceError / InvalidProblemError).

Usage: ``python benchmarks/bench_planner.py [--problems DIR] [--repeat 3] [--intervals N]
[--naive 5] [--json OUT]``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidProblemError, WorkspaceError
from falcon_plan.planning.api import default_model, plan_problem
from falcon_plan.planning.casadi_planner import solve_min_time
from falcon_plan.planning.problem import PlanOptions, PlanProblem

BUILTIN = [
    {"name": "diag", "start_m": [0, 0, 0.12], "goal_m": [0.03, 0.02, 0.14], "tc_max": 2500},
    {"name": "down", "start_m": [0, 0.03, 0.10], "goal_m": [0, -0.02, 0.13], "tc_max": 2500},
    {"name": "across", "start_m": [-0.03, 0, 0.11], "goal_m": [0.03, 0.01, 0.12], "tc_max": 2500},
]
PROBLEM_KEYS = ("start_m", "goal_m", "start_velocity_m_s", "goal_velocity_m_s", "via_m", "payload_kg")


def load_problems(folder: Path | None) -> list[dict[str, Any]]:
    """Problem dicts from ``folder/*.json`` (sorted), or the built-in list."""
    if folder is None or not folder.is_dir():
        return [dict(p, expect={"status": "solved"}) for p in BUILTIN]
    return [json.loads(f.read_text()) for f in sorted(folder.glob("*.json"))]


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def run(folder: Path | None, repeat: int, n_intervals: int | None, naive: int = 5) -> dict[str, Any]:
    """Plan every problem; returns the per-problem rows and the summary."""
    model = default_model()
    rows: list[dict[str, Any]] = []
    solve_times: list[float] = []
    solve_cpus: list[float] = []
    refusals_ok = refusals = 0
    solved: list[tuple[PlanProblem, float, float]] = []  # (problem, tc_max, our median solve [s])
    for spec in load_problems(folder):
        problem = PlanProblem(**{k: spec[k] for k in PROBLEM_KEYS if k in spec})
        opts = PlanOptions(tc_max=float(spec["tc_max"]), n_intervals=int(spec.get("n_intervals", n_intervals or PlanOptions.n_intervals)),
                           refine=False, plant_check=False)
        if spec.get("expect", {}).get("status") == "refused":
            refusals += 1
            try:
                plan_problem(problem, opts, model)
                print(f"{spec['name']:28s} NOT REFUSED", flush=True)
            except (WorkspaceError, InvalidProblemError) as exc:
                refusals_ok += 1
                print(f"{spec['name']:28s} refused: {str(exc)[:70]}", flush=True)
            continue
        result = plan_problem(problem, opts, model)
        rep = result.report
        times, cpus = [rep.timings_s["optimiser"]], [rep.solve_cpu_s]
        for _ in range(repeat - 1):
            again = solve_min_time(model, problem, n_intervals=rep.n_intervals, tc_max=opts.tc_max,
                                   hessian=opts.hessian)
            times.append(again.solve_time_s)
            cpus.append(again.solve_cpu_s)
        solve_times += times
        solve_cpus += cpus
        solved.append((problem, opts.tc_max, float(np.median(times))))
        row = {"name": spec["name"], "method": rep.method, "duration_s": rep.duration_s,
               "toppra_ms": 1e3 * rep.timings_s.get("toppra", float("nan")),
               "solve_ms_median": 1e3 * float(np.median(times)), "cpu_ms_median": 1e3 * float(np.median(cpus)),
               "iterations": rep.solver_iterations,
               "worst_command_ratio": rep.worst_command_ratio,
               "planner_over_toppra_same_path": rep.planner_over_toppra_same_path,
               "planner_over_toppra_straight": rep.planner_over_toppra_straight,
               "ruckig_over_planner": rep.ruckig_over_planner}
        rows.append(row)
        fmt = lambda x: "   -  " if x is None else f"{x:6.4f}"  # noqa: E731
        print(f"{spec['name']:28s} {rep.method:15s} T={1e3 * rep.duration_s:7.2f} ms  solve "
              f"{row['solve_ms_median']:6.1f} ms (cpu {row['cpu_ms_median']:6.1f}, {rep.solver_iterations:3d} it) |Tc|/max "
              f"{rep.worst_command_ratio:.4f}  /same {fmt(row['planner_over_toppra_same_path'])}  "
              f"/straight {fmt(row['planner_over_toppra_straight'])}  ruckig/ {fmt(row['ruckig_over_planner'])}",
              flush=True)

    def stats(key: str) -> dict[str, float]:
        vals = [r[key] for r in rows if r[key] is not None and r["method"] == "casadi"]
        return {"median": float(np.median(vals)), "min": float(np.min(vals)), "max": float(np.max(vals))} if vals else {}

    naive_ratios = naive_reference(model, solved[:naive], n_intervals)
    toppra_ratios = [r["toppra_ms"] / r["solve_ms_median"] for r in rows if r["method"] == "casadi"]
    summary = {
        "speed_vs_toppra_median": float(np.median(toppra_ratios)),
        "speed_vs_naive_median": float(np.median(naive_ratios)) if naive_ratios else None,
        "naive_problems": len(naive_ratios),
        "problems_solved": len(rows), "fallbacks": sum(r["method"] != "casadi" for r in rows),
        "refusals_as_expected": f"{refusals_ok}/{refusals}",
        "solve_ms_median": 1e3 * float(np.median(solve_times)), "solve_ms_p95": 1e3 * percentile(solve_times, 95),
        "cpu_ms_median": 1e3 * float(np.median(solve_cpus)), "cpu_ms_p95": 1e3 * percentile(solve_cpus, 95),
        "planner_over_toppra_same_path": stats("planner_over_toppra_same_path"),
        "planner_over_toppra_straight": stats("planner_over_toppra_straight"),
        "ruckig_over_planner": stats("ruckig_over_planner"),
        "worst_command_ratio": max(r["worst_command_ratio"] for r in rows),
    }
    return {"rows": rows, "summary": summary}


def naive_reference(model: Any, solved: list[tuple[PlanProblem, float, float]],
                    n_intervals: int | None) -> list[float]:
    """Solve time of the naive configuration over ours, per problem (same transcription and
    N; uncompiled, exact Hessian, workspace constraints always imposed)."""
    import os

    previous = os.environ.get("FALCON_PLAN_NO_COMPILE")
    os.environ["FALCON_PLAN_NO_COMPILE"] = "1"
    ratios = []
    try:
        for problem, tc_max, ours_s in solved:
            ref = solve_min_time(model, problem, n_intervals=n_intervals or PlanOptions.n_intervals,
                                 tc_max=tc_max, hessian="exact", screen_workspace=False)
            ratios.append(ref.solve_time_s / ours_s)
            print(f"naive reference: {1e3 * ref.solve_time_s:8.1f} ms ({ref.iterations} it) vs ours "
                  f"{1e3 * ours_s:6.1f} ms -> {ratios[-1]:.1f}x", flush=True)
    finally:
        if previous is None:
            os.environ.pop("FALCON_PLAN_NO_COMPILE", None)
        else:
            os.environ["FALCON_PLAN_NO_COMPILE"] = previous
    return ratios


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=Path, default=Path(__file__).resolve().parents[1] / "problems")
    parser.add_argument("--repeat", type=int, default=3, help="solves per problem for timing")
    parser.add_argument("--intervals", type=int, default=None, help="override N")
    parser.add_argument("--naive", type=int, default=5, help="problems also solved by the naive reference")
    parser.add_argument("--json", type=Path, help="write rows and summary here")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    default_model()
    # build and warm the NLP once (not part of the per-plan timing)
    solve_min_time(default_model(), PlanProblem((0, 0, 0.12), (0.01, 0, 0.12)),
                   n_intervals=args.intervals or PlanOptions.n_intervals, tc_max=2500.0)
    out = run(args.problems, args.repeat, args.intervals, args.naive)
    out["summary"]["wall_s"] = time.perf_counter() - t0
    print(json.dumps(out["summary"], indent=2))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
