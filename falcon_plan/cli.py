"""falcon-plan: plan, simulate, execute and serve minimum-time motions of the Novint Falcon.

The command line is a dispatcher over the subcommand modules. Each subcommand lives in ``falcon_plan/commands/<name>.py`` and defines
``register(subparsers) -> None`` (adds its parser and sets ``func``). The log level comes from
the environment variable FALCON_PLAN_LOG (default WARNING).
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

COMMAND_MODULES = ("characterise", "simulate", "plan", "bench", "execute", "home", "serve",
                   "request", "discrepancy", "experiment", "calibrate", "demo")


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every available subcommand."""
    parser = argparse.ArgumentParser(prog="falcon-plan", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        module_name = f"falcon_plan.commands.{name}"
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name == module_name:
                continue  # subcommand not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``falcon-plan`` command; returns the process exit code."""
    logging.basicConfig(level=os.environ.get("FALCON_PLAN_LOG", "WARNING").upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    parser = build_parser()
    args = parser.parse_args(argv)
    from falcon_plan.errors import FalconPlanError
    try:
        return int(args.func(args) or 0)
    except FalconPlanError as exc:
        print(f"falcon-plan {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"falcon-plan {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
