"""Every subcommand, driven with bad arguments, missing and unwritable files and malformed
inputs, ends in exactly one line on stderr that names the problem (and what is allowed),
never a traceback, with exit status 2 for bad usage or input and 1 for a failed run.

The cases run in-process through ``falcon_plan.cli.main`` (the console script's entry point);
two of them also through a real ``python -m falcon_plan.cli`` process.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from falcon_plan import cli
from falcon_plan.falconlog import FalconLog, write_log

GOOD_TO = "0.02,0.01,0.13"


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """Inputs of every kind: a good falcon log, malformed ones, a big JSON file, bad JSON."""
    d = tmp_path_factory.mktemp("inputs")
    n = 50
    log = FalconLog([k / 800 for k in range(n)], [[k, -k, 0] for k in range(n)], [[0, 0, 0]] * n,
                    meta={"rate_hz": "800", "controller": "pd kp=10 kd=0.1"})
    write_log(d / "good.csv", log)
    (d / "bad_row.csv").write_text("t,enc0,enc1,enc2,tc0,tc1,tc2\n0.0,1,2,3,4,5,6\n0.1,1,2,x,4,5,6\n")
    (d / "big.json").write_text(json.dumps({"t_s": list(range(200_000)), "junk": "x" * 1_000_000}))
    (d / "not_json.json").write_text("{this is not json")
    (d / "binary.json").write_bytes(b"\xff\xfe\x00 not text")
    (d / "binary.csv").write_bytes(b"\xff\xfe\x00 not text")
    (d / "no_rows.csv").write_text("# rate_hz: 800\n# controller: pd kp=10 kd=0.1\nt,enc0,enc1,enc2,tc0,tc1,tc2\n")
    (d / "list.json").write_text("[1, 2, 3]")
    (d / "fields.json").write_text(json.dumps({"t_s": [0, 1]}))
    (d / "shape.json").write_text(json.dumps({k: [[0, 0]] for k in ("position_m", "velocity_m_s",
                                                                     "acceleration_m_s2", "commands")}
                                             | {"t_s": [0.0]}))
    (d / "a_folder").mkdir()
    still = {"t_s": [0.0, 0.01, 0.02], "velocity_m_s": [[0, 0, 0]] * 3, "acceleration_m_s2": [[0, 0, 0]] * 3,
             "commands": [[0, 0, 0]] * 3}
    (d / "outside.json").write_text(json.dumps(still | {"position_m": [[0, 0, 0.12], [0, 0, 0.09], [0, 0, 0.06]]}))
    (d / "jump.json").write_text(json.dumps(still | {"position_m": [[0, 0, 0.12], [0.03, 0, 0.12], [0.06, 0, 0.12]]}))
    # a planned move, and the same move three times as fast (its nodes consistent: velocities
    # times 3, accelerations times 9), which needs far more command than the device has
    from falcon_plan.planning.api import plan
    from falcon_plan.planning.problem import PlanOptions

    planned = json.loads(plan((-0.04, -0.03, 0.14), (0.04, 0.04, 0.10), PlanOptions.fast()).trajectory.to_json())
    (d / "planned.json").write_text(json.dumps(planned))
    fast = planned | {"t_s": [t / 3 for t in planned["t_s"]],
                      "velocity_m_s": [[3 * v for v in row] for row in planned["velocity_m_s"]],
                      "acceleration_m_s2": [[9 * a for a in row] for row in planned["acceleration_m_s2"]]}
    (d / "too_fast.json").write_text(json.dumps(fast))
    return {p.name: str(p) for p in d.iterdir()} | {"dir": str(d)}


def cases(f: dict[str, str]) -> list[tuple[list[str], int, str]]:
    """(arguments, exit status, a phrase the error line must hold)."""
    d = f["dir"]
    missing, no_folder = f"{d}/missing.json", "/nonexistent/dir/x"
    not_a_folder = f"{f['good.csv']}/x"  # a path under a file: never writable, even as root
    big, bad_json, folder = f["big.json"], f["not_json.json"], f["a_folder"]
    good = f["good.csv"]
    plan = ["plan", "--from", "0,0,0.12"]
    execute = ["execute", "--device", "sim"]
    step = ["simulate", "step", "--from", "0,0,0.12", "--to", "0,0,0.13", "--out", f"{d}/step"]
    synth = ["experiment", "synth", "--duration", "0.5", "--out", f"{d}/synth.csv"]
    disc = ["discrepancy", good, "--heldout", good, "--out", f"{d}/disc"]
    free = f"tcp/127.0.0.1:{_free_port()}"
    return [
        # top level
        ([], 2, "required: COMMAND"),
        (["nosuch"], 2, "invalid choice"),
        (["plan", "--from", "0,0,0.12", "--to", GOOD_TO, "--bogus"], 2, "unrecognized arguments"),
        # plan
        (plan, 2, "--to"),
        ([*plan, "--to", "0,0"], 2, "X,Y,Z in metres"),
        ([*plan, "--to", "a,b,c"], 2, "X,Y,Z in metres"),
        ([*plan, "--to", "0,0,130"], 2, "points are in metres"),
        ([*plan, "--to", "0.2,0,0.13"], 2, "the workspace spans"),
        ([*plan, "--to", "0,0.06,0.08"], 2, "allowed range [-20, 80] deg"),
        ([*plan, "--to", GOOD_TO, "--tc-max", "5"], 2, "must be smaller than tc_max"),
        ([*plan, "--to", GOOD_TO, "--intervals", "abc"], 2, "invalid int"),
        ([*plan, "--to", GOOD_TO, "--out", f"{no_folder}.json"], 2, "does not exist"),
        ([*plan, "--to", GOOD_TO, "--out", folder], 2, "is a folder"),
        ([*plan, "--to", GOOD_TO, "--plot", f"{not_a_folder}.png"], 2, "does not exist"),
        # output files are written in the format their name says, or refused
        ([*plan, "--to", GOOD_TO, "--plot", f"{d}/x.jpg"], 2, "written as a PNG image: give a name ending in .png"),
        ([*plan, "--to", GOOD_TO, "--plot", f"{d}/x.txt"], 2, "ending in .png"),
        ([*plan, "--to", GOOD_TO, "--out", f"{d}/t.csv"], 2, "written as JSON: give a name ending in .json"),
        ([*execute, "--to", GOOD_TO, "--log", f"{d}/run.json"], 2, "ending in .csv"),
        ([*execute, "--to", GOOD_TO, "--plot", f"{d}/run.svg"], 2, "ending in .png"),
        (["experiment", "design", "--out", f"{d}/t.csv"], 2, "ending in .json"),
        ([*synth[:-1], f"{d}/synth.json"], 2, "ending in .csv"),
        ([*disc, "--model-out", f"{d}/model.txt"], 2, "ending in .json"),
        (["request", "plan", "--to", GOOD_TO, "--plot", f"{d}/p.jpeg"], 2, "ending in .png"),
        (["demo", "--plot", f"{d}/p.pdf"], 2, "ending in .png"),
        # negative coordinates are values, not options (each case fails after parsing)
        ([*plan, "--to", "-0.03,0,0.14", "--tc-max", "5"], 2, "must be smaller than tc_max"),
        (["plan", "--from", "-0.01,-0.02,0.12", "--to", "-0.03,0,0.14", "--tc-max", "5"], 2, "smaller than tc_max"),
        ([*plan, "--to", "-0.2,0,0.13"], 2, "the workspace spans"),
        ([*plan, "--to", "-0.03,0"], 2, "X,Y,Z in metres"),
        ([*execute, "--to", "-0.03,-0.01,0.14", "--rate", "500"], 2, "invalid choice"),
        # execute
        ([*execute, "--trajectory", "/nonexistent.json"], 2, "no such file"),
        ([*execute, "--trajectory", bad_json], 2, "not valid JSON"),
        ([*execute, "--trajectory", f["list.json"]], 2, "must be a JSON object"),
        ([*execute, "--trajectory", f["fields.json"]], 2, "lacks field"),
        ([*execute, "--trajectory", f["shape.json"]], 2, "must have shape"),
        ([*execute, "--trajectory", f["outside.json"], "--from", "0,0,0.12"], 2, "the workspace spans"),
        # refused before the device moves (they used to run until the tracking trip let go)
        ([*execute, "--trajectory", f["jump.json"], "--from", "0,0,0.12"], 2, "a device cannot jump"),
        ([*execute, "--trajectory", f["too_fast.json"]], 2, "more than the device can give (4096)"),
        ([*execute, "--to", GOOD_TO, "--log", "/nonexistent/x.csv"], 2, "does not exist"),
        # a folder that access() calls writable for root but that holds no file: refused before
        # the device is opened (they used to fail after the run)
        ([*execute, "--to", GOOD_TO, "--log", "/proc/x.csv"], 2, "cannot write output /proc/x.csv"),
        ([*execute, "--to", GOOD_TO, "--plot", "/proc/x.png"], 2, "cannot write output /proc/x.png"),
        ([*execute, "--to", GOOD_TO, "--mcap", "/proc/x.mcap"], 2, "cannot write output /proc/x.mcap"),
        ([*plan, "--to", GOOD_TO, "--out", "/proc/p.json"], 2, "cannot write output /proc/p.json"),
        ([*execute, "--to", GOOD_TO, "--plot", f"{not_a_folder}.png"], 2, "does not exist"),
        ([*execute, "--to", "0,0,130"], 2, "points are in metres"),
        ([*execute, "--to", GOOD_TO, "--rate", "500"], 2, "invalid choice"),
        (["execute", "--device", "foo", "--to", GOOD_TO], 2, "invalid choice"),
        (["execute", "--device", "emulated", "--firmware", missing, "--to", GOOD_TO], 2, "no such file"),
        (["execute", "--device", "sim"], 2, "one of the arguments --to"),
        # home
        (["home", "--device", "sim", "--timeout", "abc"], 2, "invalid float"),
        (["home"], 2, "--device"),
        # simulate
        (["simulate"], 2, "EXPERIMENT"),
        ([*step, "--effects", "missing.json"], 2, "cannot read 'missing.json'"),
        ([*step, "--effects", "coulomb_Nm=abc"], 2, "not name=number"),
        ([*step, "--effects", "coulomb_Nm=-1"], 2, "must be >= 0"),
        ([*step, "--effects", '{"bad": 1}'], 2, "allowed"),
        ([*step, "--effects", "{not json"], 2, "not valid JSON"),
        ([*step, "--rate", "0"], 2, "positive number"),
        (["simulate", "step", "--from", "0,0,0.12", "--to", "0,0,0.13", "--out", not_a_folder], 2, "cannot create"),
        # experiment
        (["experiment"], 2, "ACTION"),
        ([*synth, "--effects", "missing.json"], 2, "cannot read"),
        ([*synth, "--effects", "coulomb_Nm=0.01,foo=2"], 2, "unknown Effects field"),
        ([*synth, "--controller", "foo"], 2, "cannot be reproduced"),
        ([*synth, "--controller", "pd kp=10"], 2, "lacks kd"),
        ([*synth, "--trajectory", "nosuch"], 2, "neither an excitation kind"),  # the older spelling of --kind
        ([*synth, "--kind", "nosuch"], 2, "neither an excitation kind"),
        (["experiment", "run", "--device", "sim", "--kind", bad_json, "--out", f"{d}/r.csv"], 2, "not valid JSON"),
        ([*synth, "--trajectory", bad_json], 2, "not valid JSON"),
        (["experiment", "synth", "--out", "/nonexistent/dir/x.csv"], 2, "does not exist"),
        (["experiment", "design", "--kind", "nosuch", "--out", f"{d}/t.json"], 2, "invalid choice"),
        (["experiment", "design", "--duration", "-1", "--out", f"{d}/t.json"], 2, "positive number"),
        (["experiment", "design", "--out", "/nonexistent/t.json"], 2, "does not exist"),
        # discrepancy
        (["discrepancy", missing, "--heldout", good, "--out", f"{d}/disc"], 2, "no such file"),
        (["discrepancy", big, "--heldout", big, "--out", f"{d}/disc"], 2, "bad header"),
        (["discrepancy", f["bad_row.csv"], "--heldout", good, "--out", f"{d}/disc"], 2, "enc2 = 'x' is not an integer"),
        (["discrepancy", f["binary.csv"], "--heldout", good, "--out", f"{d}/disc"], 2, "not text (a byte that is not UTF-8)"),
        (["discrepancy", f["no_rows.csv"], "--heldout", good, "--out", f"{d}/disc"], 2,
         "the training log has 0 samples; identification needs at least"),
        ([*disc, "--candidates", "foo"], 2, "allowed: coulomb_friction"),
        ([*disc, "--controller", "foo"], 2, "cannot be reproduced"),
        ([*disc, "--rate", "-5"], 2, "positive number"),
        (["discrepancy", good, "--heldout", good, "--out", not_a_folder], 2, "cannot create"),
        # characterise
        (["characterise", "--out", f"{d}/ch", "--samples", "0"], 2, "positive whole number"),
        (["characterise", "--out", not_a_folder, "--samples", "100"], 2, "cannot create"),
        (["characterise", "--out", f"{d}/ch", "--samples", "100", "--params", "nosuch"], 2, "unknown parameter set"),
        # bench
        (["bench", "--out", f"{d}/bench", "--only", "nosuch"], 2, "unknown problem"),
        (["bench", f"{d}/nosuch", "--out", f"{d}/bench"], 2, "nosuch"),
        (["bench"], 2, "--out"),
        # serve, request, demo
        (["serve", "--device", "foo"], 2, "invalid choice"),
        (["request", "nosuch"], 2, "invalid choice"),
        (["experiment", "design", "--kind", "fourier", "--rate", "1e6", "--out", f"{d}/x.json"], 2,
         "must be at most 10000 Hz"),
        (["request", "plan"], 2, "needs --to X,Y,Z"),
        (["request", "cancel"], 2, "needs a goal id"),
        # a goal id that is no key name (it ended in "unexpected ZError ... a bug")
        (["request", "result", "a*", "--connect", "tcp/127.0.0.1:9"], 2, "goal id 'a*' is not allowed"),
        (["request", "cancel", "", "--connect", "tcp/127.0.0.1:9"], 2, "goal id '' is not allowed"),
        (["request", "plan", "--to", "0,0"], 2, "X,Y,Z in metres"),
        (["request", "plan", "--to", GOOD_TO, "--options", "{bad"], 2, "not valid JSON"),
        (["request", "plan", "--from", "-0.01,0,0.13", "--to", "-0.03,0,0.14", "--via", "-0.02,-0.01,0.13",
          "--options", "{bad"], 2, "not valid JSON"),
        (["demo", "--to", "-0.03,0"], 2, "X,Y,Z in metres"),
        (["request", "state", "--timeout", "0"], 2, "positive number"),
        (["demo", "--to", "0,0"], 2, "X,Y,Z in metres"),
        (["demo", "--options", "[1]"], 2, "must be a JSON object"),
        (["demo", "--plot", f"{no_folder}.png"], 2, "does not exist"),
        # doctor, calibrate, experiment run, router
        (["doctor", "--device", "foo"], 2, "invalid choice"),
        (["doctor", "--device", "usb", "--firmware", missing], 2, "no such file"),
        (["doctor", "--device", "emulated", "--out", not_a_folder], 2, "cannot create"),
        (["doctor", "--device", "emulated", "--load-retries", "0"], 2, "positive whole number"),
        (["calibrate", "--device", "sim", "--out", not_a_folder], 2, "cannot create"),
        (["calibrate", "--device", "sim", "--out", f"{d}/cal", "--effects", "foo=1"], 2, "unknown Effects field"),
        (["calibrate", "--device", "sim", "--out", f"{d}/cal", "--model", missing], 2, "no such file"),
        (["calibrate", "--device", "sim", "--out", f"{d}/cal", "--duration", "-2"], 2, "positive number"),
        (["experiment", "run", "--device", "sim", "--kind", "nosuch", "--out", f"{d}/r.csv"], 2, "neither an excitation kind"),
        (["experiment", "run", "--device", "sim", "--out", "/nonexistent/r.csv"], 2, "does not exist"),
        (["plan", "--from", "0,0,0.12", "--to", GOOD_TO, "--model", bad_json], 2, "is not JSON"),
        (["plan", "--from", "0,0,0.12", "--to", GOOD_TO, "--model", f["binary.json"]], 2, "is not JSON text: byte 0"),
        (["router", "--listen", "tcp/127.0.0.1:notaport"], 2, "invalid port"),
        (["router", "--cfg", "nocolon"], 2, "must look like KEY:VALUE"),
        (["router", "--zenoh-config", "/nonexistent.json5"], 2, "cannot read zenoh config file"),
        # convert, recordings
        (["convert", good, "--out", f"{d}/x.txt"], 2, "must end in .csv (falcon log) or .mcap"),
        (["convert", missing, "--out", f"{d}/x.mcap"], 2, "no such file"),
        (["convert", f["bad_row.csv"], "--out", f"{d}/x.mcap"], 2, "is not an integer"),
        (["convert", good, "--out", f"{no_folder}.mcap"], 2, "does not exist"),
        (["convert", good, "--out", good], 2, "the same file"),
        ([*execute, "--planner", "quintic", "--to", GOOD_TO, "--log", f"{d}/r.mcap", "--mcap", f"{d}/s.mcap"], 2,
         "give the MCAP recording once"),
        ([*execute, "--planner", "quintic", "--to", GOOD_TO, "--live", "--live-port", "70000"], 2,
         "whole number in 0..65535"),
        (["serve", "--device", "none", "--record", not_a_folder], 2, "cannot create recording folder"),
        # calibrate, doctor
        (["calibrate", "--device", "nosuch", "--out", f"{d}/cal"], 2, "invalid choice"),
        (["doctor", "--device", "sim"], 2, "invalid choice"),
        # failed runs (exit 1): the run itself could not be done
        (["request", "state", "--connect", free, "--timeout", "0.5"], 1, "falcon0"),
        (["execute", "--device", "usb", "--to", GOOD_TO], 2, "needs its firmware image"),
        (["execute", "--device", "usb", "--firmware", f["good.csv"], "--to", GOOD_TO], 1, "usb"),
    ]


def _free_port() -> int:
    from service.config import free_loopback_port

    return free_loopback_port()


def _case_ids() -> list[str]:
    return [" ".join(args)[:60] or "(none)" for args, _, _ in cases({"dir": "D", **{k: k for k in (
        "good.csv", "bad_row.csv", "big.json", "not_json.json", "list.json", "fields.json", "shape.json",
        "a_folder", "outside.json", "jump.json", "planned.json", "too_fast.json", "binary.json", "binary.csv", "no_rows.csv")}})]


CASE_COUNT = len(_case_ids())


@pytest.mark.parametrize("index", range(CASE_COUNT), ids=_case_ids())
def test_bad_input_gives_one_line(index: int, files: dict[str, str], capsys: pytest.CaptureFixture[str]) -> None:
    args, status, phrase = cases(files)[index]
    try:
        code = cli.main(args)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    out, err = capsys.readouterr()
    # (a kernel compiled on first use on this machine says so in its own line first: not an error line)
    lines = [line for line in err.strip().splitlines() if not re.match(r"falcon-plan: compiling \S+ \(once; ", line)]
    assert "Traceback" not in err
    assert len(lines) == 1, f"stderr should be one line, got {len(lines)}:\n{err}"
    assert lines[0].startswith("falcon-plan") and ": error: " in lines[0], lines[0]
    assert len(lines[0]) <= cli.MAX_MESSAGE_CHARS + 100, "the error line must not carry a whole file"
    assert phrase.lower() in lines[0].lower(), lines[0]
    assert code == status, f"exit status {code}, expected {status}: {lines[0]}"


def _point_options(parser: argparse.ArgumentParser):
    """(leaf parser, point action) for every point option of every (sub)command."""
    from falcon_plan.commands.common import _PointAction

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                yield from _point_options(child)
        elif isinstance(action, _PointAction):
            yield parser, action


def test_every_point_option_takes_negative_coordinates() -> None:
    """``--to -0.03,0,0.14`` (one argument that starts with a minus) and the older
    ``--to -0.03 0 0.14``, for every point option of every command (other arguments left
    out: the parse is checked, not the command)."""
    found = list(_point_options(cli.build_parser()))
    flags = {flag for _, action in found for flag in action.option_strings}
    assert {"--from", "--to", "--start", "--goal", "--via"} <= flags
    assert {p.prog for p, _ in found} >= {"falcon-plan plan", "falcon-plan execute", "falcon-plan request",
                                          "falcon-plan demo", "falcon-plan simulate step"}
    for parser, action in found:
        required = [(a, a.required) for a in parser._actions]
        for a, _ in required:
            a.required = False
        groups = [(g, g.required) for g in parser._mutually_exclusive_groups]
        for g, _ in groups:
            g.required = False
        try:
            for flag in action.option_strings:
                for argv in ([flag, "-0.03,-0.01,0.14"], [flag, "-0.03", "-0.01", "0.14"], [f"{flag}=-0.03,-0.01,0.14"]):
                    args, rest = parser.parse_known_args(argv)
                    value = getattr(args, action.dest)
                    assert rest == [] and value == ([(-0.03, -0.01, 0.14)] if action.repeat else (-0.03, -0.01, 0.14)), \
                        (parser.prog, argv, value, rest)
        finally:
            for a, was in required:
                a.required = was
            for g, was in groups:
                g.required = was


def test_the_cases_cover_every_subcommand() -> None:
    covered = {args[0] for args, _, _ in cases({"dir": "D"} | {k: k for k in (
        "good.csv", "bad_row.csv", "big.json", "not_json.json", "list.json", "fields.json", "shape.json",
        "a_folder", "outside.json", "jump.json", "planned.json", "too_fast.json", "binary.json", "binary.csv", "no_rows.csv")}) if args}
    assert {"serve", "request", "demo", "router"} <= set(cli.command_names())  # the service's, plugged in
    assert set(cli.command_names()) <= covered
    assert CASE_COUNT >= 70


def test_a_failed_run_leaves_no_empty_output_folder(files: dict[str, str], tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "new" / "disc"
    assert cli.main(["discrepancy", files["bad_row.csv"], "--heldout", files["good.csv"], "--out", str(out)]) == 2
    assert "is not an integer" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    kept = tmp_path / "kept"  # a folder that was there before stays
    kept.mkdir()
    assert cli.main(["discrepancy", files["bad_row.csv"], "--heldout", files["good.csv"], "--out", str(kept)]) == 2
    assert kept.is_dir()


def test_library_warnings_read_as_the_commands_own_lines(files: dict[str, str], tmp_path: Path) -> None:
    """A library warning (here: a falcon log with samples missing) is one ``falcon-plan:
    warning: ...`` line, not a logging record with time, level and module."""
    lines = Path(files["good.csv"]).read_text().splitlines()
    gappy = tmp_path / "gappy.csv"
    gappy.write_text("\n".join(line for i, line in enumerate(lines) if i not in (20, 21, 22)) + "\n")
    env = {k: v for k, v in os.environ.items() if k != "FALCON_PLAN_LOG"}
    done = subprocess.run([sys.executable, "-m", "falcon_plan.cli", "discrepancy", str(gappy), "--heldout",
                           files["bad_row.csv"], "--out", str(tmp_path / "disc")], capture_output=True, text=True,
                          timeout=120, env=env)
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(err) == 2, done.stderr
    assert err[0].startswith(f"falcon-plan: warning: {gappy}: 3 sample(s) missing"), err[0]
    assert err[1].startswith("falcon-plan discrepancy: error:") and "is not an integer" in err[1]


def test_a_run_stopped_by_safety_is_a_failed_run(files: dict[str, str], capsys: pytest.CaptureFixture[str]) -> None:
    """A planned move on a simulated device hiding a 0.4 kg payload: the PD, its feed-forward
    planned for the nominal device, loses it and the tracking guard stops the run; the report
    says why, exit status 1, no traceback."""
    code = cli.main(["execute", "--device", "sim", "--trajectory", files["planned.json"], "--controller", "pd",
                     "--effects", "payload_kg=0.4"])
    out, err = capsys.readouterr()
    assert code == 1 and "status: safety_stop" in out and "tracking error" in out and "Traceback" not in err


def test_debug_shows_the_traceback_and_the_line(files: dict[str, str], capsys: pytest.CaptureFixture[str]) -> None:
    code = cli.main(["--debug", "experiment", "synth", "--effects", "missing.json", "--out", f"{files['dir']}/x.csv"])
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert code == 2 and "Traceback" in err and last.startswith("falcon-plan experiment synth: error:")


@pytest.mark.parametrize("args, status", [
    (["plan", "--from", "0,0,0.12", "--to", "0,0,130"], 2),
    (["experiment", "synth", "--out", "/nonexistent/dir/x.csv"], 2),
])
def test_the_installed_command_prints_one_line(args: list[str], status: int) -> None:
    done = subprocess.run([sys.executable, "-m", "falcon_plan.cli", *args], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "FALCON_PLAN_LOG": "WARNING"})
    assert done.returncode == status and done.stdout == ""
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr


def test_version_and_help(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("falcon-plan ")
    parser = cli.build_parser()
    def walk(sub: argparse.ArgumentParser) -> None:
        text = sub.format_help()
        assert "``" not in text and ":mod:" not in text and ":class:" not in text, sub.prog
        assert sub.description, f"{sub.prog} has no description"
        for action in sub._actions:
            if isinstance(action, argparse._SubParsersAction):
                for child in action.choices.values():
                    walk(child)
            else:
                assert action.help, f"{sub.prog} {action.option_strings or action.dest} has no help"

    for sub in parser._subparsers._group_actions[0].choices.values():
        walk(sub)
    plan_help = parser._subparsers._group_actions[0].choices["plan"].format_help()
    assert "(default 24" in plan_help and "command units" in plan_help
    synth = parser._subparsers._group_actions[0].choices["experiment"]._subparsers._group_actions[0].choices["synth"]
    synth_help = " ".join(synth.format_help().split())      # as the reader sees it, not where a line wraps
    assert "coulomb_Nm" in synth_help and "(default mixed)" in synth_help
    # the top level lists every experiment action; the excitation is --kind in each
    assert "identification experiments (design, run, synth)" in parser.format_help()
    experiment = parser._subparsers._group_actions[0].choices["experiment"]._subparsers._group_actions[0]
    for action in ("design", "run", "synth"):
        assert "--kind" in experiment.choices[action].format_help(), action


def test_written_files_are_0644_and_whole(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "t.json"
    assert cli.main(["experiment", "design", "--duration", "1", "--out", str(out)]) == 0
    log = tmp_path / "x.csv"
    assert cli.main(["experiment", "synth", "--trajectory", str(out), "--out", str(log)]) == 0
    for path in (out, log):
        assert path.stat().st_mode & 0o777 == 0o644, path
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary left
