"""The figure behind the switching-time planner: commands of minimum-time plans are bang-bang.

For four benchmark problems (via_over_top: one switch more than equations) it plots each
leg's command [command units] against time normalised by the duration: the 192-interval transcription (lines), the default 24-interval
transcription (dots) and the switching-time plan (dashed). Writes
``docs/figures/bang-bang.png`` (or ``--out``) and prints the durations.

Usage: ``python benchmarks/plot_switching.py [--out PNG]``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from falcon_plan.planning.api import default_model, plan_problem  # noqa: E402
from falcon_plan.planning.min_time import solve_min_time  # noqa: E402
from falcon_plan.planning.transcription import MinTimeSettings  # noqa: E402
from falcon_plan.planning.problem import PlanOptions, PlanProblem  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
NAMES = ("across_diagonal", "short_x", "via_depth", "via_over_top")
KEYS = ("start_m", "goal_m", "start_velocity_m_s", "goal_velocity_m_s", "via_m", "payload_kg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "bang-bang.png")
    args = parser.parse_args()
    model = default_model()
    fig, axes = plt.subplots(len(NAMES), 1, figsize=(9, 3.2 * len(NAMES)), sharex=True)
    for ax, name in zip(axes, NAMES):
        spec = json.loads((ROOT / "problems" / f"{name}.json").read_text())
        problem = PlanProblem(**{k: spec[k] for k in KEYS if k in spec})
        options = PlanOptions.fast(tc_max=float(spec["tc_max"]), refine=True)
        bound = options.command_bound(model.params)
        fine = solve_min_time(model, problem, bound, MinTimeSettings(192))
        coarse = solve_min_time(model, problem, bound, MinTimeSettings(options.intervals_for(problem)))
        plan_problem(problem, options, model)   # once to load (or compile) the kernels
        exact = plan_problem(problem, options, model)
        for leg, colour in enumerate(("C0", "C1", "C2")):
            ax.plot(fine.trajectory.t_s / fine.duration_s, fine.trajectory.commands[:, leg], "-", color=colour,
                    lw=2.5, alpha=0.35, label=f"leg {leg}, N=192" if leg == 0 else None)
            ax.plot(coarse.trajectory.t_s / coarse.duration_s, coarse.trajectory.commands[:, leg], "o",
                    color=colour, ms=3, label="N=24 nodes" if leg == 0 else None)
            t = exact.trajectory.t_s / exact.trajectory.duration_s
            ax.plot(t, exact.trajectory.commands[:, leg], "--", color=colour, lw=1,
                    label="switching-time plan" if leg == 0 else None)
        gap24 = 100 * (coarse.duration_s / fine.duration_s - 1)
        gap = 100 * (exact.report.duration_s / fine.duration_s - 1)
        ax.set_title(f"{name}: duration N=192 {1e3 * fine.duration_s:.3f} ms; against it N=24 {gap24:+.3f} %,\n"
                     f"switching-time plan {gap:+.4f} % (planned in {1e3 * exact.report.total_time_s:.0f} ms)",
                     fontsize=10)
        ax.set_ylabel("command Tc [units]")
        ax.grid(alpha=0.3)
        print(f"{name}: N=192 {fine.duration_s:.6f} s, N=24 {gap24:+.3f} %, switching {gap:+.4f} %, "
              f"report: {exact.report.switching and exact.report.switching['iterations']} Newton iterations")
    axes[0].legend(loc="lower right", fontsize=8)
    axes[-1].set_xlabel("t / T")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
