"""The safe stop's cost (issue 24 item 3): computing the brake (plan_brake) and the controller's
tail (the LQR's stationary gains at the stop, Controller.splice) at many cancel ticks of a
planned move, against a reference timed in the same run (one 800-sample LQR design: what
Executor.prepare does before every run). A paced loop at 800 Hz has 1.25 ms per tick.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_brake.py --repeat 20
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.execution.braking import STOP_HOLD_S, plan_brake
from falcon_plan.execution.executor import Executor
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import counts_to_position
from falcon_plan.planning.api import plan_problem
from falcon_plan.planning.problem import PlanOptions, PlanProblem


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args(argv)
    model = FalconModel()
    home = counts_to_position(np.zeros(3))
    plan = plan_problem(PlanProblem(tuple(home), tuple(home + [0.03, -0.02, 0.01])), PlanOptions.fast(), model)
    with SimDevice(model=model, rate_hz=800.0) as dev:
        ex = Executor(dev, model, preroll_s=0.05)
        s = ex.prepare(plan.trajectory)
        c = ex.controller
        ticks = np.arange(40, 40 + int(plan.trajectory.duration_s * 800), 5)
        brake_s, tail_s, ref_s = [], [], []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            c.schedule(s.ref_counts + 1e-6 * len(ref_s), model)  # a fresh design (not cached)
            ref_s.append(time.perf_counter() - t0)
            for k in ticks:
                t0 = time.perf_counter()
                b = plan_brake(s.ref_counts, s.position_m, s.velocity_m_s, int(k), model, c.feedforward_effects,
                               800.0, c.feedforward_lead_samples, int(STOP_HOLD_S * 800))
                t1 = time.perf_counter()
                c.splice_tail(s.tracker, int(k), b.ref_counts, b.feedforward, model)
                brake_s.append(t1 - t0)
                tail_s.append(time.perf_counter() - t1)
    total = np.array(brake_s) + np.array(tail_s)
    ms = lambda x, q: float(np.percentile(x, q)) * 1e3  # noqa: E731
    out = {"samples": int(total.size), "brake_p50_ms": ms(brake_s, 50), "tail_p50_ms": ms(tail_s, 50),
           "total_p50_ms": ms(total, 50), "total_p99_ms": ms(total, 99), "total_min_ms": ms(total, 0),
           "reference_design_p50_ms": ms(ref_s, 50), "total_p50_over_reference": ms(total, 50) / ms(ref_s, 50)}
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
