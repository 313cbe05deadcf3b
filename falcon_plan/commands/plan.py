"""``falcon-plan plan``: plan a minimum-time move and print its report.

Example: ``falcon-plan plan --from 0,0,0.12 --to 0.03,0.02,0.14 --tc-max 2500 --out move.json``.
Points are x,y,z in metres (base frame: x right, y up, z toward the user). ``--out FILE``
also writes the trajectory (JSON) and, next to it, a plot (FILE with .png; ``--plot PNG``
chooses another name). The report has the dense re-check, the refinement (converged duration
and the plan's gap to it) and a run on the simulated plant; ``--crosscheck`` adds the toppra
and ruckig reference durations (about half a second more: toppra loads matplotlib).
``--fast`` skips the refinement and the plant run too (the service's fast path). ``--limit device`` plans with the device's speed-dependent
command limit (2500 at rest up to 4096 in motion) instead of ``--tc-max``;
``--feedback-reserve`` keeps command units free for the executor's feedback. ``--model FILE``
plans with a model file (e.g. the corrected model written by ``discrepancy`` or
``calibrate``): its friction, payload, tilt and gain enter the constraints; the report's notes
say which effects cannot and what is done instead.
"""
from __future__ import annotations

import argparse
from typing import Any

from falcon_plan.commands import common
from falcon_plan.planning.bound import LIMIT_KINDS
from falcon_plan.planning.problem import (DEFAULT_INTERVALS, INTERVALS_PER_VIA, PROFILES, CommandLimits, PlanOptions,
                                          SolverSettings, Transcription)


def register(subparsers: Any) -> None:
    """Add the ``plan`` subcommand to ``subparsers`` (the ``falcon-plan`` parser's
    subcommands)."""
    parser = subparsers.add_parser("plan", help="plan a minimum-time move and print its report",
                                   description=__doc__)
    common.add_point_option(parser, "--from", "--start", dest="start", required=True, help="start point [m]")
    common.add_point_option(parser, "--to", "--goal", dest="goal", required=True, help="goal point [m]")
    common.add_point_option(parser, "--via", dest="via", repeat=True, help="a via point [m] (repeatable, in order)")
    parser.add_argument("--tc-max", type=float, default=CommandLimits.tc_max,
                        help="constant command limit [command units, the device's 16-bit motor command], "
                             "<= 4096, with --limit constant; the static saturation is 2500 (default 2500)")
    parser.add_argument("--limit", choices=LIMIT_KINDS, default=CommandLimits.limit,
                        help="command bound: constant (--tc-max) or device (the device's speed-dependent "
                             f"limit, 2500 at rest to 4096 in motion); default {CommandLimits.limit}")
    parser.add_argument("--feedback-reserve", type=float, default=CommandLimits.feedback_reserve,
                        help="command units kept free for feedback, subtracted from the limit "
                             f"(default {CommandLimits.feedback_reserve:g})")
    parser.add_argument("--profile", choices=PROFILES, default=Transcription.profile,
                        help=f"acceleration on each interval (default {Transcription.profile})")
    parser.add_argument("--payload-kg", type=float, default=0.0, help="payload at the end effector [kg]")
    parser.add_argument("--intervals", type=int, default=None,
                        help=f"transcription intervals N (default {DEFAULT_INTERVALS}, plus "
                             f"{INTERVALS_PER_VIA} per via point)")
    parser.add_argument("--time-budget", type=float, default=SolverSettings.time_budget_s,
                        help="optimiser time budget [s]; past it the ruckig fallback is returned")
    parser.add_argument("--fast", action="store_true",
                        help="skip cross-checks, refinement and plant run")
    parser.add_argument("--crosscheck", action="store_true",
                        help="also compute the toppra (same path, straight line) and ruckig reference durations")
    common.add_json_option(parser)
    parser.add_argument("--out", type=common.output_file_as(".json"), metavar="FILE.json",
                        help="write the trajectory (JSON) to this file, and its plot next to it")
    parser.add_argument("--plot", type=common.output_file_as(".png"), metavar="FILE.png",
                        help="write a plot of the plan (position, velocity, leg angles and speeds, "
                             "commands against the limit, workspace margins)")
    common.add_model_option(parser, "model file to plan with (default: nominal acra2009)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Plan and print; exit code 0 on success (errors are FalconPlanErrors: exit 2)."""
    from falcon_plan.model.modelfile import load_model
    from falcon_plan.plots import plot_plan

    make = PlanOptions.fast if args.fast else PlanOptions.of
    options = make(tc_max=args.tc_max, n_intervals=args.intervals, time_budget_s=args.time_budget,
                   limit=args.limit, feedback_reserve=args.feedback_reserve, profile=args.profile,
                   crosscheck=args.crosscheck)
    model = load_model(args.model)
    result = common.plan_with_progress(args.start, args.goal, options, model, via_m=args.via,
                                       payload_kg=args.payload_kg)
    written = []
    if args.out is not None:
        written.append(common.write_trajectory(args.out, result.trajectory))
    plot = common.plot_path(args.plot, args.out)
    if plot is not None:
        written.append(plot_plan(result.trajectory, plot, model=model, tc_max=options.limits.tc_max))
    if args.json:
        common.print_json(result.report.to_dict())
    else:
        print(result.report.summary())
        if written:
            print("wrote " + ", ".join(map(str, written)))
    return 0
