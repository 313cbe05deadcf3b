"""``falcon-plan demo``: the service end to end in one process.

Starts the Zenoh service in-process (peer mode, loopback only, multicast scouting off,
simulated device in real time), opens a separate client session, sends one goal (plan and
execute), follows its progress, prints the plan report and the tracking report, and closes
both sessions and the device.
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any, TextIO

DEMO_GOAL_M = (0.02, 0.01, 0.13)
"""Default goal [m]: about 25 mm from the simulated device's home (0, 0, 0.145) m."""


def register(subparsers: Any) -> None:
    """Add the ``demo`` subcommand."""
    parser = subparsers.add_parser(
        "demo", help="start the service in-process and send it one goal end to end (plan + execute)",
        description=__doc__.splitlines()[0])
    parser.add_argument("--goal", nargs=3, type=float, default=DEMO_GOAL_M, metavar=("X", "Y", "Z"),
                        help=f"goal point [m] (default {DEMO_GOAL_M})")
    parser.add_argument("--options", type=json.loads, default=None, help="PlanOptions as a JSON object")
    parser.add_argument("--port", type=int, default=0, help="loopback port to listen on (default: a free one)")
    parser.add_argument("--timeout", type=float, default=120.0, help="longest wait for the goal [s]")
    parser.set_defaults(func=_run)


def _section(out: TextIO, title: str, body: Any) -> None:
    out.write(f"\n== {title} ==\n")
    json.dump(body, out, indent=2, sort_keys=True)
    out.write("\n")


def run_demo(goal_m: tuple[float, float, float] = DEMO_GOAL_M, *, options: dict[str, Any] | None = None,
             port: int = 0, timeout_s: float = 120.0, out: TextIO | None = None) -> int:
    """Run the demo, printing to ``out`` (default: the current sys.stdout); returns 0 when
    the goal was planned and executed (status done)."""
    out = out or sys.stdout
    from service.client import FalconClient, wait_for_instance
    from service.config import SessionSettings, free_loopback_port
    from service.main import build_service, serve_arguments

    endpoint = f"tcp/127.0.0.1:{port or free_loopback_port()}"
    service = build_service(serve_arguments(["--device", "sim", "--listen", endpoint, "--planning-workers", "1"]))
    out.write(f"service {service.keys.base}: peer mode, listening on {endpoint}, simulated device\n")
    with service, FalconClient(SessionSettings.client([endpoint]), timeout_s=timeout_s) as client:
        wait_for_instance(client, service.keys.instance)
        state = client.state()
        out.write(f"client connected; device at {[round(v, 4) for v in state['position_m']]} m, "
                  f"homed {state['homed']}\n")
        ack = client.submit_goal(goal_m, options=options)
        out.write(f"goal {ack['id']} accepted (queue position {ack['position']}); result on {ack['keys']['result']}\n")
        phases: set[str] = set()

        def on_progress(body: dict[str, Any]) -> None:
            if body["phase"] not in phases:
                phases.add(body["phase"])
                out.write(f"  {body['phase']} ...\n")

        result = client.wait_result(ack["id"], timeout_s=timeout_s, on_progress=on_progress)
    plan, track = result.get("plan_report") or {}, result.get("tracking_report") or {}
    _section(out, "plan report", plan)
    _section(out, "tracking report", track)
    if plan:
        out.write(f"\nplan: {plan.get('method')} {plan.get('status')}, motion {plan.get('duration_s', 0):.3f} s, "
                  f"planned in {plan.get('total_time_s', 0):.2f} s\n")
    if track.get("tracking"):
        tr = track["tracking"]
        out.write(f"tracking: {track['status']}, {track['samples']} samples at {track['rate_hz']:g} Hz, "
                  f"Cartesian error rms {tr['norm_rms_mm']:.2f} mm, max {tr['norm_max_mm']:.2f} mm, "
                  f"missed deadlines {track.get('missed_deadlines')}\n")
    if result.get("error"):
        _section(out, "error", result["error"])
    out.write(f"goal {result['id']}: {result['status']} (from {result['start_m']} to {result['goal_m']} m); "
              "sessions closed\n")
    return 0 if result["status"] == "done" else 1


def _run(args: argparse.Namespace) -> int:
    return run_demo(tuple(args.goal), options=args.options, port=args.port, timeout_s=args.timeout)
