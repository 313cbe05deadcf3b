"""``falcon-plan convert IN --out OUT``: a falcon log (CSV) to an MCAP recording and back, or a
recording cut short (its writer was killed) to a complete one.

The formats come from the file names: ``.csv`` is a falcon log, ``.mcap`` an MCAP recording
(:mod:`falcon_plan.recording`). CSV -> MCAP writes the channels a run records (legs, commands,
reference, end effector, tracking error, the 3D scene); MCAP -> CSV writes the falcon log the
recording holds; MCAP -> MCAP copies every channel and metadata record of a recording, so a
file cut short (no footer, e.g. ``invalid magic bytes in Footer`` in PlotJuggler) opens
everywhere again. Outputs are written whole (a temporary file renamed into place).
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from falcon_plan.commands import common
from falcon_plan.errors import InvalidParameterError

FORMATS = (".csv", ".mcap")


def register(subparsers: Any) -> None:
    """Add the ``convert`` subcommand to ``subparsers`` (the ``falcon-plan`` parser's subcommands)."""
    parser = subparsers.add_parser("convert", help="falcon log <-> MCAP recording; complete a cut-short recording",
                                   description=__doc__)
    parser.add_argument("source", type=common.input_file, metavar="IN", help="a falcon log (.csv) or an MCAP "
                        "recording (.mcap)")
    parser.add_argument("--out", required=True, type=common.output_file, metavar="OUT",
                        help="the file to write: .mcap (an MCAP recording) or .csv (a falcon log)")
    common.add_json_option(parser)
    parser.set_defaults(func=run)


def _format(path: Path, role: str) -> str:
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise InvalidParameterError(f"{role} {path}: the name must end in .csv (falcon log) or .mcap (MCAP recording)")
    return suffix


def run(args: argparse.Namespace) -> int:
    """Convert ``args.source`` into ``args.out``; exit code 0."""
    from falcon_plan.falconlog import read_log, write_log
    from falcon_plan.recording.mcapfile import copy_recording, is_mcap

    source, target = Path(args.source), Path(args.out)
    _format(source, "IN")
    if source.resolve() == target.resolve():
        raise InvalidParameterError(f"IN and --out are the same file ({source}); write to another name")
    if _format(target, "--out") == ".mcap" and is_mcap(source):
        contents = copy_recording(source, target)
        summary = {"in": str(source), "out": str(target), "messages": len(contents.messages),
                   "complete_before": contents.complete}
        note = "" if contents.complete else " (the input was cut short: it now has its footer)"
        text = f"{len(contents.messages)} messages -> {target}{note}"
    else:
        log = read_log(source)
        if len(log) == 0:
            raise InvalidParameterError(f"IN {source}: the log has a header and no rows: nothing to convert "
                                        "(was its run stopped before the first sample?)")
        write_log(target, log)
        summary = {"in": str(source), "out": str(target), "rows": len(log)}
        text = f"{len(log)} rows -> {target}"
    if args.json:
        common.print_json(summary)
    else:
        print(text)
    return 0
