"""One convention for points, rates and units across the command line, the service client and
the Python API; notes where data is not what it seems (gaps in a log, a rate mismatch)."""
from __future__ import annotations

import json

import numpy as np
import pytest

import falcon_plan as fp
from falcon_plan.cli import build_parser, main
from falcon_plan.commands import common
from falcon_plan.falconlog import FalconLog, read_log, write_log


def test_points_are_x_y_z_in_metres_under_one_name_with_the_old_spellings_kept() -> None:
    parser = build_parser()
    new = parser.parse_args(["plan", "--from", "0,0,0.12", "--to", "0.02,0.01,0.13", "--via", "0.01,0,0.12"])
    old = parser.parse_args(["plan", "--start", "0", "0", "0.12", "--goal", "0.02", "0.01", "0.13"])
    assert new.start == old.start == (0.0, 0.0, 0.12) and new.goal == old.goal == (0.02, 0.01, 0.13)
    assert new.via == [(0.01, 0.0, 0.12)]
    for command in (["request", "plan"], ["demo"], ["execute", "--device", "sim"]):
        args = parser.parse_args([*command, "--to", "0.02,0.01,0.13"])
        assert args.goal == (0.02, 0.01, 0.13), command
    assert parser.parse_args(["request", "plan", "--goal", "0.02", "0.01", "0.13"]).goal == (0.02, 0.01, 0.13)


def test_rates_default_to_800_hz_and_1_khz_on_usb_frames() -> None:
    """800 Hz (the paper's) everywhere, except on a device whose packets move in 1 ms USB
    frames (a real Falcon, the emulated one with frame timing; the doctor's devices): 1 kHz,
    one period a frame; ``--rate`` wins."""
    from falcon_plan.commands.execute import loop_rate

    parser = build_parser()
    for argv in (["execute", "--device", "sim", "--to", "0,0,0.13"], ["home", "--device", "sim"],
                 ["execute", "--device", "emulated", "--to", "0,0,0.13"],
                 ["calibrate", "--device", "emulated", "--out", "x"]):
        assert loop_rate(parser.parse_args(argv)) == 800.0, argv
    for argv in (["simulate", "step", "--from", "0,0,0.12", "--to", "0,0,0.13"],
                 ["experiment", "design", "--out", "x.json"], ["experiment", "synth", "--out", "x.csv"]):
        assert float(parser.parse_args(argv).rate) == 800.0, argv
    for argv in (["execute", "--device", "usb", "--to", "0,0,0.13"], ["home", "--device", "usb"],
                 ["execute", "--device", "emulated", "--usb-timing", "frames", "--to", "0,0,0.13"],
                 ["experiment", "run", "--device", "emulated", "--usb-timing", "wall", "--out", "x.csv"],
                 ["calibrate", "--device", "usb", "--out", "x"]):
        assert loop_rate(parser.parse_args(argv)) == 1000.0, argv
    assert loop_rate(parser.parse_args(["execute", "--device", "usb", "--rate", "800", "--to", "0,0,0.13"])) == 800.0
    for argv in (["doctor", "--device", "usb"], ["doctor", "--device", "emulated"]):
        assert float(parser.parse_args(argv).rate) == 1000.0, argv


