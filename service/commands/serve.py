"""``falcon-plan serve``: run one Zenoh service instance owning one device (see service/README.md)."""
from __future__ import annotations

import argparse
from typing import Any


def register(subparsers: Any) -> None:
    """Add the ``serve`` subcommand to ``subparsers`` (the ``falcon-plan`` command line's)."""
    from service.main import add_serve_arguments

    parser = subparsers.add_parser(
        "serve", help="run the Zenoh planning service (peer mode, loopback by default)",
        description="Serve plan requests and goals over Zenoh under <prefix>/<instance>/... "
                    "(keys and payloads: service/README.md). Stops cleanly on Ctrl-C or SIGTERM.")
    add_serve_arguments(parser)
    parser.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from service.main import run

    return run(args)
