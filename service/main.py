"""Run one service instance: ``python -m service.main`` or ``falcon-plan serve``.

Arguments become a :class:`~service.config.SessionSettings` and a
:class:`~service.server.ServiceOptions`; :func:`run` serves until SIGINT or SIGTERM, then
closes everything (device at zero force, session closed) and returns 0. The log level comes
from FALCON_PLAN_LOG (default INFO here).
"""
from __future__ import annotations

import argparse
import gc
import logging
import os
import signal
import sys
import threading
from typing import TYPE_CHECKING, Any

from falcon_plan.commands.common import add_live_options, live_port
from falcon_plan.errors import FalconPlanError
from service.config import add_session_arguments, settings_from_args
from service.device import DEVICE_KINDS, make_runner
from service.handlers import MAX_TIME_BUDGET_S, falcon_planner
from service.keys import DEFAULT_INSTANCE, DEFAULT_PREFIX, ServiceKeys
from service.options import ServiceOptions

if TYPE_CHECKING:
    from service.server import FalconService

log = logging.getLogger(__name__)

def add_serve_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the arguments of ``serve`` to ``parser``."""
    parser.add_argument("--device", choices=DEVICE_KINDS, default="sim",
                        help="device this instance owns: sim (default), emulated, usb, or none (planning only)")
    parser.add_argument("--instance", default=DEFAULT_INSTANCE,
                        help=f"instance id, unique under the prefix (default {DEFAULT_INSTANCE})")
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help=f"key prefix (default {DEFAULT_PREFIX})")
    parser.add_argument("--firmware", default=None, help="firmware image for --device usb (default: already loaded)")
    parser.add_argument("--controller", choices=("lqr", "pd"), default="lqr",
                        help="tracking controller of the executor: lqr (time-varying LQR + feed-forward, "
                             "default) or pd (the PD + feed-forward)")
    parser.add_argument("--state-rate", type=float, default=50.0, help="state publication rate [Hz] (default 50)")
    parser.add_argument("--planning-workers", type=int, default=os.cpu_count() or 1,
                        help="planner processes, each planning one request at a time (default: one per core, "
                             f"here {os.cpu_count() or 1})")
    parser.add_argument("--request-cap", type=float, default=MAX_TIME_BUDGET_S,
                        help="longest a plan request or a goal's planning may take from its arrival, queue time "
                             f"included [s] (default {MAX_TIME_BUDGET_S:g})")
    parser.add_argument("--plan-cache", type=int, default=64, help="plans cached by request (default 64, 0: off)")
    parser.add_argument("--queue-limit", type=int, default=16, help="pending goals allowed (default 16)")
    parser.add_argument("--model", default=None,
                        help="model file (JSON, e.g. a corrected model from calibrate) to plan and "
                             "execute with; reported in info (default: nominal acra2009)")
    parser.add_argument("--record", default=None, metavar="DIR",
                        help="record every goal as an MCAP file DIR/<goal id>.mcap (events, plan, every tick; "
                             "open it in Foxglove or PlotJuggler)")
    add_live_options(parser, "--foxglove", what="goals")
    add_session_arguments(parser, server=True)


def serve_arguments(argv: list[str]) -> argparse.Namespace:
    """``argv`` parsed as ``serve`` arguments (for callers that build a service as ``serve`` does)."""
    parser = argparse.ArgumentParser(prog="serve")
    add_serve_arguments(parser)
    return parser.parse_args(argv)


def build_service(args: argparse.Namespace) -> FalconService:
    """A not yet started service from parsed ``serve`` arguments."""
    from falcon_plan.model.modelfile import read_model_file
    from falcon_plan.model.dynamics import FalconModel
    from service.server import FalconService  # the session, the planners: loaded to serve, not to parse

    keys = ServiceKeys(args.prefix, args.instance)
    settings = settings_from_args(args, server=True)
    record_dir = getattr(args, "record", None)
    if record_dir is not None:
        from falcon_plan.fileio import make_folder

        make_folder(record_dir, "recording folder")
    options = ServiceOptions(state_rate_hz=args.state_rate, planning_workers=args.planning_workers,
                             request_cap_s=args.request_cap, plan_cache_size=args.plan_cache,
                             queue_limit=args.queue_limit, record_dir=record_dir,
                             foxglove_port=live_port(args, "--foxglove"))
    model_path = getattr(args, "model", None)
    model = FalconModel() if model_path is None else read_model_file(model_path).model
    runner = make_runner(args.device, model, firmware_path=args.firmware,
                         controller=getattr(args, "controller", "lqr"))
    # each planning process builds its planner itself, loading the model file if there is one
    return FalconService(settings, keys, falcon_planner, runner, options, model_path=model_path)


def run(args: argparse.Namespace, ready: Any = None) -> int:
    """Serve until SIGINT/SIGTERM (or until ``ready``'s caller stops it); returns 0.

    ``ready``, if given, is called with the started service (tests and the demo use it)."""
    service = build_service(args)
    stop_signals = (signal.SIGINT, signal.SIGTERM)
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in stop_signals:
            previous[sig] = signal.signal(sig, lambda signum, _frame: service.request_stop())
    try:
        with service:
            # Everything built at start-up (model, planner functions) lives as long as the
            # process: keep it out of the cyclic collector, whose full passes over it paused
            # replies by ~50 ms in the load benchmark.
            gc.freeze()
            print(f"falcon-plan service {service.keys.base} ready ({service.settings.describe()}, "
                  f"device {args.device}); Ctrl-C stops it", flush=True)
            if service.live is not None:
                print(f"falcon-plan live view at {service.live.url} (Foxglove: Open connection -> "
                      "Foxglove WebSocket)", flush=True)
            if ready is not None:
                ready(service)
            while not service.wait(0.5):
                pass
            log.info("stopping")
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("falcon-plan service stopped", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m service.main [serve arguments]``: serve with the arguments ``argv``
    (default the process's); returns the exit code."""
    logging.basicConfig(level=os.environ.get("FALCON_PLAN_LOG", "INFO").upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    parser = argparse.ArgumentParser(prog="python -m service.main", description=__doc__.splitlines()[0])
    add_serve_arguments(parser)
    try:
        return run(parser.parse_args(argv))
    except FalconPlanError as exc:
        print(f"python -m service.main: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
