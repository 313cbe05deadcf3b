"""``falcon-plan simulate``: experiments on the simulated plant.

``falcon-plan simulate step --from X,Y,Z --to X,Y,Z [--rate 800] [--duration 1.5]
[--out DIR] [--effects JSON]`` runs the paper's Section 6 step experiment
(:mod:`falcon_plan.sim.step`) and writes to DIR: ``step_log.csv`` (falcon log),
``step_plot.png`` (counts and commands, like the paper's Figure 9) and ``step_summary.json``;
it prints a short summary. Points are in metres, base frame.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from falcon_plan.commands import common


def register(subparsers: Any) -> None:
    """Add the ``simulate`` subcommand (with its ``step`` experiment) to ``subparsers`` (the
    ``falcon-plan`` parser's subcommands)."""
    parser = subparsers.add_parser("simulate", help="experiments on the simulated plant",
                                   description=__doc__)
    sub = parser.add_subparsers(dest="experiment", metavar="EXPERIMENT")
    sub.required = True
    step = sub.add_parser("step", help="the paper's Section 6 PD step experiment, simulated",
                          description="The paper's Section 6 step experiment on the simulated plant: the "
                                      "validation PD holds START, the reference steps to GOAL; writes "
                                      "step_log.csv, step_plot.png and step_summary.json to --out.")
    common.add_point_option(step, "--from", "--start", dest="start", required=True, help="start point [m]")
    common.add_point_option(step, "--to", "--goal", dest="goal", required=True, help="goal point [m]")
    common.add_rate_option(step)
    step.add_argument("--duration", type=common.positive_float, default=1.5, help="total time [s]")
    step.add_argument("--step-at", type=common.positive_float, default=0.25,
                      help="time of the reference step [s]")
    step.add_argument("--out", type=Path, default=Path("."), metavar="DIR", help="output folder")
    step.add_argument("--effects", default=None,
                      help=common.EFFECTS_HELP.format(fields=common.effect_fields()).replace("%", "%%"))
    step.add_argument("--params", default="acra2009",
                      help="parameter set: acra2009, libnifalcon or a .json file")
    common.add_model_option(step, "model file: the simulated device is that model (parameters and effects; "
                                  "--effects, if given, replaces its effects); overrides --params")
    common.add_json_option(step)
    step.set_defaults(func=run_step)


def run_step(args: argparse.Namespace) -> int:
    """Run the step experiment and write its outputs; returns the exit code."""
    from falcon_plan.falconlog import write_log
    from falcon_plan.fileio import make_folder
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import get_params
    from falcon_plan.sim.step import plot_step, run_step_experiment

    from falcon_plan.model.modelfile import load_model

    if args.model is not None:
        loaded = load_model(args.model)
        model = FalconModel(loaded.params)
        effects = loaded.effects if args.effects is None else common.load_effects(args.effects)
    else:
        model = FalconModel(get_params(args.params))
        effects = common.load_effects(args.effects)
    result = run_step_experiment(args.start, args.goal, rate_hz=args.rate, duration_s=args.duration,
                                 step_at_s=args.step_at, effects=effects, model=model)
    out = make_folder(args.out)
    write_log(out / "step_log.csv", result.log)
    plot_step(result, out / "step_plot.png")
    common.write_json(out / "step_summary.json", result.to_dict(), "summary")
    if args.json:
        common.print_json(result.to_dict())
        return 0
    print(result.summary())
    print(f"wrote {out / 'step_log.csv'}, {out / 'step_plot.png'}, {out / 'step_summary.json'}")
    return 0
