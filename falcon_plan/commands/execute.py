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
(:mod:`falcon_plan.approach`). ``--model FILE`` plans and executes with a model
file (e.g. the corrected model of ``discrepancy`` / ``calibrate``); ``--effects`` gives the
simulated device (sim, emulated) hidden effects. Simulated and emulated devices run as fast
as possible unless ``--realtime``; the USB Falcon always runs in real time. ``--mcap FILE``
records the run as an MCAP file beside the falcon log (``--log FILE.mcap``: instead of it) and
``--live`` shows it in Foxglove while it runs (:mod:`falcon_plan.recording`).

Ctrl-C (SIGINT) during the run is a cancel, and so are SIGTERM and SIGHUP (a closed terminal):
the device brakes to rest within the command limit and holds there with gravity compensation
before the run ends (a second signal ends it at once with zero force); ``--release`` makes a
cancel drop to zero force at once instead. Any other signal that ends the process sends zero
force first.

Exit code: 0 when the run completed, 1 when it was stopped (safety, device), 128 + the signal
when a signal cancelled it (130 for Ctrl-C), 2 on bad input.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import signal
import sys
import threading
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.commands import common
from falcon_plan.devices.base import SignalExit
from falcon_plan.errors import InvalidParameterError

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.trajectory import Trajectory

RATES_HZ = (800, 1000)


def add_device_arguments(parser: argparse.ArgumentParser) -> None:
    """Add --device, --firmware, --rate to ``parser`` (shared with ``falcon-plan home``)."""
    parser.add_argument("--device", choices=("sim", "emulated", "usb"), required=True,
                        help="sim: simulated plant; emulated: USB driver against the emulated Falcon "
                             "(any firmware image; a dummy one by default); usb: a real Falcon")
    parser.add_argument("--firmware", type=common.input_file, default=None,
                        help="firmware image to load (required for usb; optional for emulated)")
    common.add_rate_option(parser, choices=RATES_HZ, default=None,
                           help="loop rate [Hz] (default: 1000 on a device with USB frames: usb, or emulated "
                                "with --usb-timing frames or wall; 800 otherwise)")
    parser.add_argument("--usb-timing", choices=USB_TIMINGS, default="instant",
                        help="emulated only: instant (every transfer completes at once, blocking I/O, "
                             "each reading answers its own command; deterministic), frames (1 ms USB "
                             "frames, the FTDI latency timer, threaded I/O as on a real Falcon: readings "
                             "trail the commands, as doctor measures) or wall (frames, and the device "
                             "keeps its own time: a stalled host finds the grip moved on)")


USB_TIMINGS = ("instant", "frames", "wall")
"""``--usb-timing`` choices for the emulated device."""


def loop_rate(args: argparse.Namespace) -> float:
    """The loop rate [Hz] for the device ``args`` name: ``--rate``, else
    :data:`~falcon_plan.commands.common.FRAME_RATE_HZ` on a device whose packets move in USB
    frames (usb; emulated with ``--usb-timing`` frames or wall), else the paper's 800 Hz."""
    if args.rate is not None:
        return float(args.rate)
    framed = args.device == "usb" or getattr(args, "usb_timing", "instant") != "instant"
    return common.FRAME_RATE_HZ if framed else common.DEFAULT_RATE_HZ


def usb_timing_for(args: argparse.Namespace) -> Any:
    """The emulated device's :class:`~falcon_plan.devices.emulated.UsbTiming` for
    ``args.usb_timing`` (None: instant); InvalidParameterError for frames on another device."""
    if getattr(args, "usb_timing", "instant") == "instant":
        return None
    if args.device != "emulated":
        raise InvalidParameterError(f"--usb-timing {args.usb_timing} applies to --device emulated, "
                                    f"not {args.device}")
    from falcon_plan.devices.emulated import UsbTiming

    return UsbTiming(clock="wall" if args.usb_timing == "wall" else "packets")


def wants_pacing(args: argparse.Namespace) -> bool:
    """Whether a run on the device ``args`` name keeps wall-clock time: always on a real
    Falcon and on an emulated one with USB timing (``--usb-timing frames|wall``: its frames
    go in wall-clock time, so a loop that ran ahead of them would hand over commands faster
    than the bus carries them and the device would never see some), and with ``--realtime``
    (if the command has it)."""
    return (args.device == "usb" or getattr(args, "usb_timing", "instant") != "instant"
            or getattr(args, "realtime", False))


