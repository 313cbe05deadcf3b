"""02: a minimum-time move, its report and cross-checks, and a plot of the motion.

Run: .venv/bin/python examples/02_plan_point_to_point.py [--out DIR]   (default: out/examples)
"""
from __future__ import annotations

import argparse
from pathlib import Path

import falcon_plan as fp

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "out" / "examples"


def main(out_dir: Path) -> None:
    # --- problem: points in metres, base frame --------------------------------------------
    start_m, goal_m = (0.0, 0.0, 0.12), (0.03, 0.02, 0.14)
    model = fp.FalconModel()                     # acra2009 parameters, nominal effects
    options = fp.PlanOptions.of(tc_max=2500)        # every check: toppra, ruckig, N->2N, plant run

    # --- solve ------------------------------------------------------------------------------
    result = fp.plan(start_m, goal_m, options, model)
    print(result)                                # one line: method, duration, trajectory
    print(result.report.summary())

    # --- the picture: position, velocity, leg angles and speeds, commands, margins ----------
    out_dir.mkdir(parents=True, exist_ok=True)
    png = fp.plot_plan(result.trajectory, out_dir / "02_plan.png", model=model, tc_max=options.limits.tc_max)
    print(f"wrote {png}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for the PNG")
    main(parser.parse_args().out)
