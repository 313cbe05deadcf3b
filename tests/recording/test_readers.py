"""Discrepancy and calibrate read MCAP recordings as they read falcon logs (one reader, one type)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from falcon_plan.cli import main
from falcon_plan.falconlog import read_log
from falcon_plan.recording.mcapfile import scan


@pytest.mark.slow
def test_discrepancy_names_a_hidden_payload_from_recordings(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for name, kind, seconds, seed in (("train", "mixed", "4", "11"), ("held", "fourier", "3", "23")):
        assert main(["experiment", "run", "--device", "sim", "--effects", "payload_kg=0.05", "--kind", kind,
                     "--duration", seconds, "--seed", seed, "--out", str(tmp_path / f"{name}.mcap")]) == 0
        assert scan(tmp_path / f"{name}.mcap").complete and not (tmp_path / f"{name}.csv").exists()
    capsys.readouterr()
    assert main(["discrepancy", str(tmp_path / "train.mcap"), "--heldout", str(tmp_path / "held.mcap"),
                 "--out", str(tmp_path / "d"), "--no-plots", "--candidates", "coulomb_friction,payload_mass",
                 "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["effects"] == ["payload_mass"]
    model = json.loads((tmp_path / "d" / "model.json").read_text())
    assert model["provenance"]["logs"] == {"train": str(tmp_path / "train.mcap"), "heldout": str(tmp_path / "held.mcap")}
    assert model["effects"]["payload_kg"] == pytest.approx(0.05, rel=0.1)
    # the recording's falcon log is the one the discrepancy read: the controller replays from its metadata
    log = read_log(tmp_path / "train.mcap")
    assert log.meta["controller"].startswith("pd kp=10") and log.ref is not None


@pytest.mark.slow
def test_calibrate_verifies_from_a_recording_as_from_a_falcon_log(tmp_path: Path) -> None:
    """The verification run of ``calibrate --mcap`` reads its per-move figures back from the MCAP
    recording; the same run logged as CSV gives the same figures."""
    from falcon_plan.calibration import verification_run
    from falcon_plan.execution.device_factory import open_device
    from falcon_plan.model.dynamics import FalconModel

    model = FalconModel()
    runs = {}
    for suffix in ("csv", "mcap"):
        with open_device("sim", rate_hz=800.0, model=model) as dev:
            runs[suffix] = verification_run(dev, "sim", model, "nominal", log_path=tmp_path / f"verify.{suffix}")
    assert runs["mcap"].log_path.endswith(".mcap") and scan(runs["mcap"].log_path).complete
    assert len(runs["mcap"].per_move_counts_rms) == 5
    assert runs["mcap"].per_move_counts_rms == pytest.approx(runs["csv"].per_move_counts_rms, rel=1e-9)
    assert runs["mcap"].counts_rms == pytest.approx(runs["csv"].counts_rms, rel=1e-9)
    assert read_log(tmp_path / "verify.mcap").t_s.tolist() == read_log(tmp_path / "verify.csv").t_s.tolist()
