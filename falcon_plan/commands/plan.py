"""``falcon-plan plan``: plan a minimum-time move and print its report.

Example: ``falcon-plan plan --from 0,0,0.12 --to 0.03,0.02,0.14 --tc-max 2500 --json``.
Points are x,y,z in metres (base frame: x right, y up, z toward the user). ``--out FILE``
also writes the trajectory (JSON). ``--fast`` skips the cross-checks, the 2N refinement and
the plant run (the service's fast path). ``--model FILE`` plans with a model file (e.g. the
corrected model written by ``discrepancy`` or ``calibrate``): its friction, payload, tilt and
gain enter the constraints; the report's notes say which effects cannot and what is done.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from falcon_plan.planning.problem import PlanOptions


def _point(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected x,y,z in metres, got {text!r}")
    try:
        x, y, z = (float(p) for p in parts)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected three numbers x,y,z, got {text!r}") from exc
    return (x, y, z)


def register(subparsers: Any) -> None:
    """Add the ``plan`` subcommand."""
    parser = subparsers.add_parser("plan", help="plan a minimum-time move and print its report",
                                   description=__doc__.splitlines()[0])
    parser.add_argument("--from", dest="start", required=True, type=_point, metavar="X,Y,Z",
                        help="start point [m]")
    parser.add_argument("--to", dest="goal", required=True, type=_point, metavar="X,Y,Z",
                        help="goal point [m]")
    parser.add_argument("--via", action="append", type=_point, default=[], metavar="X,Y,Z",
                        help="a via point [m] (repeatable, in order)")
    parser.add_argument("--tc-max", type=float, default=2500.0, help="command limit (default 2500, <= 4096)")
    parser.add_argument("--payload-kg", type=float, default=0.0, help="payload at the end effector [kg]")
    parser.add_argument("--intervals", type=int, default=PlanOptions.n_intervals,
                        help=f"transcription intervals N (default {PlanOptions.n_intervals})")
    parser.add_argument("--time-budget", type=float, default=PlanOptions.time_budget_s,
                        help="optimiser time budget [s]; past it the ruckig fallback is returned")
    parser.add_argument("--fast", action="store_true",
                        help="skip cross-checks, refinement and plant run")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--out", type=Path, help="write the trajectory JSON to this file")
    parser.add_argument("--model", type=Path, default=None,
                        help="model file (JSON) to plan with (default: nominal acra2009)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Plan and print; exit code 0 on success (errors are FalconPlanErrors: exit 2)."""
    from falcon_plan.model.modelfile import load_model
    from falcon_plan.planning.api import plan

    make = PlanOptions.fast if args.fast else PlanOptions
    options = make(tc_max=args.tc_max, n_intervals=args.intervals, time_budget_s=args.time_budget)
    result = plan(args.start, args.goal, options, load_model(args.model), via_m=args.via,
                  payload_kg=args.payload_kg)
    if args.out is not None:
        result.trajectory.to_json(args.out)
    if args.json:
        json.dump(result.report.to_dict(), sys.stdout, indent=2)
        print()
    else:
        print(result.report.summary())
    return 0
