"""``falcon-plan discrepancy TRAIN.csv --heldout HELDOUT.csv --out DIR [--json]``: find, name
and fit what the nominal model misses in falcon logs (see falcon_plan.discrepancy)."""
from __future__ import annotations

import argparse
import json

from falcon_plan.model.effects import EFFECT_NAMES


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``discrepancy`` subcommand."""
    p = subparsers.add_parser("discrepancy", help="identify model discrepancies from falcon logs",
                              description=__doc__)
    p.add_argument("train", help="training falcon log (CSV)")
    p.add_argument("--heldout", required=True, help="held-out falcon log (a different motion)")
    p.add_argument("--out", required=True, help="output folder (report.md, report.json, effects.json, plots)")
    p.add_argument("--json", action="store_true", help="print the JSON report on stdout")
    p.add_argument("--rate", type=float, default=None, help="control rate [Hz] if the logs lack rate_hz")
    p.add_argument("--controller", default=None,
                   help='controller if the logs lack it, e.g. "pd kp=10 kd=0.1"')
    p.add_argument("--threshold", type=float, default=10.0, help="delta BIC for very strong evidence")
    p.add_argument("--candidates", default=",".join(EFFECT_NAMES),
                   help="comma-separated candidate effects (default: all)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the workflow on the two logs and write the report."""
    from falcon_plan.discrepancy.report import write_report
    from falcon_plan.discrepancy.workflow import find_discrepancy
    from falcon_plan.falconlog import read_log

    train = read_log(args.train)
    heldout = read_log(args.heldout)
    names = [n.strip() for n in args.candidates.split(",") if n.strip()]
    report = find_discrepancy(train, heldout, rate_hz=args.rate, controller=args.controller,
                              threshold=args.threshold, candidates=names)
    paths = write_report(report, args.out, plots=not args.no_plots)
    if args.json:
        print(json.dumps(report.to_dict(), indent=1))
    else:
        print(f"effects: {', '.join(report.effects)}")
        for fld, p in report.parameters.items():
            print(f"  {fld} = {p.value:.5g} +- {p.std:.2g} {p.unit}")
        print(f"held-out replay RMS [counts]: {report.heldout_before.rms_counts_all:.3g} (nominal) -> "
              f"{report.heldout_after.rms_counts_all:.3g} (corrected)")
        print(f"report: {paths['markdown']}")
    return 0