def add_model_arguments(parser: argparse.ArgumentParser, *, effects: bool = True) -> None:
    """Add to ``parser`` --model FILE (the model to plan and control with) and, with
    ``effects``, --effects (hidden effects of the simulated device)."""
    common.add_model_option(parser, "model file (e.g. the corrected model written by discrepancy or "
                                    "calibrate) to plan and control with (default: nominal acra2009)")
    if effects:
        parser.add_argument("--effects", default=None,
                            help="hidden " + common.EFFECTS_HELP.format(fields=common.effect_fields())
                            .replace("%", "%%") + " (sim, emulated)")


def open_for(args: argparse.Namespace, model: FalconModel, start_m: Any = None) -> Device:
    """Open the device ``args`` name at its :func:`loop_rate`; a simulated device simulates ``model``'s
    parameters with the hidden ``--effects`` (never the model's own effects: those are the
    controller's belief) and starts at ``start_m`` (sim only)."""
    from falcon_plan.execution.device_factory import open_device
    from falcon_plan.model.dynamics import FalconModel

    effects = common.load_effects(getattr(args, "effects", None))
    if args.device == "usb" and not effects.is_nominal:
        raise InvalidParameterError("--effects applies to the simulated devices (sim, emulated), not usb")
    return open_device(args.device, rate_hz=loop_rate(args), model=FalconModel(model.params),
                       firmware=args.firmware, start_m=start_m if args.device == "sim" else None,
                       effects=effects, usb_timing=usb_timing_for(args))


def register(subparsers: Any) -> None:
    """Add the ``execute`` subcommand to ``subparsers`` (the ``falcon-plan`` parser's
    subcommands)."""
    parser = subparsers.add_parser("execute", help="plan a move and execute it on a device",
                                   description=__doc__)
    add_device_arguments(parser)
    add_model_arguments(parser)
    common.add_point_option(parser, "--from", "--start", dest="start",
                            help="start point [m] (default: the device's position)")
    target = parser.add_mutually_exclusive_group(required=True)
    common.add_point_option(target, "--to", "--goal", dest="goal", help="goal point [m]")
    target.add_argument("--trajectory", type=common.input_file, metavar="FILE.json",
                        help="execute a saved trajectory (Trajectory JSON, e.g. from plan --out)")
    parser.add_argument("--planner", choices=("casadi", "quintic"), default="casadi",
                        help="casadi: the minimum-time planner (default); quintic: a smooth "
                             "straight-line move within the command limit (no optimiser)")
    parser.add_argument("--log", type=common.output_file_as(".csv", ".mcap"), default=None, metavar="FILE.csv",
                        help="write the falcon log (CSV) as the run goes, and a plot of the run next to it; "
                             "a FILE.mcap gets an MCAP recording instead")
    parser.add_argument("--plot", type=common.output_file_as(".png"), default=None, metavar="FILE.png",
                        help="write a plot of the run (reference vs measured, tracking error per leg in "
                             "counts and in mm, commands against the limit)")
    parser.add_argument("--controller", choices=("lqr", "pd"), default="lqr",
                        help="lqr: time-varying LQR along the plan with an observer and the model's "
                             "feed-forward (default); pd: the PD (kp=10, kd=0.1 on the error) + feed-forward")
    common.add_recording_options(parser)
    parser.add_argument("--realtime", action="store_true",
                        help="pace sim/emulated runs in wall-clock time (usb always is)")
    parser.add_argument("--settle", type=float, default=0.2, help="hold the goal this long after the move [s]")
    parser.add_argument("--release", action="store_true",
                        help="on a cancel (Ctrl-C, SIGTERM, SIGHUP), release the grip at once (zero force) instead of braking to rest and "
                             "holding it there with gravity compensation")
    parser.add_argument("--preroll", type=float, default=0.5, help="hold the start this long before the move [s]")
    common.add_json_option(parser)
    parser.set_defaults(func=run)


def make_trajectory(args: argparse.Namespace, start_m: np.ndarray,
                    model: FalconModel) -> tuple[Trajectory, dict[str, Any] | None]:
    """The plan report (dict) and the move from ``start_m`` (x, y, z) [m], base frame, to
    ``args.goal`` planned with ``model`` by ``args.planner``."""
    if args.planner == "quintic":
        from falcon_plan.planning.quintic import quintic_trajectory

        return quintic_trajectory(start_m, args.goal, model, rate_hz=loop_rate(args)), None
    from falcon_plan.planning.problem import PlanOptions

    result = common.plan_with_progress(start_m, args.goal, PlanOptions.fast(), model)
    return result.trajectory, result.report.to_dict()


CANCEL_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))
"""Signals that cancel a run (the executor's safe stop) instead of ending the process at once:
Ctrl-C, a polite termination (a service manager's stop) and a closed terminal or lost ssh
session (SIGHUP). Every other signal that ends the process still sends zero force first
(:data:`falcon_plan.devices.base.ENDING_SIGNALS`)."""


