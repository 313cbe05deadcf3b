"""The ``execute`` and ``home`` subcommands, through the CLI dispatcher."""
from __future__ import annotations

import json

import pytest

from falcon_plan.cli import main
from falcon_plan.falconlog import read_log


def test_execute_on_the_sim_with_the_planner_prints_a_json_report(capsys, tmp_path):
    log = tmp_path / "cli.csv"
    code = main(["execute", "--device", "sim", "--rate", "800", "--from", "0.0,0.0,0.14",
                 "--to", "0.02,0.01,0.13", "--log", str(log), "--preroll", "0.2", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and out["execution"]["status"] == "completed"
    assert out["plan"]["method"] in ("casadi", "ruckig-fallback")
    assert out["execution"]["rate_hz"] == 800.0 and out["execution"]["tracking"]["norm_max_mm"] < 1.0
    assert len(read_log(log)) == out["execution"]["samples"]


def test_execute_on_the_emulated_falcon_with_a_saved_quintic(capsys, tmp_path, make_move):
    path = tmp_path / "move.json"
    code = main(["execute", "--device", "emulated", "--to", "0.0,0.02,0.14", "--planner", "quintic",
                 "--preroll", "0.8", "--settle", "0"])
    text = capsys.readouterr().out
    assert code == 0 and "status: completed" in text and "tracking Cartesian" in text
    make_move().to_json(path)  # starts at home, where a fresh simulated device is
    assert main(["execute", "--device", "sim", "--rate", "800", "--trajectory", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["execution"]["trajectory_source"] == "quintic" and out["plan"] is None


def test_home_prints_counts_and_position(capsys):
    assert main(["home", "--device", "emulated", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["homed"] is True and len(out["counts"]) == 3 and 100 < out["position_mm"][2] < 160


@pytest.mark.parametrize("argv, message", [
    (["execute", "--device", "usb", "--to", "0,0,0.13"], "firmware"),
    (["execute", "--device", "sim", "--to", "0,-0.2,0.13", "--planner", "quintic"], "outside the workspace"),
])
def test_errors_are_clear_and_exit_2(capsys, argv, message):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_a_bad_point_is_an_argument_error(capsys):
    with pytest.raises(SystemExit):
        main(["execute", "--device", "sim", "--to", "1,2"])
    assert "X,Y,Z" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["execute", "--device", "emulated", "--to", "0.0,0.02,0.14", "--planner", "quintic", "--log"],
    ["experiment", "run", "--device", "emulated", "--duration", "1", "--out"],
], ids=["execute", "experiment-run"])
def test_a_usb_writer_failure_mid_run_exits_1_naming_it_with_zero_force_and_a_whole_log(
        capsys, monkeypatch, tmp_path, argv):
    # the emulated Falcon with threaded I/O (as on hardware), its writer failing mid-run on an
    # exception that is not a USB error
    from falcon_plan.devices.emulated import FaultPlan, TransferFault
    from falcon_plan.execution import device_factory

    real_open, opened = device_factory.open_device, []

    def open_with_a_failing_writer(kind, **options):
        # early in the run (homing takes ~30 packets), with a 100 ms silence bound, so that a
        # loaded machine does not stop the run before the fault
        options.update(io="threaded", reply_timeout_s=0.025, faults=FaultPlan(
            transfer=TransferFault("write", "runtime", after_packets=80)))
        opened.append(real_open(kind, **options))
        return opened[-1]

    monkeypatch.setattr(device_factory, "open_device", open_with_a_failing_writer)
    log = tmp_path / "run.csv"
    code = main(argv + [str(log)])
    out, err = capsys.readouterr()
    assert code == 1, out + err
    status = [line for line in out.splitlines() if line.startswith("status:")]
    assert len(status) == 1 and status[0].startswith("status: device_error"), out
    assert "writer thread" in status[0] and "RuntimeError: emulated backend failure" in status[0]
    assert "Traceback" not in err and "could not send zero force" not in err, err
    samples = int(next(line for line in out.splitlines() if line.startswith("samples:")).split()[1].split("/")[0])
    assert 0 < samples == len(read_log(log))  # closed whole, every sent command in it
    device = opened[0]
    assert not device.is_open and device.backend.falcon.transfer_faults == 1
    assert device.backend.falcon.held_commands.tolist() == [0, 0, 0]
