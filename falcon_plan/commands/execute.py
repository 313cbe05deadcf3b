"""``falcon-plan execute``: plan a move and stream it to a device, then print the tracking report.

Devices: ``sim`` (the simulated plant, stepped directly), ``emulated`` (the real USB driver
against the emulated Falcon; it accepts any firmware image, so without ``--firmware`` a
dummy image is generated for the load), ``usb`` (a real Falcon; ``--firmware`` required).
The device is homed first (on a real Falcon: pull the grip fully out and push it back in).
The move starts at ``--from`` (default: where the device is; the simulated device is placed
there) and ends at ``--to``; points are ``X,Y,Z`` in metres, base frame. The plan is the
minimum-time planner's (``falcon_plan.planning.api``) unless ``--planner quintic``, or a
saved trajectory with ``--trajectory FILE.json``. When the device is elsewhere than the
move's start, a planned approach move takes it there first, in the same run
(:mod:`falcon_plan.execution.approach`). ``--model FILE`` plans and executes with a model
file (e.g. the corrected model of ``discrepancy`` / ``calibrate``); ``--effects`` gives the
simulated device (sim, emulated) hidden effects. Simulated and emulated devices run as fast
as possible unless ``--realtime``; the USB Falcon always runs in real time.

Exit code: 0 when the run completed, 1 when it was cancelled or stopped (safety, device).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidParameterError, PlanningFailed

RATES_HZ = (800, 1000)


def parse_point(text: str) -> np.ndarray:
    """``"X,Y,Z"`` [m] -> array (3,); argparse error otherwise."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in metres (e.g. 0.02,-0.01,0.13), got {text!r}")
    return np.array(values)


def add_device_arguments(parser: argparse.ArgumentParser) -> None:
    """--device, --firmware, --rate (shared with ``falcon-plan home``)."""
    parser.add_argument("--device", choices=("sim", "emulated", "usb"), required=True,
                        help="sim: simulated plant; emulated: USB driver against the emulated Falcon "
                             "(any firmware image; a dummy one by default); usb: a real Falcon")
    parser.add_argument("--firmware", type=Path, default=None,
                        help="firmware image to load (required for usb; optional for emulated)")
    parser.add_argument("--rate", type=int, choices=RATES_HZ, default=1000, help="loop rate [Hz] (default 1000)")


def add_model_arguments(parser: argparse.ArgumentParser, *, effects: bool = True) -> None:
    """--model FILE (the model to plan and control with) and, with ``effects``, --effects
    (hidden effects of the simulated device)."""
    parser.add_argument("--model", type=Path, default=None,
                        help="model file (JSON, e.g. the corrected model written by discrepancy or "
                             "calibrate) to plan and control with (default: nominal acra2009)")
    if effects:
        parser.add_argument("--effects", default=None,
                            help="hidden effects of the simulated device (sim, emulated): JSON object "
                                 "or file, e.g. '{\"coulomb_Nm\": 0.01}'")


def open_for(args: argparse.Namespace, model: Any, start_m: Any = None) -> Any:
    """Open the device ``args`` name at ``args.rate``; a simulated device simulates ``model``'s
    parameters with the hidden ``--effects`` (never the model's own effects: those are the
    controller's belief) and starts at ``start_m`` (sim only)."""
    from falcon_plan.commands.simulate import load_effects
    from falcon_plan.execution.device_factory import open_device
    from falcon_plan.model.dynamics import FalconModel

    effects = load_effects(getattr(args, "effects", None))
    if args.device == "usb" and not effects.is_nominal:
        raise InvalidParameterError("--effects applies to the simulated devices (sim, emulated), not usb")
    return open_device(args.device, rate_hz=float(args.rate), model=FalconModel(model.params),
                       firmware=args.firmware, start_m=start_m if args.device == "sim" else None,
                       effects=effects)


def register(subparsers: Any) -> None:
    """Add the ``execute`` subcommand."""
    parser = subparsers.add_parser("execute", help="plan a move and execute it on a device",
                                   description=__doc__.splitlines()[0])
    add_device_arguments(parser)
    add_model_arguments(parser)
    parser.add_argument("--from", dest="start", type=parse_point, default=None,
                        help="start X,Y,Z [m] (default: the device's position)")
    target = parser.add_mutually_exclusive_group(required=True)
    target.add_argument("--to", dest="goal", type=parse_point, help="goal X,Y,Z [m]")
    target.add_argument("--trajectory", type=Path, help="execute a saved trajectory (Trajectory JSON)")
    parser.add_argument("--planner", choices=("casadi", "quintic"), default="casadi",
                        help="casadi: the minimum-time planner (default); quintic: a smooth "
                             "straight-line move within the command limit (no optimiser)")
    parser.add_argument("--log", type=Path, default=None, help="falcon log (CSV) to write as the run goes")
    parser.add_argument("--realtime", action="store_true",
                        help="pace sim/emulated runs in wall-clock time (usb always is)")
    parser.add_argument("--settle", type=float, default=0.2, help="hold the goal this long after the move [s]")
    parser.add_argument("--preroll", type=float, default=0.5, help="hold the start this long before the move [s]")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.set_defaults(func=run)


def make_trajectory(args: argparse.Namespace, start_m: np.ndarray, model: Any) -> tuple[Any, dict[str, Any] | None]:
    """The trajectory to execute and the plan report (dict) if a planner made it."""
    from falcon_plan.planning.trajectory import Trajectory

    if args.trajectory is not None:
        return Trajectory.from_json(args.trajectory), None
    if args.planner == "quintic":
        from falcon_plan.execution.quintic import quintic_trajectory

        return quintic_trajectory(start_m, args.goal, model, rate_hz=float(args.rate)), None
    try:
        from falcon_plan.planning.api import plan
        from falcon_plan.planning.problem import PlanOptions
    except ImportError as exc:
        raise PlanningFailed(f"the planner (falcon_plan.planning.api) is not available ({exc}); "
                             "use --planner quintic or --trajectory FILE") from exc
    result = plan(start_m, args.goal, PlanOptions.fast(), model)
    return result.trajectory, result.report.to_dict()


def run(args: argparse.Namespace) -> int:
    """Open and home the device, plan, approach and execute, print the report; returns the
    exit code."""
    from falcon_plan.execution.approach import home_if_needed, run_from_here
    from falcon_plan.execution.device_factory import read_position
    from falcon_plan.model.modelfile import load_model, unplannable_effect_notes

    model = load_model(args.model)
    start = None if args.start is None else np.asarray(args.start)
    with open_for(args, model, start) as device:
        home_if_needed(device, args.device)
        if start is None:
            start = read_position(device, model.params)
        trajectory, plan_report = make_trajectory(args, start, model)
        pace = args.realtime or args.device == "usb"
        report, _ = run_from_here(device, args.device, trajectory, model, rate_hz=float(args.rate),
                               log_path=args.log, pace=pace, preroll_s=args.preroll, settle_s=args.settle)
    notes = unplannable_effect_notes(model.effects, model.params)
    if args.json:
        print(json.dumps({"execution": report.to_dict(), "plan": plan_report,
                          "model": {"path": None if args.model is None else str(args.model),
                                    "effects": model.effects.to_dict(), "notes": notes}}, indent=2))
    else:
        if plan_report is not None:
            print(f"plan: {plan_report.get('method')} {plan_report.get('duration_s', float('nan')):.4f} s")
        for note in notes:
            print(f"note: {note}")
        print(report.summary())
    return 0 if report.status == "completed" else 1
