"""The executor in real time, against the timer's own jitter; and tracking on the plant.

Part 1, real time at 1 kHz on the emulated Falcon (UsbFalcon over EmulatedFalconBackend: the
whole USB packet path and the SimPlant behind it, in this process). For each round:

- reference: a bare loop with the executor's deadline scheme (absolute deadlines, sleep then
  spin 0.3 ms) doing nothing but waiting (``timing.run_bare_loop``), as many ticks as the
  executor run; this is the timer's own jitter on this machine at this moment;
- the executor streaming a planned move (PD + feed-forward, workspace guard, watchdog,
  falcon log) through the emulated USB device.

Reported: share of missed deadlines (a tick starting more than one period late) and the
p50/p99/max tick start error of both, and the ratio executor/reference of p99.

Part 2, tracking error of plans on the simulated plant (SimDevice, as fast as possible,
pre-roll 0.8 s so that each move starts settled): the minimum-time planner's plans
(``planning.api.plan`` with ``PlanOptions.fast()``) of a few benchmark problems, at 800 Hz
and 1 kHz, and for comparison the quintic move between the same points (the executor's
test fixture; slower, so it tracks better).

Usage: ``python benchmarks/bench_executor.py [--rounds N] [--out results.json]``.
The machine is shared: run it with ``nice`` and trust ratios within a run.
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.execution.device_factory import open_device, read_position
from falcon_plan.execution.executor import Executor
from falcon_plan.planning.quintic import quintic_trajectory
from falcon_plan.timing import run_bare_loop
from falcon_plan.model.dynamics import FalconModel

PROBLEMS_DIR = Path(__file__).resolve().parents[1] / "problems"
TRACKING_PROBLEMS = ("across_x", "short_diagonal", "random_01", "random_02", "edge_to_edge_x")
"""Rest-to-rest problems without via points or payload."""
REALTIME_MOVES_M = ((0.02, 0.02, 0.0), (-0.02, -0.02, 0.0), (0.0, 0.02, -0.02), (0.0, -0.02, 0.02))
"""Moves of the real-time rounds, relative to where the device is (they alternate)."""
FAST_USB = dict(check_timeout_s=0.02, echo_timeout_s=0.05, reply_timeout_s=0.01)


def plan_move(start_m: Any, goal_m: Any, model: FalconModel) -> tuple[Any, str]:
    """(trajectory, method) of the minimum-time planner, fast options."""
    from falcon_plan.planning.api import plan
    from falcon_plan.planning.problem import PlanOptions

    result = plan(start_m, goal_m, PlanOptions.fast(), model)
    return result.trajectory, result.report.method


def realtime_rounds(model: FalconModel, rounds: int, log_dir: Path) -> dict[str, Any]:
    """Part 1: alternate the bare reference loop and a paced executor run, ``rounds`` times."""
    device = open_device("emulated", rate_hz=1000.0, model=model, **FAST_USB)
    rows = []
    with device:
        device.home(timeout_s=5.0)
        for r in range(rounds):
            start = read_position(device, model.params)
            goal = start + np.asarray(REALTIME_MOVES_M[r % len(REALTIME_MOVES_M)])
            traj, method = plan_move(start, goal, model)
            ex = Executor(device, model, 1000.0, log_dir / f"realtime_{r}.csv", pace=True,
                          preroll_s=0.8, settle_s=0.2)
            ticks = int(round((0.8 + traj.duration_s + 0.2) * 1000)) + 1
            bare = run_bare_loop(1000.0, ticks)
            report = ex.run(traj)
            rows.append({"round": r, "method": method, "status": report.status,
                         "reference": bare.to_dict(), "executor": report.to_dict()})
            print(f"  round {r}: bare p99 {bare.p99_us:7.1f} us, missed {bare.missed_deadlines}/{bare.ticks}"
                  f" | executor p99 {report.timing.p99_us:7.1f} us, missed {report.timing.missed_deadlines}/"
                  f"{report.timing.ticks} ({report.status}), |e|max {report.tracking.norm_max_mm:.3f} mm"
                  if report.tracking and report.timing else f"  round {r}: {report.status} {report.reason}",
                  file=sys.stderr)

    def pooled(side: str) -> dict[str, float]:
        if side == "reference":
            missed = sum(row["reference"]["missed_deadlines"] for row in rows)
            ticks = sum(row["reference"]["ticks"] for row in rows)
        else:
            missed = sum(row["executor"]["missed_deadlines"] for row in rows)
            ticks = sum(row["executor"]["ticks"] for row in rows)
        p99 = [row[side]["jitter_p99_us"] for row in rows if row[side]["jitter_p99_us"] is not None]
        p50 = [row[side]["jitter_p50_us"] for row in rows if row[side]["jitter_p50_us"] is not None]
        return {"missed_share": missed / ticks if ticks else 0.0, "missed": missed, "ticks": ticks,
                "p50_us_median": statistics.median(p50), "p99_us_median": statistics.median(p99),
                "p99_us_worst": max(p99)}

    ref, exe = pooled("reference"), pooled("executor")
    return {"rounds": rows, "reference": ref, "executor": exe,
            "p99_ratio_executor_over_reference": exe["p99_us_median"] / max(ref["p99_us_median"], 1e-9)}


def tracking_table(model: FalconModel) -> list[dict[str, Any]]:
    """Part 2: planned and quintic moves on the simulated plant at 800 Hz and 1 kHz."""
    rows = []
    for name in TRACKING_PROBLEMS:
        problem = json.loads((PROBLEMS_DIR / f"{name}.json").read_text())
        start, goal = np.asarray(problem["start_m"]), np.asarray(problem["goal_m"])
        planned, method = plan_move(start, goal, model)
        quintic = quintic_trajectory(start, goal, model)
        for rate in (800.0, 1000.0):
            for label, traj in ((method, planned), ("quintic", quintic)):
                device = open_device("sim", rate_hz=rate, model=model, start_m=start)
                with device:
                    device.home()
                    report = Executor(device, model, rate, preroll_s=0.8).run(traj)
                tr = report.tracking
                rows.append({"problem": name, "rate_hz": rate, "trajectory": label,
                             "duration_s": traj.duration_s, "status": report.status,
                             "counts_max": max(tr.counts_max), "counts_rms": max(tr.counts_rms),
                             "norm_max_mm": tr.norm_max_mm, "norm_rms_mm": tr.norm_rms_mm,
                             "final_mm": tr.final_mm})
                print(f"  {name:16s} {rate:6.0f} Hz {label:16s} T={traj.duration_s:.3f} s "
                      f"max {max(tr.counts_max):5.1f} counts, |e| max {tr.norm_max_mm:.3f} mm "
                      f"rms {tr.norm_rms_mm:.3f} mm", file=sys.stderr)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="real-time rounds (default 5)")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = parser.parse_args()
    model = FalconModel()
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-executor-") as tmp:
        print("part 1: real time, 1 kHz, emulated Falcon", file=sys.stderr)
        realtime = realtime_rounds(model, args.rounds, Path(tmp))
    print("part 2: tracking on the simulated plant", file=sys.stderr)
    tracking = tracking_table(model)
    results = {"machine": platform.platform(), "python": platform.python_version(),
               "runtime_s": time.perf_counter() - started, "realtime_1khz_emulated": realtime,
               "tracking_sim": tracking}
    ref, exe = realtime["reference"], realtime["executor"]
    print("\n| loop at 1 kHz | missed share | p50 [us] | p99 [us] (median of rounds) | p99 worst [us] |")
    print("|---|---|---|---|---|")
    for label, row in (("bare deadline loop (reference)", ref), ("executor, emulated Falcon", exe)):
        print(f"| {label} | {row['missed_share']:.4f} ({row['missed']}/{row['ticks']}) | "
              f"{row['p50_us_median']:.1f} | {row['p99_us_median']:.1f} | {row['p99_us_worst']:.1f} |")
    print(f"\np99 ratio executor / reference: {realtime['p99_ratio_executor_over_reference']:.2f}")
    print("\n| problem | rate | trajectory | T [s] | max err [counts] | max |e| [mm] | rms |e| [mm] |")
    print("|---|---|---|---|---|---|---|")
    for row in tracking:
        print(f"| {row['problem']} | {row['rate_hz']:.0f} | {row['trajectory']} | {row['duration_s']:.3f} | "
              f"{row['counts_max']:.1f} | {row['norm_max_mm']:.3f} | {row['norm_rms_mm']:.3f} |")
    if args.out is not None:
        args.out.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
