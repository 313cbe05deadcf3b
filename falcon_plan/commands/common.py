"""What every subcommand shares: points, rates, input and output files, JSON, progress.

Conventions of the command line (the service client and the Python API use the same ones):

- a point is one argument ``X,Y,Z`` in metres, base frame (x right, y up, z toward the user);
  ``--from``/``--to`` name the start and the goal everywhere (``--start``/``--goal`` are
  accepted as aliases, and three separate numbers as the older form);
- the control rate is ``--rate`` in Hz, 800 by default (the paper's rate), 1000 on a device
  whose packets move in 1 ms USB frames;
- human output is compact and in mm; ``--json`` prints the whole result for machines;
- outputs are checked before any work starts and written atomically with mode 0644;
- waits longer than about a second print progress on stderr.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from falcon_plan.errors import InvalidParameterError
from falcon_plan.fileio import check_writable, write_text

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.effects import Effects
    from falcon_plan.planning.report import Plan
    from falcon_plan.planning.problem import PlanOptions
    from falcon_plan.trajectory import Trajectory

DEFAULT_RATE_HZ = 800.0
"""The control rate of every command unless ``--rate`` says otherwise [Hz] (the paper's),
except on a device whose packets move in USB frames (:data:`FRAME_RATE_HZ`)."""
FRAME_RATE_HZ = 1000.0
"""The default loop rate on a device whose packets move in 1 ms USB frames (a real Falcon, the
emulated one with frame timing) [Hz]: one period a frame keeps one phase against the frames
for a whole run (:class:`~falcon_plan.timing.ArrivalLock`); at 800 Hz the loop's delay changes
from tick to tick (emulated Falcon, wall clock, LQR, ``execute --to 0.03,0.02,0.14``: 0.22 mm
RMS at 800 Hz, 0.03 mm at 1 kHz). The service runs such devices at this rate too."""

PROGRESS_AFTER_S = 1.0
"""A wait prints progress once it has lasted this long [s]."""


# --- points --------------------------------------------------------------------------------

def parse_point(text: str) -> tuple[float, float, float]:
    """``text`` ``"X,Y,Z"`` in metres (spaces also separate) -> (x, y, z) [m]; an argparse
    error naming the form otherwise (a point outside the workspace is the planner's error,
    with the extent and a mm hint)."""
    try:
        values = tuple(float(v) for v in text.replace(" ", ",").split(",") if v != "")
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in metres (e.g. 0.02,-0.01,0.13), got {text!r}")
    return values  # type: ignore[return-value]


class _PointAction(argparse.Action):
    """Takes ``X,Y,Z`` (one argument) or ``X Y Z`` (three numbers, the older form)."""

    one_metavar = True  # help shows X,Y,Z, not X,Y,Z [X,Y,Z ...]

    def __init__(self, *args: Any, repeat: bool = False, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.repeat = repeat

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        try:
            point = parse_point(",".join(values))
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentError(self, str(exc)) from None
        if self.repeat:
            setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), point])
        else:
            setattr(namespace, self.dest, point)


def add_point_option(parser: argparse.ArgumentParser | Any, *flags: str, dest: str, help: str,
                     required: bool = False, default: Any = None, repeat: bool = False) -> None:
    """Add a point option to ``parser`` (a parser or an argument group): ``--to X,Y,Z`` [m]
    (``--to X Y Z`` also accepted), under the option strings ``flags`` (e.g. ``"--to",
    "--goal"``), stored as an (x, y, z) tuple in ``dest`` with the ``help`` text. It may be
    ``required``; otherwise it is ``default`` when absent. With ``repeat`` it may be given
    several times and collects a list (default empty)."""
    parser.add_argument(*flags, dest=dest, action=_PointAction, nargs="+", metavar="X,Y,Z", repeat=repeat,
                        required=required, default=[] if repeat else default, help=help)


# --- rates, JSON, files ----------------------------------------------------------------------

def add_rate_option(parser: argparse.ArgumentParser, *, choices: Sequence[int] | None = None,
                    help: str = "control rate [Hz]", default: float | None = DEFAULT_RATE_HZ) -> None:
    """Add ``--rate`` [Hz] to ``parser``, ``default`` by default (800; None: the command
    chooses by its device), with the ``help`` text; with ``choices`` it is one of those whole
    rates, otherwise a number in (0, :data:`MAX_RATE_HZ`]."""
    kwargs: dict[str, Any] = {"type": int, "choices": choices} if choices else {"type": rate_hz}
    if default is not None and choices:
        default = int(default)
    parser.add_argument("--rate", default=default, help=help, **kwargs)


def add_json_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--json`` to ``parser``: print the whole result as JSON instead of the compact
    summary."""
    parser.add_argument("--json", action="store_true",
                        help="print the whole result as JSON (default: a compact summary in mm)")


def mm(point_m: Any) -> str:
    """``point_m``, a point (x, y, z) [m], as ``(x, y, z) mm`` to 0.1 mm, for human output
    ("?" when it is None)."""
    if point_m is None:
        return "?"
    return "(" + ", ".join(f"{round(1e3 * float(v), 1) + 0.0:.1f}" for v in point_m) + ") mm"  # + 0.0: no "-0.0"


def print_json(body: Any) -> None:
    """Print ``body`` as indented JSON on stdout."""
    json.dump(body, sys.stdout, indent=2)
    sys.stdout.write("\n")


def positive_float(text: str) -> float:
    """argparse type: ``text`` as a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


MAX_RATE_HZ = 10_000.0
"""Highest sample rate a command takes [Hz] (a device's loop runs at 800 or 1000 Hz; at 1 MHz a
1 s design was a 554 MB file that took minutes to read)."""


def rate_hz(text: str) -> float:
    """argparse type: ``text`` as a sample rate [Hz] in (0, :data:`MAX_RATE_HZ`]."""
    value = positive_float(text)
    if value > MAX_RATE_HZ:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_RATE_HZ:g} Hz (a device runs at 800 or 1000), "
                                         f"got {text!r}")
    return value


def positive_int(text: str) -> int:
    """argparse type: ``text`` as a whole number > 0."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive whole number, got {text!r}")
    return value


