"""The CLI: experiment design, experiment synth, discrepancy --json."""
from __future__ import annotations

import json

import pytest

from falcon_plan.cli import main
from falcon_plan.falconlog import read_log
from falcon_plan.trajectory import Trajectory


def test_design_and_synth_and_discrepancy(tmp_path, capsys) -> None:
    traj = tmp_path / "p2p.json"
    assert main(["experiment", "design", "--kind", "p2p", "--duration", "3", "--seed", "4",
                 "--out", str(traj)]) == 0
    assert Trajectory.from_json(traj).duration_s == pytest.approx(4.0, abs=0.01)
    train, held = tmp_path / "train.csv", tmp_path / "held.csv"
    effects = json.dumps({"viscous_Nms": 0.02})
    assert main(["experiment", "synth", "--effects", effects, "--trajectory", "mixed", "--duration",
                 "5", "--seed", "1", "--out", str(train)]) == 0
    assert main(["experiment", "synth", "--effects", effects, "--trajectory", str(traj),
                 "--seed", "2", "--noise", "0.3", "--out", str(held)]) == 0
    log = read_log(train)
    assert log.meta["rate_hz"] == "800" and log.ref is not None and "viscous" not in str(log.meta)
    capsys.readouterr()
    assert main(["discrepancy", str(train), "--heldout", str(held), "--out", str(tmp_path / "rep"),
                 "--json", "--no-plots"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["effects"] == ["viscous_friction"]
    assert data["parameters"]["viscous_Nms"]["value"] == pytest.approx(0.02, rel=0.2)
    assert data["heldout_rms_after"] < data["heldout_rms_before"]
    assert (tmp_path / "rep" / "report.md").exists() and (tmp_path / "rep" / "effects.json").exists()


def test_missing_controller_metadata_names_the_option(tmp_path, capsys) -> None:
    log = tmp_path / "bare.csv"
    log.write_text("# rate_hz: 800\nt,enc0,enc1,enc2,tc0,tc1,tc2,ref0,ref1,ref2\n"
                   + "".join(f"{k / 800},0,0,0,0,0,0,0,0,0\n" for k in range(300)))
    assert main(["discrepancy", str(log), "--heldout", str(log), "--out", str(tmp_path / "o")]) == 2
    assert "--controller" in capsys.readouterr().err