def test_every_command_with_a_result_has_json_output(tmp_path, capsys) -> None:
    import argparse

    def leaves(parser: argparse.ArgumentParser):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            yield parser
        for action in subs:
            for child in action.choices.values():
                yield from leaves(child)

    without = [p.prog for p in leaves(build_parser()) if not any("--json" in a.option_strings for a in p._actions)]
    assert sorted(without) == ["falcon-plan router", "falcon-plan serve"]  # servers print no result
    out = tmp_path / "x.csv"
    assert main(["experiment", "synth", "--duration", "1", "--out", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["samples"] == len(read_log(out))
    assert main(["simulate", "step", "--from", "0,0,0.12", "--to", "0.01,0,0.125", "--out", str(tmp_path),
                 "--duration", "0.5", "--json"]) == 0
    assert "settling_time_s" in json.loads(capsys.readouterr().out)


def test_the_api_refuses_millimetres_with_the_extent(model) -> None:
    with pytest.raises(fp.WorkspaceError) as err:
        fp.plan((0.0, 0.0, 0.12), (0.0, 0.0, 130.0), fp.PlanOptions.fast(), model)
    text = str(err.value)
    assert "did you mean 0,0,0.13?" in text and "the workspace spans x" in text and "mm" in text


def test_the_workspace_extent_is_the_sampled_workspace(model, rng) -> None:
    """The extent named in errors bounds points drawn independently from the workspace, and
    points just outside it on each axis are refused."""
    from falcon_plan.model.workspace import in_workspace, sample_workspace, workspace_extent_m

    lo, hi = workspace_extent_m(model.params, model.limits)
    pts = sample_workspace(5000, rng, model.params, model.limits)
    assert (pts >= lo - 0.002).all() and (pts <= hi + 0.002).all()
    for axis in range(3):
        probe = np.tile((lo + hi) / 2, (2, 1))
        probe[0, axis], probe[1, axis] = lo[axis] - 0.003, hi[axis] + 0.003
        assert not in_workspace(probe, model.params, model.limits).any()


def test_a_plan_prints_in_one_line_and_is_importable_from_the_package(model) -> None:
    from falcon_plan import plan

    result = plan((0.0, 0.0, 0.12), (0.02, 0.01, 0.13), fp.PlanOptions.fast(), model)
    text = repr(result)
    assert "\n" not in text and len(text) < 250 and "ms" in text and "(20.0, 10.0, 130.0) mm" in text


def test_gaps_in_a_log_are_noted(tmp_path) -> None:
    t = np.delete(np.arange(100) / 800.0, [10, 11, 12, 50])  # 4 samples lost in 2 gaps
    n = len(t)
    zeros = np.zeros((n, 3), int)
    write_log(tmp_path / "gaps.csv", FalconLog(t, zeros, zeros, meta={"rate_hz": "800"}))
    notes = read_log(tmp_path / "gaps.csv").notes
    assert len(notes) == 1 and notes[0].startswith("4 sample(s) missing in 2 gap(s)")
    whole = FalconLog(np.arange(10) / 800.0, np.zeros((10, 3), int), np.zeros((10, 3), int))
    assert whole.notes == []


def test_a_trajectory_run_at_another_rate_gets_a_note(tmp_path, capsys) -> None:
    path = tmp_path / "ex.json"
    assert main(["experiment", "design", "--duration", "1", "--out", str(path)]) == 0
    trajectory = common.read_trajectory(path)
    assert common.rate_note(trajectory, 800.0) is None
    assert "sampled at 800 Hz and runs at 1000 Hz" in common.rate_note(trajectory, 1000.0)
    capsys.readouterr()
    assert main(["execute", "--device", "sim", "--trajectory", str(path), "--rate", "1000",
                 "--from", ",".join(str(v) for v in trajectory.position_m[0])]) == 0
    assert "note: the trajectory was sampled at 800 Hz" in capsys.readouterr().err


def test_effects_as_pairs_equal_effects_as_json() -> None:
    pairs = common.load_effects("coulomb_Nm=0.01,backlash_rad=0.002,cable_stiffness_Nm_rad=inf")
    as_json = common.load_effects(json.dumps({"coulomb_Nm": 0.01, "backlash_rad": 0.002}))
    assert pairs == as_json == fp.Effects(coulomb_Nm=0.01, backlash_rad=0.002)


@pytest.mark.slow
def test_request_plan_starts_at_the_device_and_prints_a_summary(model, capsys, tmp_path) -> None:
    """A real service on loopback: ``request plan --to`` without ``--from`` plans from the
    device's position (the state's), and prints a short summary in mm; --json the whole body."""
    from service.client import FalconClient, wait_for_instance
    from service.config import SessionSettings, free_loopback_port
    from service.device import make_runner
    from service.handlers import falcon_planner
    from service.keys import ServiceKeys
    from service.server import FalconService

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    keys = ServiceKeys(prefix="conv")
    service = FalconService(SessionSettings.server([endpoint]), keys, falcon_planner, make_runner("sim", model))
    with service, FalconClient(SessionSettings.client([endpoint]), prefix="conv") as client:
        wait_for_instance(client, keys.instance)
        home = client.state()["position_m"]
        base = ["request", "--prefix", "conv", "--connect", endpoint]
        assert main([*base, "plan", "--to", "0.02,0.01,0.13"]) == 0
        out, err = capsys.readouterr()
        assert "from the device's position" in err
        assert len(out.splitlines()) == 2 and "plan: casadi" in out and "to (20.0, 10.0, 130.0) mm" in out
        assert main([*base, "plan", "--to", "0.02,0.01,0.13", "--json", "--plot", str(tmp_path / "p.png")]) == 0
        body = json.loads(capsys.readouterr().out)
        assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
        assert np.allclose(body["trajectory"]["position_m"][0], home, atol=1e-9)
        assert main([*base, "state"]) == 0
        assert "mm" in capsys.readouterr().out
        assert main([*base, "info"]) == 0 and "can_execute: True" in capsys.readouterr().out
        assert main([*base, "instances"]) == 0 and capsys.readouterr().out.split() == [keys.instance]


def test_the_readme_api_example_prints_what_the_planner_gives(model) -> None:
    """The README's Python API block: its plan's duration in the comment is the one the
    planner gives today (it said 98.97 ms while the plan gave 101.63 ms)."""
    import re
    from pathlib import Path

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    stated = re.search(r"print\(result\)\s+# Plan\(casadi optimal, ([0-9.]+) ms", readme)
    assert stated, "the README's API example no longer prints a plan"
    result = fp.plan((0.0, 0.0, 0.12), (0.03, 0.02, 0.14), fp.PlanOptions.of(tc_max=2500, crosscheck=False,
                                                                              plant_check=False), model)
    assert f"{1e3 * result.report.duration_s:.2f}" == stated.group(1)
    assert f"Plan(casadi optimal, {stated.group(1)} ms" in repr(result)
