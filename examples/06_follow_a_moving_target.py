"""06: follow a target that moves on a circle, plan by plan, on the simulated Falcon.

The target is sampled at 20 Hz; each sample is a new goal for the running motion: a plan from
the running reference's state a little ahead, spliced in continuous in position and velocity
(falcon_plan.moving_target, falcon_plan.execution.splice). Prints how far behind the target
the device stays and plots the target, the spliced plans and the executed path.

Run: .venv/bin/python examples/06_follow_a_moving_target.py [--out DIR] [--seconds S]   (default: out/examples, 4 s)
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from falcon_plan.model.kinematics import counts_to_position
from falcon_plan.moving_target import circle_target, follow_target, plot_moving_target

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "out" / "examples"


def main(out_dir: Path, seconds: float) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    home = counts_to_position(np.zeros(3))
    # a 20 mm circle about the home point in the plane facing the user, once every 2 s
    run = follow_target(circle_target(home, radius_m=0.02, period_s=2.0), duration_s=seconds, update_hz=20.0)
    taken = run.taken()
    lag = run.lag()
    print(f"status: {run.report.status}; {len(run.target_m)} target samples, {len(taken)} plans spliced in")
    print(f"largest splice jump: position {max((s['position_jump_counts'] for s in taken), default=0):.2g} counts, "
          f"velocity {max((s['velocity_jump_counts_s'] for s in taken), default=0):.2g} counts/s")
    latencies = [o["latency_ms"] for o in run.outcomes if "latency_ms" in o]
    print(f"replan latency p50 {np.median(latencies):.0f} ms (budget {run.outcomes[-1].get('budget_ms', float('nan')):.0f} ms)")
    print(f"behind the target: mean {lag['distance_mean_mm']:.1f} mm, max {lag['distance_max_mm']:.1f} mm, "
          f"about {1e3 * lag['time_lag_s']:.0f} ms")
    print(f"plot: {plot_moving_target(run, out_dir / '06_moving_target.png')}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder")
    parser.add_argument("--seconds", type=float, default=4.0, help="how long the target moves [s]")
    args = parser.parse_args()
    main(args.out, args.seconds)
