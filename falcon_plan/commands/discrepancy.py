"""``falcon-plan discrepancy TRAIN.csv --heldout HELDOUT.csv --out DIR [--json]``: find, name
and fit what the nominal model misses in falcon logs (see falcon_plan.discrepancy), and write
the corrected model file (``DIR/model.json``, or ``--model-out FILE``) that ``plan``,
``execute``, ``serve`` ... load with ``--model``."""
from __future__ import annotations

import argparse

from falcon_plan.commands import common
from falcon_plan.model.effects import EFFECT_NAMES


def _candidates(text: str) -> list[str]:
    """argparse type: comma-separated effect names, each one of EFFECT_NAMES."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in EFFECT_NAMES]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown effect(s) {', '.join(unknown) or '(none given)'}; "
                                         f"allowed: {', '.join(EFFECT_NAMES)}")
    return names


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``discrepancy`` subcommand to ``subparsers`` (the CLI's argparse subparsers)."""
    p = subparsers.add_parser("discrepancy", help="identify model discrepancies from falcon logs",
                              description=__doc__)
    p.add_argument("train", type=common.input_file, help="training falcon log (CSV)")
    p.add_argument("--heldout", required=True, type=common.input_file,
                   help="held-out falcon log (CSV, a different motion)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (report.md, report.json, effects.json, plots)")
    p.add_argument("--json", action="store_true", help="print the JSON report on stdout")
    p.add_argument("--rate", type=common.positive_float, default=None,
                   help="control rate [Hz] if the logs lack rate_hz")
    p.add_argument("--controller", default=None, type=common.controller_text,
                   help='controller if the logs lack it, e.g. "pd kp=10 kd=0.1" or "lqr" (see falcon_plan.control), '
                        'or "open-loop" to replay the logged commands')
    common.add_model_option(p, "model file to start from (default: nominal acra2009)")
    p.add_argument("--model-out", type=common.output_file_as(".json"), default=None,
                   help="corrected model file to write (default: OUT/model.json)")
    p.add_argument("--threshold", type=common.positive_float, default=10.0,
                   help="delta BIC for very strong evidence")
    p.add_argument("--candidates", default=EFFECT_NAMES, type=_candidates, metavar="NAME,NAME",
                   help=f"comma-separated candidate effects (default: all: {', '.join(EFFECT_NAMES)})")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the workflow on the two logs and write the report."""
    from pathlib import Path

    from falcon_plan.calibration import corrected_model_file
    from falcon_plan.discrepancy.report import write_report
    from falcon_plan.discrepancy.workflow import find_discrepancy
    from falcon_plan.falconlog import read_log
    from falcon_plan.fileio import output_folder
    from falcon_plan.model.modelfile import load_model, save_model

    with output_folder(args.out):  # a failed run leaves no empty folder
        train = read_log(args.train)  # its notes (e.g. samples missing) are logged as warnings
        heldout = read_log(args.heldout)
        model = load_model(args.model)
        with common.progress("identifying (replays and fits of every candidate effect)"):
            report = find_discrepancy(train, heldout, rate_hz=args.rate, controller=args.controller,
                                      model=model, threshold=args.threshold, candidates=list(args.candidates))
        with common.progress("writing the report and plots"):
            paths = write_report(report, args.out, plots=not args.no_plots)
        model_file = corrected_model_file(report, model, {"train": str(args.train), "heldout": str(args.heldout)})
        model_path = save_model(args.model_out or Path(args.out) / "model.json", model_file.model,
                                model_file.provenance)
    if args.json:
        common.print_json(report.to_dict())
    else:
        print(f"effects: {', '.join(report.effects)}")
        for fld, p in report.parameters.items():
            print(f"  {fld} = {p.value:.5g} +- {p.std:.2g} {p.unit}")
        print(f"held-out replay RMS [counts]: {report.heldout_before.rms_counts_all:.3g} (nominal) -> "
              f"{report.heldout_after.rms_counts_all:.3g} (corrected)")
        print(f"report: {paths['markdown']}")
        print(f"corrected model: {model_path} (use it with --model)")
    return 0
