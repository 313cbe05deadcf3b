"""``falcon-plan home``: home a device (all three legs) and print where it is.

On a real Falcon: pull the grip fully out, then push it back in, while this waits. The
device is left with zero force. Output: the encoder counts and the end-effector position
[mm, base frame] after homing (``--json`` for a JSON object).
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from falcon_plan.commands.common import mm
from falcon_plan.commands.execute import add_device_arguments, loop_rate, usb_timing_for


def register(subparsers: Any) -> None:
    """Add the ``home`` subcommand to ``subparsers`` (the ``falcon-plan`` parser's
    subcommands)."""
    parser = subparsers.add_parser("home", help="home the device's legs and print its position",
                                   description=__doc__.splitlines()[0])
    add_device_arguments(parser)
    parser.add_argument("--timeout", type=float, default=30.0, help="give up after this long [s] (default 30)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Open, home, read the position, close (zero force); returns the exit code."""
    import numpy as np

    from falcon_plan.execution.device_factory import open_device
    from falcon_plan.model.kinematics import PositionTracker
    from falcon_plan.model.params import ACRA2009

    with open_device(args.device, rate_hz=loop_rate(args), firmware=args.firmware,
                     usb_timing=usb_timing_for(args)) as device:
        if args.device == "usb":
            print("homing: pull the grip fully out, then push it back in", file=sys.stderr)
        device.home(timeout_s=args.timeout)
        reading = device.exchange(np.zeros(3, dtype=np.int64))
        position_m = PositionTracker(ACRA2009).position(reading.counts)
    result = {"device": args.device, "homed": bool(reading.all_homed),
              "counts": reading.counts.tolist(), "position_mm": (position_m * 1e3).round(3).tolist()}
    if args.json:
        print(json.dumps(result))
    else:
        print(f"homed: counts {result['counts']}, position {mm(position_m)}")
    return 0
