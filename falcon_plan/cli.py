"""falcon-plan: plan, simulate, execute and serve minimum-time motions of the Novint Falcon.

The command line is a dispatcher over the subcommand modules. Each of the library's
subcommands lives in ``falcon_plan/commands/<name>.py`` and defines ``register(subparsers) ->
None`` (adds its parser and sets ``func``); what they share is in
:mod:`falcon_plan.commands.common`. Applications built on the library add their own
subcommands without the library importing them: a ``register`` function declared in the
entry-point group ``falcon_plan.commands`` (COMMAND_ENTRY_POINTS) is called the same way. The
service's ``serve``, ``request``, ``demo`` and ``router`` come in that way (pyproject.toml).

Errors: every failure ends in one line on stderr, ``falcon-plan COMMAND: error: ...``, naming
the problem and what is allowed. Exit status 2 for bad usage or input (options, files,
points outside the workspace), 1 for a run that failed (planning, device, safety stop),
130 when interrupted. ``--debug`` adds the traceback. The log level comes from the
environment variable FALCON_PLAN_LOG (default WARNING).
"""
from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import logging
import os
import re
import sys
import textwrap
import traceback
from typing import Any, NoReturn

COMMAND_MODULES = ("characterise", "simulate", "plan", "bench", "execute", "home", "discrepancy",
                   "experiment", "calibrate", "doctor", "convert")
"""The library's own subcommands (modules of :mod:`falcon_plan.commands`), in help order."""
COMMAND_ENTRY_POINTS = "falcon_plan.commands"
"""Entry-point group of the subcommands that installed applications add (each names a
``register(subparsers) -> None`` function); listed after the library's own."""

MAX_MESSAGE_CHARS = 400
"""An error line longer than this is cut (a message must never carry a whole file)."""

EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

_COMMAND_PREFIX = re.compile(r"^falcon-plan [a-z |]+: ")
_ROLE = re.compile(r":(?:mod|class|func|meth|attr|data|exc):`~?([^`]+)`")


def plain_text(doc: str | None) -> str | None:
    """The docstring ``doc`` as help text: reST roles and double backquotes removed (None
    stays None)."""
    if doc is None:
        return None
    text = _ROLE.sub(lambda m: m.group(1).rsplit(".", 1)[-1] if "~" in m.group(0) else m.group(1), doc)
    text, prefixed = _COMMAND_PREFIX.subn("", text.replace("``", "").strip())
    return text[:1].upper() + text[1:] if prefixed else text


class HelpFormatter(argparse.HelpFormatter):
    """Wraps each paragraph of a description (keeping indented blocks and list items as
    written) and shows each option's default."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        paragraphs = []
        for block in text.strip("\n").split("\n\n"):
            lines = block.splitlines()
            if any(line.startswith((" ", "-")) for line in lines):
                paragraphs.append("\n".join(indent + line for line in lines))
            else:
                paragraphs.append(textwrap.fill(" ".join(lines), width, initial_indent=indent,
                                                subsequent_indent=indent))
        return "\n\n".join(paragraphs)

    def _format_args(self, action: argparse.Action, default_metavar: str) -> str:
        if getattr(action, "one_metavar", False):  # a point: X,Y,Z (three numbers also accepted)
            return str(action.metavar)
        return super()._format_args(action, default_metavar)

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        hidden = (default is None or isinstance(default, bool) or default is argparse.SUPPRESS
                  or (isinstance(default, (list, str)) and not default))
        if action.option_strings and not action.required and "default" not in text.lower() and not hidden:
            if isinstance(default, tuple):
                shown = ",".join(f"{v:g}" for v in default)
            elif isinstance(default, float):
                shown = f"{default:g}"
            else:
                shown = "%(default)s"
            text += f" (default {shown})"
        return text


NEGATIVE_VALUE = re.compile(r"^-\.?\d[\d.eE+\-, ]*$")
"""An argument that starts with a minus and holds only numbers, commas and spaces: a value
(a negative number, or a point such as ``-0.03,0,0.14``), never an option."""


class Parser(argparse.ArgumentParser):
    """The ``falcon-plan`` parsers: plain-text descriptions, defaults shown, usage errors as
    one line (exit status 2), and values that start with a minus taken as values
    (``--to -0.03,0,0.14``; argparse alone reads only a plain negative number so)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        kwargs["description"] = plain_text(kwargs.get("description"))
        super().__init__(*args, **kwargs)
        # argparse's own test for "a negative number, not an option" (no option of ours looks
        # like one), widened to points
        self._negative_number_matcher = NEGATIVE_VALUE
        self.set_defaults(command_name=self.prog)  # the deepest parser's wins: "falcon-plan simulate step"

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {_one_line(message)} (see {self.prog} --help)\n")


def _describe(sub: argparse._SubParsersAction) -> None:
    """Give every subcommand without a description its one-line help, recursively."""
    helps = {action.dest: action.help for action in sub._choices_actions}
    for name, parser in sub.choices.items():
        if not parser.description and helps.get(name):
            parser.description = helps[name][0].upper() + helps[name][1:] + "."
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                _describe(action)


def version() -> str:
    """The installed version of falcon-plan."""
    from falcon_plan import __version__

    return __version__


