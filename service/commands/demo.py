"""``falcon-plan demo``: the service end to end in one process.

Starts the Zenoh service in-process (peer mode, loopback only, multicast scouting off,
simulated device in real time), opens a separate client session, sends one goal (plan and
execute), follows its progress, prints a summary of the plan and of the tracking (``--json``:
the whole goal result), and closes both sessions and the device. ``--plot FILE.png`` draws
the executed run against its plan, and the plan next to it (FILE-plan.png).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, TextIO

from falcon_plan.commands import common
from service.commands.request import add_options_argument, goal_summary, plot_goal

DEMO_GOAL_M = (0.02, 0.01, 0.13)
"""Default goal [m]: about 25 mm from the simulated device's home (0, 0, 0.145) m."""


def register(subparsers: Any) -> None:
    """Add the ``demo`` subcommand to ``subparsers`` (the ``falcon-plan`` command line's)."""
    parser = subparsers.add_parser(
        "demo", help="start the service in-process and send it one goal end to end (plan + execute)",
        description=__doc__.splitlines()[0])
    common.add_point_option(parser, "--to", "--goal", dest="goal", default=DEMO_GOAL_M, help="goal point [m]")
    add_options_argument(parser)
    parser.add_argument("--port", type=int, default=0, help="loopback port to listen on (default: a free one)")
    parser.add_argument("--timeout", type=common.positive_float, default=120.0, help="longest wait for the goal [s]")
    parser.add_argument("--plot", type=common.output_file_as(".png"), default=None, metavar="FILE.png",
                        help="write a plot of the executed run (measured against the plan) and, next to it "
                             "as FILE-plan.png, the plan's")
    common.add_json_option(parser)
    parser.set_defaults(func=_run)


def run_demo(goal_m: tuple[float, float, float] = DEMO_GOAL_M, *, options: dict[str, Any] | None = None,
             port: int = 0, timeout_s: float = 120.0, out: TextIO | None = None, as_json: bool = False,
             plot: Path | None = None) -> int:
    """Run the demo: a service on loopback port ``port`` (0: a free one) and one goal to
    ``goal_m`` [m, base frame] planned with ``options`` (PlanOptions fields, None: the
    defaults), waiting at most ``timeout_s`` [s] for it; printing to ``out`` (default: the
    current sys.stdout). Returns 0 when the goal was planned and executed (status done). ``as_json`` prints the goal result as
    JSON instead of the summary; ``plot`` draws the executed run to that PNG and the plan next to it
    (``request goal --plot``)."""
    out = out or sys.stdout
    from falcon_plan.commands.common import mm
    from service.client import FalconClient, wait_for_instance
    from service.config import SessionSettings, free_loopback_port
    from service.main import build_service, serve_arguments

    endpoint = f"tcp/127.0.0.1:{port or free_loopback_port()}"
    service = build_service(serve_arguments(["--device", "sim", "--listen", endpoint, "--planning-workers", "1"]))
    say = sys.stderr.write if as_json else out.write
    say(f"service {service.keys.base}: peer mode, listening on {endpoint}, simulated device\n")
    with service, FalconClient(SessionSettings.client([endpoint]), timeout_s=timeout_s) as client:
        wait_for_instance(client, service.keys.instance)
        state = client.state()
        say(f"client connected; device at {mm(state['position_m'])}, homed {'yes' if all(state['homed']) else 'no'}\n")
        ack = client.submit_goal(goal_m, options=options)
        say(f"goal {ack['id']} to {mm(goal_m)} accepted (queue position {ack['position']}); "
            f"result on {ack['keys']['result']}\n")
        phases: set[str] = set()

        def on_progress(body: dict[str, Any]) -> None:
            if body["phase"] not in phases:
                phases.add(body["phase"])
                say(f"  {body['phase']} ...\n")

        result = client.wait_result(ack["id"], timeout_s=timeout_s, on_progress=on_progress)
        if plot is not None and result["status"] == "done":  # the service answers from its plan cache
            plot_goal(result, client.plan(result["start_m"], result["goal_m"], options), plot)
    if as_json:
        json.dump(result, out, indent=2)
        out.write("\n")
    else:
        out.write(goal_summary(result) + "\n")
    say("sessions closed\n")
    return 0 if result["status"] == "done" else 1


def _run(args: argparse.Namespace) -> int:
    return run_demo(tuple(args.goal), options=args.options, port=args.port, timeout_s=args.timeout,
                    as_json=args.json, plot=args.plot)
