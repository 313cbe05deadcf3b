"""``falcon-plan plan``: plan a minimum-time move and print its report.

Example: ``falcon-plan plan --from 0,0,0.12 --to 0.03,0.02,0.14 --tc-max 2500 --json``.
Points are x,y,z in metres (base frame: x right, y up, z toward the user). ``--out FILE``
also writes the trajectory (JSON). ``--fast`` skips the cross-checks, the 2N refinement and
the plant run (the service's fast path). ``--limit device`` plans with the device's
speed-dependent command limit (2500 at rest up to 4096 in motion) instead of ``--tc-max``;
``--feedback-reserve`` keeps command units free for the executor's feedback.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from falcon_plan.planning.bound import LIMIT_KINDS
from falcon_plan.planning.problem import DEFAULT_INTERVALS, INTERVALS_PER_VIA, PROFILES, PlanOptions


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
    parser.add_argument("--tc-max", type=float, default=2500.0,
                        help="constant command limit [command units] (default 2500, <= 4096; with --limit constant)")
    parser.add_argument("--limit", choices=LIMIT_KINDS, default=PlanOptions.limit,
                        help="command bound: constant (--tc-max) or device (the device's speed-dependent "
                             f"limit, 2500 at rest to 4096 in motion); default {PlanOptions.limit}")
    parser.add_argument("--feedback-reserve", type=float, default=PlanOptions.feedback_reserve,
                        help="command units kept free for feedback, subtracted from the limit "
                             f"(default {PlanOptions.feedback_reserve:g})")
    parser.add_argument("--profile", choices=PROFILES, default=PlanOptions.profile,
                        help=f"acceleration on each interval (default {PlanOptions.profile})")
    parser.add_argument("--payload-kg", type=float, default=0.0, help="payload at the end effector [kg]")
    parser.add_argument("--intervals", type=int, default=None,
                        help=f"transcription intervals N (default {DEFAULT_INTERVALS}, plus "
                             f"{INTERVALS_PER_VIA} per via point)")
    parser.add_argument("--time-budget", type=float, default=PlanOptions.time_budget_s,
                        help="optimiser time budget [s]; past it the ruckig fallback is returned")
    parser.add_argument("--fast", action="store_true",
                        help="skip cross-checks, refinement and plant run")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--out", type=Path, help="write the trajectory JSON to this file")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Plan and print; exit code 0 on success (errors are FalconPlanErrors: exit 2)."""
    from falcon_plan.planning.api import plan

    make = PlanOptions.fast if args.fast else PlanOptions
    options = make(tc_max=args.tc_max, n_intervals=args.intervals, time_budget_s=args.time_budget,
                   limit=args.limit, feedback_reserve=args.feedback_reserve, profile=args.profile)
    result = plan(args.start, args.goal, options, via_m=args.via, payload_kg=args.payload_kg)
    if args.out is not None:
        result.trajectory.to_json(args.out)
    if args.json:
        json.dump(result.report.to_dict(), sys.stdout, indent=2)
        print()
    else:
        print(result.report.summary())
    return 0
