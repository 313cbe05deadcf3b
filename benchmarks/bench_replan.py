"""Replanning while moving (issue 24 item 1): random mid-motion goal switches.

Running plans between random workspace points; for each case a random running plan, a random
splice time (10-90 % of its length) and a new goal: a nudge of the old goal (within 10 mm), a
random workspace point, or a reversal (back near the running plan's start). Per replan: wall
time, method (warm from the running plan, or the pipeline), the dense re-check's |Tc|/bound.
On a sample, the gap to an independent high-resolution solve from the same state (the
pipeline with refinement: its converged duration). Times are distorted by other load on the
machine: the cold plan of a fixed rest-to-rest problem, timed in the same run, is the reference.
``--search first`` replans with ``replan_search="first"`` (the first warm guess that plans)
instead of the search for the shortest extremal: the same cases, for the trade of time for
duration.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_replan.py --cases 1000 --sample 20
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from falcon_plan.errors import PlanningFailed
from falcon_plan.model.workspace import sample_workspace
from falcon_plan.planning.api import default_model, plan_problem
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.replan import replan

KINDS = ("nudge", "random", "reversal")


def _new_goal(kind: str, running: PlanProblem, rng: np.random.Generator, pool: np.ndarray, model) -> np.ndarray:
    from falcon_plan.model.workspace import in_workspace

    for _ in range(100):
        if kind == "random":
            goal = pool[rng.integers(len(pool))]
        else:
            centre = np.asarray(running.goal_m if kind == "nudge" else running.start_m)
            goal = centre + rng.uniform(-0.01, 0.01, 3)
        if np.all(in_workspace(goal[None, :], model.params, model.limits)):
            return goal
    return np.asarray(running.goal_m)


REFERENCE_INTERVALS = (None, 48, 16)
"""N of the independent reference's attempts in turn (None: the options' default, 24 refined):
IPOPT can run out of iterations from a fast moving start at one N and not at another."""


def _reference_duration(problem: PlanProblem, precise: PlanOptions, model) -> float | None:
    """The converged optimum [s] of ``problem`` by the pipeline with refinement (``precise``),
    at each N of :data:`REFERENCE_INTERVALS` until one plans; None when none does."""
    for n in REFERENCE_INTERVALS:
        try:
            ref = plan_problem(problem, precise if n is None else precise.replace(n_intervals=n), model)
        except PlanningFailed:
            continue
        if ref.trajectory.source != "ruckig":
            return ref.report.converged_duration_s or ref.report.duration_s
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", type=int, default=1000)
    parser.add_argument("--running", type=int, default=20, help="running plans to switch from")
    parser.add_argument("--sample", type=int, default=20, help="cases checked against a high-resolution solve")
    parser.add_argument("--seed", type=int, default=24)
    parser.add_argument("--search", default="shortest", choices=("shortest", "first"),
                        help="how the replans search their warm guesses (PlanOptions replan_search)")
    parser.add_argument("--json", default=None, help="write the figures to this JSON file")
    args = parser.parse_args(argv)
    model = default_model()
    options = PlanOptions.fast(replan_search=args.search)
    rng = np.random.default_rng(args.seed)
    pool = sample_workspace(4000, rng, model.params)
    # the reference: a cold rest-to-rest plan, timed in this run
    ref_problem = PlanProblem(tuple(pool[0]), tuple(pool[1]))
    plan_problem(ref_problem, options, model)
    ref_times = []
    for _ in range(5):
        t0 = time.perf_counter()
        plan_problem(ref_problem, options, model)
        ref_times.append(time.perf_counter() - t0)
    ref_s = float(np.median(ref_times))
    runs = []
    while len(runs) < args.running:
        a, b = pool[rng.integers(len(pool), size=2)]
        if np.linalg.norm(a - b) > 0.02:
            runs.append(plan_problem(PlanProblem(tuple(a), tuple(b)), options, model))
    rows = []
    for case in range(args.cases):
        running = runs[rng.integers(len(runs))]
        kind = KINDS[case % len(KINDS)]
        prob = PlanProblem.from_dict(running.report.problem)
        splice = float(rng.uniform(0.1, 0.9) * running.trajectory.duration_s)
        goal = _new_goal(kind, prob, rng, pool, model)
        try:
            r = replan(running, splice, goal, options=options, model=model)
            rows.append({"case": case, "kind": kind, "method": r.method, "time_s": r.solve_time_s, "ratio": r.worst_command_ratio,
                         "duration_s": r.duration_s, "problem": r.problem, "ok": True})
        except Exception as exc:  # a failure is a figure too
            rows.append({"case": case, "kind": kind, "method": "failed", "time_s": float("nan"), "ratio": float("nan"),
                         "duration_s": float("nan"), "problem": None, "ok": False, "error": f"{type(exc).__name__}: {exc}"})
        if (case + 1) % 100 == 0:
            print(f"{case + 1} cases", file=sys.stderr, flush=True)
    ok = [r for r in rows if r["ok"]]
    times = np.array([r["time_s"] for r in ok])
    tolerance = options.checks.command_tolerance

    def pct(x: np.ndarray, q: float) -> float:
        return float(np.percentile(x, q)) * 1e3 if x.size else float("nan")

    out = {"search": args.search, "cases": len(rows), "failed": len(rows) - len(ok), "reference_cold_plan_ms": 1e3 * ref_s,
           "p50_ms": pct(times, 50), "p99_ms": pct(times, 99), "max_ms": pct(times, 100),
           "p50_over_reference": pct(times, 50) / (1e3 * ref_s), "p99_over_reference": pct(times, 99) / (1e3 * ref_s),
           "within_bound": int(sum(r["ratio"] <= 1.0 for r in ok)),
           "within_tolerance": int(sum(r["ratio"] <= 1 + tolerance for r in ok)),
           "worst_ratio": float(max(r["ratio"] for r in ok)) if ok else None, "by": {}}
    for key in ("method", "kind"):
        for value in sorted({r[key] for r in ok}):
            t = np.array([r["time_s"] for r in ok if r[key] == value])
            out["by"][f"{key}={value}"] = {"n": int(t.size), "p50_ms": pct(t, 50), "p99_ms": pct(t, 99)}
    # the gap to an independent high-resolution solve (the pipeline with refinement)
    gaps, no_reference = [], []
    precise = PlanOptions.of(crosscheck=False, plant_check=False)
    for r in ok[:: max(1, len(ok) // max(1, args.sample))][: args.sample]:
        best = _reference_duration(r["problem"], precise, model)
        if best is None:   # the reference could not plan it at any N: no figure, said so
            no_reference.append(r["case"])
            continue
        gaps.append((r["case"], r["kind"], r["method"], r["duration_s"] / best - 1.0))
    out["gap_sample"] = len(gaps)
    out["gap_no_reference"] = no_reference
    out["gap_max"] = float(max(g[-1] for g in gaps)) if gaps else None
    out["gap_median"] = float(np.median([g[-1] for g in gaps])) if gaps else None
    out["gap_over_0.3%"] = [list(g) for g in gaps if g[-1] > 0.003]
    errors = sorted({f'case {r["case"]}: {r["error"]}' for r in rows if not r["ok"]})[:5]
    out["over_bound"] = [[r["case"], r["method"], r["ratio"]] for r in ok if r["ratio"] > 1.0]
    out["errors"] = errors
    print(json.dumps(out, indent=2))
    out["rows"] = [{k: r[k] for k in ("case", "kind", "method", "time_s", "duration_s", "ratio")} for r in rows]
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
