"""The executor in real time, against the timer's own jitter; and tracking on the plant.

Part 1, real time at 1 kHz on the emulated Falcon (UsbFalcon over EmulatedFalconBackend: the
whole USB packet path and the SimPlant behind it, in this process), without and with CPU
stress processes beside it (``--stress 0,1``: busy-looping processes, one keeps the other
core busy). For each round:

- reference: a bare loop with the executor's deadline scheme (absolute deadlines, sleep then
  spin 0.3 ms) doing nothing but waiting (``timing.run_bare_loop``), as many ticks as the
  executor run; this is the timer's own jitter on this machine at this moment;
- the executor streaming a planned move (its default controller, the time-varying LQR with
  the model feed-forward; workspace guard, watchdog, falcon log) through the emulated USB
  device.

Reported per stress level: share of missed deadlines (a tick starting more than one period
late), the p50/p99 tick start error of both, the ratio executor/reference of p99, and the
executor's per-tick work: ``work`` is the tick's own computation after the device I/O
(controller, forward kinematics and workspace guard, encoder-step check, falcon log row;
the issue's budget: p50 <= 150 us, p99 <= 400 us, <= 0.1 % missed deadlines) and ``busy``
adds the device exchange (here the emulated device's packet path and its simulated plant,
in this process); ``work, own CPU`` is the same span in the loop thread's CPU time, without
the time the driver's and the emulated device's threads held the interpreter meanwhile. ``--usb-timing`` also runs the threaded I/O against the emulator's USB
frame timing (then ``busy`` includes waiting for a status, so only ``work`` is the tick's).

Part 0, the tick's parts one by one (median µs per call over a path of readings, same
process, no device): the workspace guard's compiled path against its scalar Python path (the
reference: what every tick ran before), the falcon log's row, the PD law.

Part 2, tracking error of plans on the simulated plant (SimDevice, as fast as possible,
pre-roll 0.8 s so that each move starts settled): the minimum-time planner's plans
(``planning.api.plan`` with ``PlanOptions.fast()``) of a few benchmark problems, at 800 Hz
and 1 kHz, and for comparison the quintic move between the same points (the executor's
test fixture; slower, so it tracks better).

Usage: ``python benchmarks/bench_executor.py [--rounds N] [--stress 0,1] [--usb-timing]
[--skip-tracking] [--out results.json]``. The machine is shared: trust ratios within a run.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.errors import OutputError
from falcon_plan.execution.device_factory import open_device, read_position
from falcon_plan.fileio import check_writable, write_bytes
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


def tick_parts(model: FalconModel, log_dir: Path, calls: int = 5000) -> dict[str, float]:
    """Part 0: median µs per call of each part of a tick over ``calls`` readings along a
    slow random walk of the counts (a hold with noise)."""
    from falcon_plan.control import pd_law
    from falcon_plan.execution.safety import WorkspaceGuard
    from falcon_plan.falconlog import LogWriter
    from falcon_plan.model.kinematics import position_to_counts

    rng = np.random.default_rng(0)
    centre = position_to_counts(np.array([0.0, 0.0, 0.13]), model.params)
    counts = np.rint(centre + np.cumsum(rng.normal(0.0, 0.5, (calls, 3)), axis=0))
    ref = counts + 0.5

    def median_us(call) -> float:
        times = np.empty(calls)
        for i in range(calls):
            t0 = time.perf_counter()
            call(i)
            times[i] = time.perf_counter() - t0
        return float(np.median(times) * 1e6)

    compiled, scalar = WorkspaceGuard(model.params, model.limits), WorkspaceGuard(model.params, model.limits, compiled=False)
    writer = LogWriter(log_dir / "parts.csv", {"rate_hz": "1000"}, with_ref=True)
    zeros = np.zeros(3)
    try:
        out = {"guard_compiled_us": median_us(lambda i: compiled.check(counts[i])),
               "guard_scalar_us (reference)": median_us(lambda i: scalar.check(counts[i])),
               "log_row_us": median_us(lambda i: writer.write(i * 1e-3, counts[i], zeros, ref[i])),
               "pd_law_us": median_us(lambda i: pd_law(counts[i], counts[i - 1], zeros, ref[i], zeros, 10.0, 0.1,
                                                       0.27, 1000.0, 4096))}
    finally:
        writer.close()
    for name, value in out.items():
        print(f"  {name:28s} {value:7.1f}", file=sys.stderr)
    return out


@contextlib.contextmanager
def cpu_stress(processes: int):
    """``processes`` busy-looping Python processes for the duration (killed after)."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(processes)]
    try:
        time.sleep(0.2 if procs else 0.0)            # let them get going
        yield
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def realtime_rounds(model: FalconModel, rounds: int, log_dir: Path, usb_timing: bool = False) -> dict[str, Any]:
    """Part 1: alternate the bare reference loop and a paced executor run, ``rounds`` times
    (``usb_timing``: threaded I/O against the emulator's USB frame timing)."""
    from falcon_plan.devices.emulated import UsbTiming

    device = open_device("emulated", rate_hz=1000.0, model=model,
                         usb_timing=UsbTiming() if usb_timing else None, **FAST_USB)
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
            tm = report.timing
            print(f"  round {r}: bare p99 {bare.p99_us:7.1f} us, missed {bare.missed_deadlines}/{bare.ticks}"
                  f" | executor p99 {tm.p99_us:7.1f} us, missed {tm.missed_deadlines}/{tm.ticks}, work p50/p99 "
                  f"{tm.work_p50_us:.0f}/{tm.work_p99_us:.0f} us (CPU {tm.work_cpu_p50_us:.0f}/{tm.work_cpu_p99_us:.0f} us), "
                  f"busy p50/p99 {tm.busy_p50_us:.0f}/"
                  f"{tm.busy_p99_us:.0f} us ({report.status})"
                  if tm and tm.work_p50_us is not None else f"  round {r}: {report.status} {report.reason}",
                  file=sys.stderr)

    def pooled(side: str) -> dict[str, float]:
        missed = sum(row[side]["missed_deadlines"] for row in rows)
        ticks = sum(row[side]["ticks"] for row in rows)
        out = {"missed_share": missed / ticks if ticks else 0.0, "missed": missed, "ticks": ticks}
        for key in ("jitter_p50_us", "jitter_p99_us", "work_p50_us", "work_p99_us", "work_cpu_p50_us",
                    "work_cpu_p99_us", "busy_p50_us", "busy_p99_us"):
            values = [row[side].get(key) for row in rows if row[side].get(key) is not None]
            if values:
                out[key.replace("_us", "_us_median")] = statistics.median(values)
                out[key.replace("_us", "_us_worst")] = max(values)
        return out

    ref, exe = pooled("reference"), pooled("executor")
    return {"rounds": rows, "reference": ref, "executor": exe,
            "p99_ratio_executor_over_reference": exe["jitter_p99_us_median"] / max(ref["jitter_p99_us_median"], 1e-9)}


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
    parser.add_argument("--rounds", type=int, default=5, help="real-time rounds per stress level (default 5)")
    parser.add_argument("--stress", default="0,1",
                        help="CPU-stress processes beside the loop, one run per value (default 0,1)")
    parser.add_argument("--usb-timing", action="store_true",
                        help="also run the threaded I/O against the emulator's USB frame timing")
    parser.add_argument("--skip-tracking", action="store_true", help="skip part 2 (tracking on the plant)")
    parser.add_argument("--out", type=Path, default=None,
                        help="write the results as JSON to this file (a folder: bench_executor.json in it)")
    args = parser.parse_args()
    if args.out is not None:      # before the run: an output that cannot be written is an error
        args.out = args.out / "bench_executor.json" if args.out.is_dir() else args.out
        try:
            check_writable(args.out, "results JSON")
        except OutputError as exc:
            print(f"bench_executor: {exc}", file=sys.stderr)
            return 2
    model = FalconModel()
    started = time.perf_counter()
    realtime: dict[str, Any] = {}
    paths = [("instant", False)] + ([("usb_timing", True)] if args.usb_timing else [])
    with tempfile.TemporaryDirectory(prefix="bench-executor-") as tmp:
        print("part 0: the tick's parts", file=sys.stderr)
        parts = tick_parts(model, Path(tmp))
        for stress in (int(x) for x in args.stress.split(",")):
            for label, timed in paths:
                print(f"part 1: real time, 1 kHz, emulated Falcon ({label}), {stress} stress process(es)",
                      file=sys.stderr)
                with cpu_stress(stress):
                    realtime[f"{label}_stress{stress}"] = realtime_rounds(model, args.rounds, Path(tmp), timed)
    tracking = []
    if not args.skip_tracking:
        print("part 2: tracking on the simulated plant", file=sys.stderr)
        tracking = tracking_table(model)
    results = {"machine": platform.platform(), "python": platform.python_version(),
               "command": " ".join(sys.argv), "runtime_s": time.perf_counter() - started,
               "tick_parts_us": parts, "realtime_1khz_emulated": realtime, "tracking_sim": tracking}
    print("\n| tick part | median [us] |\n|---|---|")
    for name, value in parts.items():
        print(f"| {name} | {value:.1f} |")
    print("\n| loop at 1 kHz | missed share | start error p50 / p99 [us] | work p50 / p99 [us] | "
          "work, own CPU p50 / p99 [us] | busy p50 / p99 [us] |")
    print("|---|---|---|---|---|---|")
    for name, part in realtime.items():
        for label, row in ((f"{name}: bare deadline loop (reference)", part["reference"]),
                           (f"{name}: executor", part["executor"])):
            work = (f"{row['work_p50_us_median']:.0f} / {row['work_p99_us_median']:.0f}"
                    if "work_p50_us_median" in row else "-")
            cpu = (f"{row['work_cpu_p50_us_median']:.0f} / {row['work_cpu_p99_us_median']:.0f}"
                   if "work_cpu_p50_us_median" in row else "-")
            busy = (f"{row['busy_p50_us_median']:.0f} / {row['busy_p99_us_median']:.0f}"
                    if "busy_p50_us_median" in row else "-")
            print(f"| {label} | {row['missed_share']:.4f} ({row['missed']}/{row['ticks']}) | "
                  f"{row['jitter_p50_us_median']:.1f} / {row['jitter_p99_us_median']:.1f} | {work} | {cpu} | {busy} |")
    print("\n(medians over rounds; p99 ratio executor / reference: "
          + ", ".join(f"{name} {part['p99_ratio_executor_over_reference']:.2f}" for name, part in realtime.items())
          + ")")
    if tracking:
        print("\n| problem | rate | trajectory | T [s] | max err [counts] | max |e| [mm] | rms |e| [mm] |")
        print("|---|---|---|---|---|---|---|")
        for row in tracking:
            print(f"| {row['problem']} | {row['rate_hz']:.0f} | {row['trajectory']} | {row['duration_s']:.3f} | "
                  f"{row['counts_max']:.1f} | {row['norm_max_mm']:.3f} | {row['norm_rms_mm']:.3f} |")
    if args.out is not None:
        try:
            write_bytes(args.out, (json.dumps(results, indent=2) + "\n").encode(), "results JSON")
        except OutputError as exc:
            print(f"bench_executor: {exc}", file=sys.stderr)
            return 1
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