def plugin_commands() -> list[importlib.metadata.EntryPoint]:
    """The subcommands installed applications declare under COMMAND_ENTRY_POINTS, in the
    order their installed metadata lists them."""
    return list(importlib.metadata.entry_points(group=COMMAND_ENTRY_POINTS))


def command_names() -> list[str]:
    """Names of every subcommand: the library's own, then those of installed applications."""
    return [*COMMAND_MODULES, *(entry.name for entry in plugin_commands())]


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every available subcommand (the library's and the
    installed applications')."""
    parser = Parser(prog="falcon-plan", description=__doc__.split("\n\n")[0],
                    epilog="Points are X,Y,Z in metres (base frame: x right, y up, z toward the user); "
                           "rates default to 800 Hz (1 kHz on a device with 1 ms USB frames); "
                           "'falcon-plan COMMAND --help' for each command.")
    parser.add_argument("--version", action="version", version=f"falcon-plan {version()}")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(f"falcon_plan.commands.{name}").register(sub)
    for entry in plugin_commands():
        entry.load()(sub)
    _describe(sub)
    return parser


def _one_line(text: str) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= MAX_MESSAGE_CHARS else line[:MAX_MESSAGE_CHARS - 3] + "..."


def _classify(exc: BaseException) -> tuple[int, str]:
    """Exit status and message for an exception that ended a command."""
    from falcon_plan.errors import (FalconPlanError, InvalidParameterError, InvalidProblemError,
                                    LogFormatError, OutputError, WorkspaceError)

    usage = (InvalidParameterError, InvalidProblemError, WorkspaceError, LogFormatError, OutputError)
    if isinstance(exc, usage):
        return EXIT_USAGE, str(exc)
    if isinstance(exc, FalconPlanError):
        # the service's error replies carry what is allowed and whether the request's own
        # content was refused (service.client.ServiceError.bad_input): that is bad input too
        allowed = getattr(exc, "allowed", None)
        message = str(exc) if not allowed or "allowed" in str(exc) else f"{exc}; allowed: {allowed}"
        return (EXIT_USAGE if getattr(exc, "bad_input", False) else EXIT_FAILED), message
    if isinstance(exc, (FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError)):
        where = exc.filename or ""
        return EXIT_USAGE, f"{where}: {exc.strerror}" if where else str(exc)
    if isinstance(exc, OSError):
        return EXIT_FAILED, f"{exc.filename + ': ' if exc.filename else ''}{exc.strerror or exc}"
    return EXIT_FAILED, (f"unexpected {type(exc).__name__}: {exc} (a bug: please report it with the "
                         "output of --debug)")


class _PlainFormatter(logging.Formatter):
    """Log records as the command's own lines: ``falcon-plan: warning: ...``."""

    def format(self, record: logging.LogRecord) -> str:
        return f"falcon-plan: {record.levelname.lower()}: {record.getMessage()}"


def _configure_logging() -> None:
    """Warnings and errors of the library on stderr, as the command's own lines; with
    FALCON_PLAN_LOG set (a level), every record at that level with time, level and logger."""
    level = os.environ.get("FALCON_PLAN_LOG")
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s") if level
                         else _PlainFormatter())
    logging.basicConfig(level=(level or "WARNING").upper(), handlers=[handler])
    # compiling kernels takes seconds to a minute on a fresh machine: always say so
    compiled = logging.getLogger("falcon_plan.compiled")
    if compiled.getEffectiveLevel() > logging.INFO and compiled.propagate:  # once per process
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("falcon-plan: %(message)s"))
        handler.addFilter(lambda record: record.levelno == logging.INFO)
        compiled.addHandler(handler)
        compiled.setLevel(logging.INFO)
        compiled.propagate = False


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``falcon-plan`` command: run the command line ``argv`` (default:
    the process's arguments); returns the process exit code.

    Ctrl-C at any point (while the parsers are built, in the command) ends it with one line,
    ``falcon-plan COMMAND: interrupted``, and status 130. Run as the process's entry point
    (``argv`` None), a Ctrl-C once the command has ended is ignored: the interpreter's exit
    would otherwise die of it (no status, no line) or print a traceback."""
    entry = argv is None
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv  # accepted anywhere on the line, not only before the command
    argv = [a for a in argv if a != "--debug"]
    name = "falcon-plan"
    try:
        _configure_logging()
        parser = build_parser()
        args = parser.parse_args(argv)
        name = args.command_name
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except SystemExit as exc:
        signum = getattr(exc, "signum", None)     # a devices.base.SignalExit: zero force was sent first
        if signum is None:
            raise
        from falcon_plan.commands.common import say_if_possible

        say_if_possible(f"{name}: terminated by {signal_name(signum)}")
        return int(exc.code)
    except Exception as exc:  # noqa: BLE001 - the one place that turns errors into a line
        status, message = _classify(exc)
        if debug:
            traceback.print_exc()
        print(f"{name}: error: {_one_line(message)}", file=sys.stderr)
        return status
    finally:
        if entry:
            _ignore_interrupts_from_now()


def signal_name(signum: int) -> str:
    """``signum``'s name, e.g. SIGTERM."""
    import signal

    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def _ignore_interrupts_from_now() -> None:
    """Ignore SIGINT for the rest of this process (its command has ended), if this is the
    main thread (where handlers can be set)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


if __name__ == "__main__":
    sys.exit(main())
