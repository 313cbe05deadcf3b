"""Benchmark: warm starts from solved neighbours against cold starts, in the same run.

A stream of nearby goals (a user nudging the target) is planned twice with the fast options:
cold (``warm_start="none"``, the reference) and warm (``"neighbours"``). Prints the median
IPOPT iterations and solve times and their ratios, and the largest relative difference in
duration (it must be at the solver's tolerance).

    .venv/bin/python benchmarks/bench_warmstart.py [--goals 30] [--out result.json]
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from falcon_plan.commands.common import progress
from falcon_plan.planning import warmstart
from falcon_plan.planning.api import plan, warm_up
from falcon_plan.planning.problem import PlanOptions


def run(n_goals: int, seed: int) -> dict[str, float]:
    """Plan the same goal stream cold and warm; return medians and ratios."""
    warm_up()
    rng = np.random.default_rng(seed)
    start = np.array([0.0, 0.0, 0.12])
    goals = [start + np.array([0.03, 0.02, 0.02]) + rng.normal(0.0, 0.004, 3) for _ in range(n_goals)]
    stats: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for mode in ("none", "neighbours"):
        warmstart.NEIGHBOURS.clear()
        reports = [plan(start, g, PlanOptions.fast(warm_start=mode)).report.to_dict() for g in goals]
        stats[mode] = (np.array([r["solver_iterations"] for r in reports], float),
                       np.array([r["solve_time_s"] for r in reports]),
                       np.array([r["duration_s"] for r in reports]))
    cold, warm = stats["none"], stats["neighbours"]
    return {
        "goals": n_goals,
        "cold_median_iterations": float(np.median(cold[0])),
        "warm_median_iterations": float(np.median(warm[0])),
        "iterations_ratio_warm_over_cold": float(np.median(warm[0]) / np.median(cold[0])),
        "cold_median_solve_ms": 1e3 * float(np.median(cold[1])),
        "warm_median_solve_ms": 1e3 * float(np.median(warm[1])),
        "solve_time_ratio_warm_over_cold": float(np.median(warm[1]) / np.median(cold[1])),
        "max_duration_rel_diff": float(np.max(np.abs(warm[2] / cold[2] - 1.0))),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--goals", type=int, default=30)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", help="write the figures as JSON here")
    args = parser.parse_args()
    with progress(f"planning {args.goals} goals cold and warm-started"):
        result = run(args.goals, args.seed)
    for key, value in result.items():
        print(f"{key:34s} {value:.4g}")
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(result, handle, indent=2)


if __name__ == "__main__":
    main()
