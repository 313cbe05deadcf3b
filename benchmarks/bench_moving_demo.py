"""The moving-target demo through the service (issue 24): a preempting goal every 50 ms on a
20 mm circle, each spliced into the running motion (``demo --moving-target``). Per run: goals,
executions (1: the run never ended between goals), splices taken (of them re-offered late
plans), the replan latency p50 / p99 of the planned splices [ms] (the coordinator's: from
choosing the splice tick to the prepared offer), the replan methods, and how far behind the
target the device stayed (mean, max [mm]). The latencies depend on the machine's load: run it
quiet and beside a CPU-stress process (``python3 -c "while True: pass" &``) to compare.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_moving_demo.py --runs 3 --seconds 2.5
"""
from __future__ import annotations

import argparse
import io
import json
import logging

import numpy as np

from service.commands.demo import run_moving_demo


def one_run(seconds: float) -> dict:
    """One demo of ``seconds`` [s] of goals: its figures (module docstring)."""
    out = io.StringIO()
    code = run_moving_demo(seconds, timeout_s=120, out=out, as_json=True, plot=None)
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
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    runs = [one_run(args.seconds) for _ in range(args.runs)]
    for r in runs:
        print(json.dumps(r))

    def med(key: str) -> float:
        return float(np.median([r[key] for r in runs if r[key] is not None]))
    print(f"median of {len(runs)}: splices {med('splices'):.0f} of {runs[0]['goals']} goals, replan latency p50 "
          f"{med('p50_ms'):.0f} ms, p99 {med('p99_ms'):.0f} ms, lag mean {med('lag_mean_mm'):.1f} mm, "
          f"max {med('lag_max_mm'):.1f} mm; runs ok {sum(r['ok'] and r['executions'] == 1 for r in runs)}/{len(runs)}")


if __name__ == "__main__":
    main()
