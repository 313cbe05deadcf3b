"""``falcon-plan calibrate --device sim|emulated|usb --out DIR``: the whole calibration loop in
one command (:mod:`falcon_plan.calibration`): record a training and a held-out excitation,
identify the discrepancy, write the corrected model file (DIR/model.json), then plan and
execute a chain of verification moves with the nominal and with the corrected model and
report the tracking error both ways (DIR/calibration.json, DIR/calibration.png).

With ``--mcap`` the four runs are MCAP recordings (DIR/train.mcap, ...) instead of CSV falcon
logs; the identification and the plots read them back the same way.

The simulated devices take hidden effects with ``--effects`` (what the loop should find),
e.g. ``--effects '{"coulomb_Nm": 0.008, "payload_kg": 0.05}'``.
"""
from __future__ import annotations

import argparse
import json
from typing import Any

from falcon_plan.commands import common


def register(subparsers: Any) -> None:
    """Add the ``calibrate`` subcommand to ``subparsers`` (the CLI's argparse subparsers)."""
    from falcon_plan.commands.execute import add_device_arguments, add_model_arguments
    from falcon_plan.discrepancy.excitation import KINDS

    parser = subparsers.add_parser("calibrate", help="record, identify, correct the model, verify",
                                   description=__doc__)
    add_device_arguments(parser)
    add_model_arguments(parser)
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--duration", type=common.positive_float, default=8.0, help="length of each excitation [s]")
    parser.add_argument("--seed", type=int, default=0, help="seed of the excitation designs")
    parser.add_argument("--train-kind", choices=KINDS, default="mixed", help="training excitation (default mixed)")
    parser.add_argument("--heldout-kind", choices=KINDS, default="fourier", help="held-out excitation (default fourier)")
    parser.add_argument("--candidates", default=None, help="comma-separated candidate effects (default: all)")
    parser.add_argument("--realtime", action="store_true", help="pace sim/emulated runs in wall-clock time")
    parser.add_argument("--mcap", action="store_true",
                        help="record the four runs as MCAP files (train.mcap, ...; for Foxglove, PlotJuggler) "
                             "instead of CSV falcon logs; identification reads them back the same way")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Open the device, run the loop, print the summary; exit code 0."""
    from falcon_plan.calibration import calibrate
    from falcon_plan.commands.execute import open_for, wants_pacing
    from falcon_plan.model.modelfile import load_model

    model = load_model(args.model)
    names = None if args.candidates is None else [n.strip() for n in args.candidates.split(",") if n.strip()]
    with open_for(args, model) as device:
        result = calibrate(device, args.device, args.out, model=model, duration_s=args.duration,
                           seed=args.seed, train_kind=args.train_kind, heldout_kind=args.heldout_kind,
                           pace=wants_pacing(args), candidates=names,
                           log_format="mcap" if args.mcap else "csv",
                           progress=common.step_printer("calibrate"))
    print(json.dumps(result.to_dict(), indent=2) if args.json else result.summary())
    return 0
