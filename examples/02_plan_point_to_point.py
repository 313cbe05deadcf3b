"""02: a minimum-time move, its report and cross-checks, and a plot of the motion.

Run: .venv/bin/python examples/02_plan_point_to_point.py [--out plan.png]
"""
from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from falcon_plan.planning.api import default_model, plan
from falcon_plan.planning.problem import PlanOptions


def main(out_png: str) -> None:
    # --- problem ----------------------------------------------------------------------------
    start_m, goal_m = (0.0, 0.0, 0.12), (0.03, 0.02, 0.14)
    options = PlanOptions(tc_max=2500)           # every check: toppra, ruckig, N->2N, plant run

    # --- solve ------------------------------------------------------------------------------
    result = plan(start_m, goal_m, options)
    print(result.report.summary())

    # --- the motion, sampled at the device rate ---------------------------------------------
    samples = result.trajectory.sample(1000.0, default_model())   # commands from the model
    fig, axes = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
    axes[0].plot(1e3 * samples.t_s, 1e3 * samples.position_m)
    axes[0].set_ylabel("position [mm]")
    axes[1].plot(1e3 * samples.t_s, samples.velocity_m_s)
    axes[1].set_ylabel("velocity [m/s]")
    axes[2].plot(1e3 * samples.t_s, samples.commands)
    axes[2].axhline(options.tc_max, ls=":", c="k")
    axes[2].axhline(-options.tc_max, ls=":", c="k")
    axes[2].set_ylabel("feed-forward Tc")
    axes[2].set_xlabel("time [ms]")
    axes[0].legend(["x", "y", "z"])
    axes[2].legend(["leg 0", "leg 1", "leg 2"])
    fig.suptitle(f"minimum-time move: {1e3 * result.report.duration_s:.1f} ms")
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    print(f"wrote {out_png}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="plan.png", help="PNG to write")
    main(parser.parse_args().out)
