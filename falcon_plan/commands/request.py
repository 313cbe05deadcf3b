"""``falcon-plan request``: a small client of the Zenoh service using only the documented keys."""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

ACTIONS = ("plan", "goal", "state", "cancel", "result", "info", "instances")


def register(subparsers: Any) -> None:
    """Add the ``request`` subcommand."""
    from service.config import add_session_arguments
    from service.keys import DEFAULT_PREFIX

    parser = subparsers.add_parser(
        "request", help="send one request to a running service (plan, goal, state, cancel, ...)",
        description="plan: plan START -> GOAL and print the report; goal: submit a goal, follow its "
                    "progress and print the tracking report; state: the device state; cancel ID; "
                    "result ID; info; instances (from liveliness).")
    parser.add_argument("action", choices=ACTIONS)
    parser.add_argument("goal_id", nargs="?", help="goal id (cancel, result; optional for goal)")
    parser.add_argument("--start", nargs=3, type=float, metavar=("X", "Y", "Z"), help="start point [m]")
    parser.add_argument("--goal", nargs=3, type=float, metavar=("X", "Y", "Z"), help="goal point [m]")
    parser.add_argument("--options", type=json.loads, default=None, help="PlanOptions as a JSON object")
    parser.add_argument("--instance", default=None,
                        help="instance for goal/state/cancel/result/info (default falcon0); for plan, "
                             "without it the shared <prefix>/plan key is used (any one instance answers)")
    parser.add_argument("--prefix", default=DEFAULT_PREFIX)
    parser.add_argument("--timeout", type=float, default=30.0, help="reply timeout [s] (default 30)")
    parser.add_argument("--no-wait", action="store_true", help="goal: return after the acknowledgement")
    parser.add_argument("--json", action="store_true", help="print the whole reply body as JSON")
    add_session_arguments(parser, server=False)
    parser.set_defaults(func=_run)


def _print(body: Any) -> None:
    json.dump(body, sys.stdout, indent=2)
    sys.stdout.write("\n")


def _need(args: argparse.Namespace, *names: str) -> None:
    from falcon_plan.errors import InvalidParameterError

    missing = [n for n in names if getattr(args, n) is None]
    if missing:
        flags = ", ".join(f"--{n.replace('_', '-')}" for n in missing)
        raise InvalidParameterError(f"request {args.action} needs {flags}")


def _run(args: argparse.Namespace) -> int:
    from service.client import FalconClient
    from service.config import settings_from_args

    from service.keys import DEFAULT_INSTANCE

    with FalconClient(settings_from_args(args, server=False), prefix=args.prefix,
                      instance=args.instance or DEFAULT_INSTANCE, timeout_s=args.timeout) as client:
        if args.action == "instances":
            _print(client.instances())
        elif args.action == "info":
            _print(client.info())
        elif args.action == "state":
            _print(client.state())
        elif args.action in ("cancel", "result"):
            if not args.goal_id:
                from falcon_plan.errors import InvalidParameterError

                raise InvalidParameterError(f"request {args.action} needs a goal id")
            _print(client.cancel(args.goal_id) if args.action == "cancel" else client.result(args.goal_id))
        elif args.action == "plan":
            _need(args, "start", "goal")
            body = client.plan(args.start, args.goal, args.options, instance=args.instance)
            if args.json:
                _print(body)
            else:
                _print({"instance": body["instance"], "duration_s": body["trajectory"]["duration_s"],
                        "samples": len(body["trajectory"]["t_s"]), "report": body["report"],
                        "timing": body["timing"]})
        else:  # goal
            _need(args, "goal")
            ack = client.submit_goal(args.goal, start_m=args.start, options=args.options, goal_id=args.goal_id)
            print(f"goal {ack['id']} accepted on {ack['instance']} at queue position {ack['position']}",
                  file=sys.stderr)
            if args.no_wait:
                _print(ack)
                return 0
            result = client.wait_result(ack["id"], timeout_s=args.timeout, on_progress=lambda p: print(
                f"  {p['phase']}: {100 * p['fraction']:.0f} %", file=sys.stderr))
            _print(result)
            return 0 if result["status"] == "done" else 1
    return 0
