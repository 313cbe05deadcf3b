"""Speed of the simulated plant: simulated seconds per wall-clock second at 800 Hz.

Workload: the paper's step experiment on the nominal plant (PD kp 10, kd 0.1, a step of a few
hundred counts that saturates the commands), SECONDS simulated seconds per round. Rows:

- ``step+pd``: the per-step API as a device loop uses it, ``EncoderPD.update`` then
  ``SimPlant.step`` per period (compiled C per period, Python in between);
- ``step``: ``SimPlant.step`` alone, replaying the commands recorded by ``step+pd``;
- ``run_open_loop``: the batched open-loop path on the same commands;
- ``run_pd``: the batched closed loop (PD compiled into the loop);
- reference ``casadi-vm step``: the same per-period RK4 Function evaluated by CasADi's
  virtual machine (``SimPlant(compile=False).step``), the plant without code generation.

Each row reports the median over rounds of the real-time factor (simulated s / wall s) and
microseconds per control period, and its speed-up over the reference measured in this run.
The compiled functions are built (or loaded from the cache) before timing.

Usage: ``python benchmarks/bench_plant.py [--rounds N] [--seconds S] [--out results.json]``.
The machine is shared: run it with ``nice`` and trust ratios within a run.
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time
from typing import Any, Callable

import numpy as np

from falcon_plan.commands.common import progress
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import position_to_counts
from falcon_plan.control import EncoderPD
from falcon_plan.sim.plant import SimPlant

RATE_HZ = 800.0
START_M = np.array([0.0, 0.0, 0.12])
GOAL_M = np.array([0.02, 0.015, 0.14])


def _reference_counts(periods: int, model: FalconModel) -> np.ndarray:
    ref = np.tile(position_to_counts(START_M, model.params), (periods, 1))
    ref[periods // 8:] = position_to_counts(GOAL_M, model.params)
    return ref


def _timed(fn: Callable[[], Any]) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def run(rounds: int, seconds: float) -> dict[str, Any]:
    model = FalconModel()
    periods = int(round(seconds * RATE_HZ))
    ref = _reference_counts(periods, model)
    fast, vm = SimPlant(model, rate_hz=RATE_HZ), SimPlant(model, rate_hz=RATE_HZ, compile=False)
    if not fast.compiled:
        print("warning: no C compiler; the 'compiled' rows run uncompiled", file=sys.stderr)
    recorded: list[np.ndarray] = []

    def step_pd() -> None:
        fast.reset(START_M)
        pd, n = EncoderPD(RATE_HZ), fast.counts
        recorded.clear()
        for k in range(periods):
            tc = pd.update(n, ref[k])
            recorded.append(tc)
            n = fast.step(tc)

    step_pd()  # warm-up, and the commands for the replays
    commands = np.array(recorded, dtype=float)

    def step_only(plant: SimPlant) -> Callable[[], None]:
        def go() -> None:
            plant.reset(START_M)
            for tc in commands:
                plant.step(tc)
        return go

    def open_loop() -> None:
        fast.reset(START_M)
        fast.run_open_loop(commands)

    def batched_pd() -> None:
        fast.reset(START_M)
        fast.run_pd(EncoderPD(RATE_HZ), ref)

    open_loop()
    batched_pd()  # build / load the batched functions before timing
    rows: dict[str, Callable[[], None]] = {
        "step+pd": step_pd, "step": step_only(fast), "run_open_loop": open_loop,
        "run_pd": batched_pd, "casadi-vm step": step_only(vm)}
    times: dict[str, list[float]] = {name: [] for name in rows}
    for _ in range(rounds):
        for name, fn in rows.items():
            times[name].append(_timed(fn))
    ref_s = statistics.median(times["casadi-vm step"])
    results = {}
    for name, samples in times.items():
        wall = statistics.median(samples)
        results[name] = {"realtime_factor": seconds / wall, "us_per_period": wall / periods * 1e6,
                         "speedup_vs_casadi_vm": ref_s / wall, "wall_s": samples}
    return {"benchmark": "plant", "rate_hz": RATE_HZ, "simulated_s_per_round": seconds,
            "rounds": rounds, "compiled": fast.compiled, "rows": results,
            "reference": "casadi-vm step (same RK4 Function, uncompiled)",
            "machine": {"python": platform.python_version(), "processor": platform.processor(),
                        "platform": platform.platform()}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5, help="timed rounds per row (default 5)")
    parser.add_argument("--seconds", type=float, default=2.0,
                        help="simulated seconds per round (default 2)")
    parser.add_argument("--out", default=None, help="write the results as JSON here")
    args = parser.parse_args(argv)
    with progress("timing the compiled and the uncompiled plant"):
        result = run(args.rounds, args.seconds)
    print(f"plant at {RATE_HZ:g} Hz, {args.seconds:g} simulated s per round, median of "
          f"{args.rounds} rounds (compiled: {result['compiled']})")
    print(f"{'row':16s} {'x real time':>12s} {'us/period':>10s} {'vs casadi-vm':>13s}")
    for name, row in result["rows"].items():
        print(f"{name:16s} {row['realtime_factor']:12.1f} {row['us_per_period']:10.1f} "
              f"{row['speedup_vs_casadi_vm']:12.1f}x")
    if args.out:
        with open(args.out, "w") as handle:
            json.dump(result, handle, indent=2)
            handle.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
