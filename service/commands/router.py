"""``falcon-plan router``: a Zenoh router for service instances and clients in client mode."""
from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    """Add the ``router`` subcommand to ``subparsers`` (the ``falcon-plan`` command line's)."""
    from service.config import DEFAULT_ENDPOINT

    parser = subparsers.add_parser(
        "router", help="run a Zenoh router (for `serve --mode client` and clients, without zenohd)",
        description="Route between Zenoh sessions in client mode (service instances and clients on any machine "
                    "that reaches LISTEN). Loopback and multicast scouting off by default. Stops on Ctrl-C or SIGTERM.")
    parser.add_argument("--listen", action="append", metavar="ENDPOINT",
                        help=f"endpoint to listen on, repeatable (default {DEFAULT_ENDPOINT})")
    parser.add_argument("--connect", action="append", metavar="ENDPOINT", help="another router to join, repeatable")
    parser.add_argument("--zenoh-config", metavar="FILE", help="JSON5 zenoh config file to start from")
    parser.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                        help="zenoh config override, JSON5 value, repeatable")
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from service.config import SessionSettings
    from service.router import serve_router

    return serve_router(SessionSettings.router(args.listen, args.connect or (), args.zenoh_config, args.cfg))