def say_if_possible(text: str) -> None:
    """``text`` on stderr, if there still is one (a closed terminal's SIGHUP leaves none)."""
    try:
        print(text, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def input_file(text: str) -> Path:
    """argparse type: ``text`` naming an existing, readable file, as a Path."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"no such file: {text}")
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"{text} is not a file")
    try:
        with path.open("rb"):
            pass
    except OSError as exc:
        raise argparse.ArgumentTypeError(f"cannot read {text}: {exc.strerror}") from None
    return path


def add_model_option(parser: argparse.ArgumentParser | Any, help: str) -> None:
    """Add ``--model FILE`` to ``parser`` with the ``help`` text: a model file (what
    ``discrepancy`` and ``calibrate`` write); default None (the nominal model)."""
    parser.add_argument("--model", type=input_file, default=None, metavar="FILE", help=help)


def output_file(text: str) -> Path:
    """argparse type: ``text`` naming a file that can be written (its folder exists and is
    writable), as a Path."""
    try:
        return check_writable(text)
    except OSError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


OUTPUT_FORMATS = {".png": "a PNG image", ".json": "JSON", ".csv": "a falcon log (CSV)",
                  ".mcap": "an MCAP recording"}
"""The formats output files are written in, by the file name's ending."""


def output_file_as(*suffixes: str) -> Any:
    """argparse type: like :func:`output_file`, for a file written in the format
    OUTPUT_FORMATS names for its ending, one of ``suffixes`` (e.g. ``".png"``); another ending
    is refused (a ``.jpg`` name would hold PNG bytes)."""
    what = " or ".join(OUTPUT_FORMATS[s] for s in suffixes)

    def check(text: str) -> Path:
        path = output_file(text)  # a missing folder, or a folder given, is said first
        if path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(
                f"{text!r}: this file is written as {what}: give a name ending in "
                f"{' or '.join(suffixes)}")
        return path

    check.__name__ = "FILE" + "|".join(suffixes)  # argparse names the type so in its messages
    return check


def write_json(path: str | Path, body: Any, what: str = "output") -> Path:
    """Write ``body`` as indented JSON to ``path`` (atomic, mode 0644); ``what`` names the
    output in an error message."""
    return write_text(path, json.dumps(body, indent=2) + "\n", what)


def write_trajectory(path: str | Path, trajectory: Trajectory) -> Path:
    """Write the JSON of ``trajectory`` to ``path`` (atomic, mode 0644)."""
    return write_text(path, trajectory.to_json(), "trajectory")


def read_trajectory(path: str | Path) -> Trajectory:
    """The Trajectory in the JSON file at ``path``, with one-line errors naming the file and
    the problem."""
    from falcon_plan.trajectory import Trajectory

    try:
        return Trajectory.from_dict(load_json_object(str(path), f"trajectory {path}"))
    except InvalidParameterError:
        raise
    except (TypeError, ValueError) as exc:  # InvalidProblemError included: fields of bad shape
        raise InvalidParameterError(f"trajectory {path}: {exc}") from None


def checked_for_device(trajectory: Trajectory, path: str | Path, model: Any, rate_hz: float) -> Trajectory:
    """``trajectory`` (read from ``path``), checked before any device runs it for ``model`` at
    ``rate_hz`` [Hz] (:func:`~falcon_plan.planning.verify.require_executable`: a node outside
    the workspace, a jump, or more command than the device has is refused; such a file used to
    run until the tracking trip let the grip go); its notes (another sampling rate, more than
    the speed-dependent limit) go to stderr."""
    from falcon_plan.planning.verify import require_executable

    for note in (rate_note(trajectory, rate_hz), require_executable(model, trajectory, f"trajectory {path}")):
        if note:
            print(note if note.startswith("note:") else f"note: {note}", file=sys.stderr)
    return trajectory


def sample_rate_hz(trajectory: Trajectory) -> float | None:
    """The rate a trajectory was sampled at [Hz]: its ``rate_hz`` metadata, else 1/dt when its
    samples are evenly spaced (at least 50 of them); None for a planner's uneven nodes."""
    if "rate_hz" in trajectory.meta:
        return float(trajectory.meta["rate_hz"])
    dt = np.diff(trajectory.t_s[:-1])  # the last interval may be a partial one
    if len(dt) >= 50 and np.ptp(dt) < 1e-9 + 1e-6 * dt.mean():
        return float(1.0 / dt.mean())
    return None


def rate_note(trajectory: Trajectory, rate_hz: float) -> str | None:
    """A note when ``trajectory``, sampled at one rate, is run at another, ``rate_hz`` [Hz]
    (it is re-sampled); None when the rates agree or the sampling rate is unknown."""
    sampled = sample_rate_hz(trajectory)
    if sampled is None or abs(sampled - rate_hz) < 1e-6 * rate_hz:
        return None
    return (f"note: the trajectory was sampled at {sampled:g} Hz and runs at {rate_hz:g} Hz "
            f"(re-sampled; --rate {sampled:g} runs it as recorded)")


@contextmanager
def run_log(log: Path | None, plot: Path | None) -> Iterator[Path | None]:
    """The falcon log a run writes: ``log`` if given; for a plot without a log, a temporary
    one removed afterwards; None when neither is asked for."""
    if log is not None or plot is None:
        yield log
        return
    import tempfile

    with tempfile.TemporaryDirectory(prefix="falcon-plan-run-") as folder:
        yield Path(folder) / "run.csv"


def add_live_options(parser: argparse.ArgumentParser, flag: str = "--live", what: str = "the run") -> None:
    """Add to ``parser`` the options of a Foxglove live view: ``flag`` (show ``what`` live: a
    WebSocket server on loopback) and ``flag-port`` (its port). :func:`live_port` reads them."""
    from falcon_plan.recording.live import DEFAULT_PORT, HOST

    parser.add_argument(flag, action="store_true",
                        help=f"show {what} live in Foxglove: a WebSocket server on {HOST} (open ws://{HOST}:PORT; "
                             "layout: docs/foxglove-layout.json)")
    parser.add_argument(f"{flag}-port", type=_port, default=DEFAULT_PORT, metavar="PORT",
                        help=f"port of the {flag} server (default {DEFAULT_PORT}; 0: any free port)")


def _port(text: str) -> int:
    from falcon_plan.recording.live import check_port

    try:
        return check_port(int(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"a port is a whole number in 0..65535, got {text!r}") from None


def live_port(args: argparse.Namespace, flag: str = "--live") -> int | None:
    """The port of the live view that ``args`` ask for with ``flag`` (see
    :func:`add_live_options`), or None when they ask for none."""
    name = flag.lstrip("-").replace("-", "_")
    return getattr(args, f"{name}_port") if getattr(args, name, False) else None


def add_recording_options(parser: argparse.ArgumentParser) -> None:
    """Add to ``parser`` the options that record a run for robotics tools: ``--mcap FILE.mcap``
    (an MCAP recording beside the falcon log), ``--live`` and ``--live-port`` (a Foxglove
    WebSocket server on loopback showing the run while it goes)."""
    parser.add_argument("--mcap", type=output_file_as(".mcap"), default=None, metavar="FILE.mcap",
                        help="also record the run as an MCAP file (open it in Foxglove or PlotJuggler; "
                             "channels in falcon_plan/recording/channels.py)")
    add_live_options(parser)


@contextmanager
def live_view(args: argparse.Namespace) -> Iterator[Any]:
    """The Foxglove live view ``args`` ask for (``--live``; its address printed on stderr), or
    None; stopped at the end of the block."""
    port = live_port(args)
    if port is None:
        yield None
        return
    from falcon_plan.recording.live import LiveView

    with LiveView(port=port) as live:
        print(f"falcon-plan: live view at {live.url} (Foxglove: Open connection -> Foxglove WebSocket)",
              file=sys.stderr, flush=True)
        yield live


def plot_path(plot: Path | None, out: Path | None) -> Path | None:
    """Where the plot goes: ``--plot`` if given, else next to ``--out`` with ``.png``."""
    if plot is not None:
        return plot
    return None if out is None else out.with_suffix(".png")


def load_json_object(text: str, option: str) -> dict[str, Any]:
    """The JSON object in ``text``, given inline (``{...}``) or as a file path; one-line
    errors naming ``option`` (the command-line option it came from)."""
    if text.lstrip().startswith(("{", "[")):
        source = text
    else:
        try:
            source = Path(text).read_text()
        except OSError as exc:
            raise InvalidParameterError(f"{option}: cannot read {text!r} ({exc.strerror}); give a JSON "
                                        "object inline ('{...}') or a JSON file") from None
    try:
        data = json.loads(source)
    except json.JSONDecodeError as exc:
        raise InvalidParameterError(f"{option}: not valid JSON ({exc.msg} at line {exc.lineno} "
                                    f"column {exc.colno})") from None
    if not isinstance(data, dict):
        raise InvalidParameterError(f"{option} must be a JSON object, got {type(data).__name__}")
    return data


# --- effects -------------------------------------------------------------------------------

def effect_fields() -> str:
    """The effect fields with their nominal values, for help texts and errors."""
    from falcon_plan.model.effects import Effects

    return ", ".join(f"{f.name} ({f.default:g})" for f in dataclasses.fields(Effects))


EFFECTS_HELP = ("effects of the simulated device: name=value pairs (coulomb_Nm=0.01,backlash_rad=0.002), "
                "a JSON object or a JSON file. Fields (nominal value): {fields}")


def load_effects(text: str | None) -> Effects:
    """:class:`Effects` from ``text``: ``name=value,...``, a JSON object or a JSON file (None
    or empty: nominal); one-line errors that list the fields."""
    from falcon_plan.model.effects import Effects

    if not text or not text.strip():
        return Effects()
    if "=" in text and not text.lstrip().startswith("{"):
        data: dict[str, Any] = {}
        for pair in text.replace(" ", ",").split(","):
            name, sep, value = pair.partition("=")
            try:
                data[name.strip()] = value.strip() if value.strip() == "inf" else float(value)
            except ValueError:
                sep = ""
            if not sep or not name.strip():
                raise InvalidParameterError(f"--effects: {pair!r} is not name=number; fields: {effect_fields()}")
    else:
        data = load_json_object(text, "--effects")
    try:
        return Effects.from_dict(data)
    except (TypeError, ValueError) as exc:
        hint = "" if "allowed" in str(exc) else f"; fields: {effect_fields()}"
        raise InvalidParameterError(f"--effects: {exc}{hint}") from None


def controller_text(text: str) -> str:
    """argparse type: ``text`` naming a controller the replay can reproduce (``pd kp=NUMBER
    kd=NUMBER`` or ``lqr``, with the optional words of :mod:`falcon_plan.control`), or ``open-loop``;
    returned unchanged."""
    from falcon_plan.control import OPEN_LOOP, Controller
    from falcon_plan.errors import FalconPlanError

    if text.strip() == OPEN_LOOP:
        return OPEN_LOOP
    try:
        Controller.from_meta({}, text=text, rate_hz=DEFAULT_RATE_HZ)
    except (FalconPlanError, ValueError) as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


# --- progress ------------------------------------------------------------------------------

def step_printer(name: str) -> Any:
    """A progress callback for a command's steps: each call prints ``name [  t s] text`` on
    stderr (``name`` e.g. "calibrate"), ``t`` the seconds since this was made."""
    start = time.perf_counter()

    def say(text: str) -> None:
        print(f"{name} [{time.perf_counter() - start:5.1f} s] {text}", file=sys.stderr, flush=True)

    return say


@contextmanager
def progress(message: str, *, every_s: float = 5.0, stream: Any = None) -> Iterator[None]:
    """Say ``message ...`` on stderr once the block has run for :data:`PROGRESS_AFTER_S`, then
    the elapsed time every ``every_s`` [s] and when it ends; quick blocks print nothing.
    ``stream``: a text stream to print to instead of stderr."""
    done = threading.Event()
    start = time.perf_counter()
    said = []

    def say(text: str) -> None:
        print(f"falcon-plan: {text}", file=stream or sys.stderr, flush=True)

    def watch() -> None:
        if done.wait(PROGRESS_AFTER_S):
            return
        said.append(True)
        say(f"{message} ...")
        while not done.wait(every_s):
            say(f"{message} ... {time.perf_counter() - start:.0f} s")

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        yield
    finally:
        done.set()
        watcher.join()
        if said:
            say(f"{message}: {time.perf_counter() - start:.1f} s")


def plan_with_progress(start_m: Any, goal_m: Any, options: PlanOptions, model: FalconModel, *, via_m: Any = (),
                       payload_kg: float = 0.0) -> Plan:
    """:func:`falcon_plan.planning.api.plan` for the command line: the problem is checked first
    (bad input is refused before any wait), the planner is prepared apart (its set-up in this
    process, and on a fresh machine the compilation of its kernels, are not planning time) and
    both waits show progress.

    ``start_m``, ``goal_m`` and the ``via_m`` points are (x, y, z) [m], base frame;
    ``payload_kg`` is an extra point mass at the end effector [kg]; ``options`` are the
    planner's ``PlanOptions`` and ``model`` the dynamics planned with. Returns the planner's
    ``Plan`` (trajectory and report)."""
    from falcon_plan.planning.api import plan_problem
    from falcon_plan.planning.pipeline import require_holdable, require_nonzero_move
    from falcon_plan.planning.problem import PlanProblem

    problem = PlanProblem(start_m, goal_m, via_m=via_m, payload_kg=payload_kg)
    require_nonzero_move(problem)
    problem.require_in_workspace(model)
    require_holdable(model, problem, options.command_bound(model.params))
    prepare_planner(model, options)
    with progress("planning"):
        return plan_problem(problem, options, model)


def prepare_planner(model: FalconModel, options: PlanOptions) -> None:
    """Set up the planner for ``model`` and ``options`` (the planner's ``PlanOptions``; the
    plant too when ``options.checks.plant_check`` runs the plan on it) before planning, with
    progress: its CasADi graphs are built and its compiled kernels loaded (~0.2 s), or on a
    fresh machine compiled once (5-60 s, each compilation said on stderr, then a line with
    their number). The ruckig fallback is left to the plan that needs it."""
    from falcon_plan.planning.api import warm_up

    with preparing("the planner"):
        warm_up(model, options, prepare_fallback=False)
        if options.checks.plant_check:  # the plan's closed-loop check on the plant
            from falcon_plan.control import Controller
            from falcon_plan.model.kinematics import FK_COMPILED_MIN_POINTS, position_to_counts
            from falcon_plan.sim.plant import SimPlant

            plant, home_m = SimPlant(model), (0.0, 0.0, 0.12)
            plant.reset(home_m, np.zeros(3))
            # a hold long enough that the reference's kinematics take the compiled path, as the plan's run does
            hold = np.repeat(position_to_counts(home_m, model.params)[None, :], FK_COMPILED_MIN_POINTS, axis=0)
            Controller.executor_default(plant.rate_hz, model).run_on(plant, hold, model)


@contextmanager
def preparing(what: str) -> Iterator[None]:
    """Progress for a set-up (``what``, e.g. "the planner"): ``preparing WHAT ...`` once it has
    run for :data:`PROGRESS_AFTER_S`, and after it a line with the number of kernels compiled
    only if any was (once per machine, then cached): loading cached kernels is not compiling."""
    from falcon_plan.compiled import build

    compiled_before = build.compilations
    with progress(f"preparing {what}"):
        yield
    compiled = build.compilations - compiled_before
    if compiled:
        print(f"falcon-plan: compiled {compiled} kernel{'s' if compiled > 1 else ''} (once per machine, "
              f"then cached in {build.cache_dir()})", file=sys.stderr, flush=True)


__all__ = ["DEFAULT_RATE_HZ", "FRAME_RATE_HZ", "EFFECTS_HELP", "add_json_option", "add_point_option", "add_rate_option",
           "add_live_options", "add_recording_options", "live_port", "live_view",
           "controller_text", "effect_fields", "input_file", "load_effects", "load_json_object", "mm",
           "output_file", "output_file_as", "parse_point", "step_printer", "plan_with_progress", "plot_path", "positive_float", "positive_int",
           "prepare_planner", "preparing",
           "print_json", "progress", "write_json"]
