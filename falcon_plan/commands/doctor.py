"""``falcon-plan doctor``: the command line of the first-contact checks of a Falcon
(:mod:`falcon_plan.doctor`, whose docstring is the command's description)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from falcon_plan import doctor
from falcon_plan.commands import common
from falcon_plan.errors import FalconPlanError


def register(subparsers: Any) -> None:
    """Add the ``doctor`` subcommand to ``subparsers`` (the ``falcon-plan`` parser's
    subcommands)."""
    parser = subparsers.add_parser("doctor", help="first-contact check of a Falcon (USB, "
                                   "firmware, homing, loop rate, conventions)",
                                   description=doctor.__doc__)
    parser.add_argument("--device", choices=("usb", "emulated"), required=True,
                        help="usb: a real Falcon; emulated: the emulated one (real USB timing)")
    parser.add_argument("--firmware", type=common.input_file, default=None,
                        help="nVent firmware image (usb: needed unless it is running already)")
    parser.add_argument("--out", type=Path, default=Path("out/doctor"),
                        help="folder for the report and the falcon logs")
    common.add_rate_option(parser, choices=(800, 1000), default=common.FRAME_RATE_HZ,
                           help="loop rate [Hz] (default 1000: both devices move their packets in 1 ms USB frames)")
    parser.add_argument("--load-retries", type=common.positive_int, default=10,
                        help="whole firmware-load attempts (as libnifalcon's tools)")
    parser.add_argument("--home-timeout", type=common.positive_float, default=60.0,
                        help="wait this long for homing [s]")
    parser.add_argument("--no-moves", action="store_true",
                        help="stop after homing: apply no force")
    common.add_model_option(parser, "model file to check against and to extend with the measured delay in "
                                    "doctor-model.json (e.g. calibrate's; default: nominal acra2009)")
    common.add_json_option(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the doctor; 0 if no check failed, 1 otherwise."""
    from falcon_plan.fileio import make_folder

    from falcon_plan.model.modelfile import load_model

    make_folder(args.out)  # an output folder that cannot be made is bad input (exit 2), before any I/O
    model = None if args.model is None else load_model(args.model)     # a bad file: exit 2
    options = doctor.DoctorOptions(args.device, args.out, args.firmware, float(args.rate),
                                   args.load_retries, args.home_timeout, not args.no_moves, model=model)
    try:
        report = doctor.diagnose(options)
    except (FalconPlanError, OSError) as exc:
        print(f"falcon-plan doctor: error: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(report.to_dict(), default=doctor.json_default) if args.json else report.text(), end="")
    if not args.json:
        print(f"report: {report.files['report']}, {report.files['text']}")
        logs = [path for key, path in report.files.items() if key.startswith("falcon_log_")]
        if logs or "model" in report.files:
            print("written: " + ", ".join(logs + ([report.files["model"]] if "model" in report.files else [])))
    return 1 if report.failed else 0
