"""The moving-target demo through the service (issue 24): a preempting goal every 50 ms on a
20 mm circle, each spliced into the running motion (``demo --moving-target``). Per run: goals,
executions (1: the run never ended between goals), splices taken (of them re-offered late
plans), the replan latency p50 / p99 of the planned splices [ms] (the coordinator's: from
choosing the splice tick to the prepared offer), the replan methods, and how far behind the
target the device stayed (mean, max [mm]). The latencies depend on the machine's load: run it
quiet and beside a CPU-stress process (``python3 -c "while True: pass" &``) to compare.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_moving_demo.py --runs 3 --seconds 2.5 [--reference]

``--reference`` runs each demo also with the planner's default replan options (the search for
the shortest extremal, a 5 s optimiser budget) in place of the demo's
(:data:`falcon_plan.moving_target.FOLLOW_OPTIONS`), in turn, for a comparison in one run.
"""
from __future__ import annotations

import argparse
import io
import json
import logging

import numpy as np

from service.commands.demo import run_moving_demo


def one_run(seconds: float, goal_options: dict | None = None) -> dict:
    """One demo of ``seconds`` [s] of goals planned with ``goal_options`` (None: the demo's):
    its figures (module docstring)."""
    out = io.StringIO()
    code = run_moving_demo(seconds, timeout_s=120, out=out, as_json=True, plot=None, goal_options=goal_options)
    summary = json.loads(out.getvalue())["summary"]
    lag = summary.get("lag", {})
    return {"ok": code == 0, "goals": summary["goals"], "executions": summary["executions"],
            "statuses": summary["statuses"], "splices": summary["splices_taken"], "reused": summary["splices_reused"],
            "p50_ms": summary["replan_latency_p50_ms"], "p99_ms": summary["replan_latency_p99_ms"],
            "methods": summary["methods"], "lag_mean_mm": lag.get("distance_mean_mm"),
            "lag_max_mm": lag.get("distance_max_mm")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=2.5, help="how long the target moves [s]")
    parser.add_argument("--reference", action="store_true",
                        help="also run each demo with the planner's default replan options (the reference), in turn")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    kinds = {"demo": None, **({"default options": {}} if args.reference else {})}
    runs: dict[str, list[dict]] = {kind: [] for kind in kinds}
    for _ in range(args.runs):
        for kind, goal_options in kinds.items():
            runs[kind].append(one_run(args.seconds, goal_options))
            print(kind, json.dumps(runs[kind][-1]))
    for kind, done in runs.items():
        def med(key: str) -> float:
            return float(np.median([r[key] for r in done if r[key] is not None]))
        print(f"{kind}, median of {len(done)}: splices {med('splices'):.0f} of {done[0]['goals']} goals, replan latency "
              f"p50 {med('p50_ms'):.0f} ms, p99 {med('p99_ms'):.0f} ms, lag mean {med('lag_mean_mm'):.1f} mm, "
              f"max {med('lag_max_mm'):.1f} mm; runs ok {sum(r['ok'] and r['executions'] == 1 for r in done)}/{len(done)}")


if __name__ == "__main__":
    main()
