"""``falcon-plan bench``: run the benchmark problems and write the results table, summary and plots.

    falcon-plan bench [problems/ ...] --out DIR [--seed S] [--jobs N] [--only NAME ...] [--quick]

Progress (k/N done, elapsed, ETA) goes to stderr; the summary's headline to stdout. Exit code
0 when every problem met its expectation, 1 when some did not, 2 on bad input.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TextIO

from falcon_plan.commands import common

DEFAULT_PROBLEMS = "problems"


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``bench`` subcommand to ``subparsers`` (the ``falcon-plan`` parser's
    subcommands)."""
    parser = subparsers.add_parser("bench", help="run the benchmark problems (plan, cross-check, execute)",
                                   description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", type=Path, default=[Path(DEFAULT_PROBLEMS)],
                        help="problem files or folders of *.json (default: problems/)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the results")
    parser.add_argument("--seed", type=int, default=0, help="global seed (default 0)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="worker processes (default: the number of cores)")
    parser.add_argument("--only", nargs="+", metavar="NAME", default=None, help="run only these problems")
    parser.add_argument("--quick", action="store_true",
                        help="coarse planner grid, for a smoke run (not benchmark figures)")
    parser.add_argument("--no-execute", dest="execute", action="store_false",
                        help="do not run the plans on the simulated plant")
    common.add_json_option(parser)
    common.add_model_option(parser, "model file to plan and execute with; the simulated device "
                                    "simulates that model (default: nominal acra2009)")
    parser.set_defaults(func=run)


class ProgressPrinter:
    """Prints ``bench: k/N done (name), elapsed, ETA`` lines to a stream (stderr)."""

    def __init__(self, stream: TextIO | None = None) -> None:
        # None: the current sys.stderr at each call (a default bound at import time would keep
        # a stream that may since have been replaced and closed)
        self.stream = stream

    def __call__(self, done: int, total: int, name: str, elapsed_s: float) -> None:
        eta_s = elapsed_s / done * (total - done) if done else float("nan")
        print(f"bench: {done}/{total} done ({name}), elapsed {elapsed_s:.1f} s, ETA {eta_s:.0f} s",
              file=self.stream or sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Load, run and write; returns the exit code."""
    from falcon_plan.batch.loader import load_problems, select_problems
    from falcon_plan.batch.runner import RunOptions, run_batch
    from falcon_plan.batch.summary import summarise, write_results

    problems = load_problems(args.paths)
    if args.only:
        problems = select_problems(problems, args.only)
    if args.model is not None:
        from falcon_plan.model.modelfile import load_model

        load_model(args.model)  # a bad file is one clear error here, not one per problem
    options = RunOptions(seed=args.seed, jobs=args.jobs, quick=args.quick, execute=args.execute,
                         model_path=None if args.model is None else str(args.model))
    print(f"bench: {len(problems)} problems, {options.workers} job(s), seed {options.seed}"
          f"{', quick' if options.quick else ''}", file=sys.stderr, flush=True)
    result = run_batch(problems, options, progress=ProgressPrinter())
    summary = summarise(result)
    paths = write_results(result, args.out, summary)
    planner = summary["methods"]["casadi"]
    if args.json:
        common.print_json(json.loads(paths["summary.json"].read_text()))
        return 0 if summary["all_met"] else 1
    print(f"{summary['problems']} problems in {summary['wall_time_s']:.1f} s: "
          f"{planner['met']}/{planner['problems']} met their expectation; results in {paths['results.md'].parent}")
    if summary["unavailable"]:
        print(f"unavailable: {', '.join(summary['unavailable'])}")
    if not summary["all_met"]:
        print(f"not met: {', '.join(summary['not_met'])}")
        return 1
    return 0