@dataclasses.dataclass
class Cancel:
    """A run's cancel: ``event`` (the executor's safe stop) is set by the first signal of
    :data:`CANCEL_SIGNALS`, ``signum`` records which (None while not cancelled)."""

    event: threading.Event = dataclasses.field(default_factory=threading.Event)
    signum: int | None = None

    @property
    def exit_code(self) -> int:
        """The exit status of a run this cancel stopped: 128 + the signal (130 for Ctrl-C)."""
        return 128 + int(self.signum if self.signum is not None else signal.SIGINT)


@contextlib.contextmanager
def cancel_on_signals(release: bool = False) -> Iterator[Cancel]:
    """A :class:`Cancel` the first signal of :data:`CANCEL_SIGNALS` sets: the device brakes to
    rest and is held (``release``: dropped to zero force at once); a second one ends the run
    at once (KeyboardInterrupt for Ctrl-C, else SystemExit(128 + signal)), the device's exit
    path sending zero force. The previous handlers are restored on exit. Off the main thread
    (where signals cannot be caught) the cancel is never set."""
    cancel = Cancel()
    if threading.current_thread() is not threading.main_thread():
        yield cancel
        return

    def handler(signum: int, frame: Any) -> None:
        if cancel.event.is_set():
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            raise SignalExit(signum)
        cancel.signum = signum
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        common.say_if_possible(f"cancelling ({name}): releasing the grip at once (zero force)" if release else
                               f"cancelling ({name}): braking to rest (Ctrl-C again to release at once)")
        cancel.event.set()

    previous = {signum: signal.signal(signum, handler) for signum in CANCEL_SIGNALS}
    try:
        yield cancel
    finally:
        for signum, before in previous.items():
            signal.signal(signum, before)


def run(args: argparse.Namespace) -> int:
    """Open and home the device, plan, approach and execute, print the report; returns the
    exit code."""
    from falcon_plan.approach import home_if_needed, run_from_here
    from falcon_plan.execution.device_factory import read_position
    from falcon_plan.execution.executor import ExecutionStatus
    from falcon_plan.model.modelfile import load_model, unplannable_effect_notes

    model = load_model(args.model)
    start = None if args.start is None else np.asarray(args.start)
    saved = None if args.trajectory is None else common.checked_for_device(
        common.read_trajectory(args.trajectory), args.trajectory, model, loop_rate(args))
    with open_for(args, model, start) as device:
        home_if_needed(device, args.device)
        if start is None:
            start = read_position(device, model.params)
        trajectory, plan_report = (saved, None) if saved is not None else make_trajectory(args, start, model)
        if args.controller == "lqr":  # its design's linearisation (kernels compiled once per machine)
            with common.preparing("the controller"):
                model.prepare_linearisation()
        pace = wants_pacing(args)
        plot = common.plot_path(args.plot, args.log)
        with common.run_log(args.log, plot) as log_path, common.live_view(args) as live:
            # the cancel is armed before the progress line says the run began (a signal right
            # after that line is a cancel, never the devices' exit path)
            with cancel_on_signals(args.release) as cancel, \
                    common.progress(f"executing on the {args.device} device"):
                report, _ = run_from_here(device, args.device, trajectory, model, rate_hz=loop_rate(args),
                                          log_path=log_path, pace=pace, preroll_s=args.preroll,
                                          settle_s=args.settle, controller_kind=args.controller,
                                          mcap=args.mcap, live=live, plan_report=plan_report,
                                          cancel=cancel.event, release=args.release)
            if plot is not None and report.samples > 1:
                from falcon_plan.falconlog import read_log
                from falcon_plan.plots import plot_run

                plot_run(read_log(log_path), plot)
        if args.log is None:
            report = dataclasses.replace(report, log_path=None)  # the temporary log is gone
    notes = unplannable_effect_notes(model.effects, model.params)
    if args.json:
        common.print_json({"execution": report.to_dict(), "plan": plan_report,
                           "model": {"path": None if args.model is None else str(args.model),
                                     "effects": model.effects.to_dict(), "notes": notes}})
    else:
        if plan_report is not None:
            print(f"plan: {plan_report.get('method')}, {1e3 * plan_report.get('duration_s', float('nan')):.1f} ms")
            if plan_report.get("fallback_reason"):
                print(f"note: the planner returned its ruckig fallback because the {plan_report['fallback_reason']}")
        for note in notes:
            print(f"note: {note}")
        print(report.summary())
        if plot is not None and report.samples > 1:
            print(f"plot: {plot}")
    if cancel.event.is_set() and report.status == ExecutionStatus.CANCELLED:
        return cancel.exit_code  # interrupted (after the safe stop): 130 for Ctrl-C, as every command
    return 0 if report.status == ExecutionStatus.COMPLETED else 1
