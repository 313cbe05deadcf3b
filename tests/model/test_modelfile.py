"""The model file: round trip, provenance, errors, the Python API, --model on the commands and
the service's info."""
from __future__ import annotations

import json
import re
import math

import numpy as np
import pytest

import falcon_plan as fp
from falcon_plan.cli import main
from falcon_plan.errors import InvalidParameterError, OutputError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.modelfile import read_model_file, save_model, unplannable_effect_notes
from falcon_plan.trajectory import Trajectory

CORRECTED = Effects(coulomb_Nm=0.0079, payload_kg=0.049, backlash_rad=0.004, extra_delay_samples=1,
                    cable_stiffness_Nm_rad=60.0)


def test_round_trip_keeps_params_effects_and_provenance(tmp_path) -> None:
    params = fp.ACRA2009.replace(name="bench-unit-3", theta_home_rad=math.radians(41.5))
    model = fp.FalconModel(params, CORRECTED)
    prov = {"logs": {"train": "a.csv"}, "parameters": {"coulomb_Nm": {"value": 0.0079, "std": math.inf}}}
    save_model(tmp_path / "m.json", model, prov)
    assert (tmp_path / "m.json").stat().st_mode & 0o777 == 0o644  # readable by others, like every output
    loaded = read_model_file(tmp_path / "m.json")
    assert loaded.model.params == params and loaded.model.effects == CORRECTED
    assert loaded.provenance["logs"] == {"train": "a.csv"} and "created_utc" in loaded.provenance
    assert loaded.provenance["parameters"]["coulomb_Nm"]["std"] == "inf"  # JSON has no inf
    assert fp.load_model(tmp_path / "m.json").effects == CORRECTED
    # the loaded model's dynamics are the corrected ones
    p, v, a = np.array([0.0, 0.0, 0.125]), np.array([0.1, 0.0, 0.0]), np.zeros(3)
    np.testing.assert_allclose(loaded.model.inverse_dynamics(p, v, a), model.inverse_dynamics(p, v, a))


def test_bad_files_are_clear_errors(tmp_path) -> None:
    (tmp_path / "x.json").write_text("{not json")
    (tmp_path / "y.json").write_text(json.dumps({"coulomb_Nm": 0.01}))
    (tmp_path / "z.json").write_text(json.dumps({"format": "falcon-plan model", "version": 1,
                                                 "params": fp.ACRA2009.to_dict(), "effects": {"glue": 1}}))
    for name, needle in (("x.json", "not JSON"), ("y.json", "not a falcon-plan model"), ("z.json", "glue"),
                         ("absent.json", "cannot read")):
        with pytest.raises(InvalidParameterError, match=needle):
            read_model_file(tmp_path / name)
    with pytest.raises(OutputError, match="cannot write the model file"):
        save_model(tmp_path / "no" / "such" / "m.json", fp.FalconModel())


def test_plan_with_a_model_file_uses_its_dynamics_and_says_what_it_cannot(tmp_path, capsys) -> None:
    path = tmp_path / "m.json"
    save_model(path, fp.FalconModel(effects=CORRECTED))
    notes = unplannable_effect_notes(CORRECTED, fp.ACRA2009)
    assert [n.split(" ")[0] for n in notes] == ["command", "backlash", "cable"]
    assert main(["plan", "--from=-0.03,0,0.12", "--to", "0.03,0.01,0.13", "--fast", "--json",
                 "--model", str(path), "--out", str(tmp_path / "t.json")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert all(n in report["notes"] for n in notes)
    # the plan's feed-forward is the corrected inverse dynamics (payload and friction in it)
    t = Trajectory.from_json(tmp_path / "t.json")
    corrected = fp.FalconModel(effects=CORRECTED).inverse_dynamics(t.position_m, t.velocity_m_s, t.acceleration_m_s2)
    nominal = fp.FalconModel().inverse_dynamics(t.position_m, t.velocity_m_s, t.acceleration_m_s2)
    assert np.abs(t.commands - corrected).max() < 1e-6 * 4096 < np.abs(t.commands - nominal).max()
    capsys.readouterr()
    with pytest.raises(SystemExit) as refused:  # a missing file is a usage error, refused before any work
        main(["plan", "--from", "0,0,0.12", "--to", "0.01,0,0.12", "--model", str(tmp_path / "absent.json")])
    assert refused.value.code == 2
    err = capsys.readouterr().err
    assert "no such file" in err and "absent.json" in err and len(err.strip().splitlines()) == 1


def test_the_service_reports_its_model(tmp_path) -> None:
    import argparse

    from service.main import add_serve_arguments, build_service
    from service.testing import PREFIX, check_schema, client_for, endpoint

    path = tmp_path / "m.json"
    save_model(path, fp.FalconModel(effects=Effects(payload_kg=0.05)), {"source": "test"})

    parser = argparse.ArgumentParser()
    add_serve_arguments(parser)
    args = parser.parse_args(["--device", "none", "--instance", "m0", "--prefix", PREFIX, "--listen", endpoint(),
                              "--model", str(path)])
    with build_service(args) as service, client_for(service, "m0") as client:
        info = check_schema(client.info(), "info")
    assert info["model"]["effects"] == {"payload_kg": 0.05} and not info["model"]["nominal"]
    assert info["model"]["path"] == str(path) and info["model"]["source"] == "test"


@pytest.mark.parametrize("field, value, problem", [
    ("encoder_counts_per_rev", 0, "encoder_counts_per_rev must be a whole number >= 1, got 0"),
    ("command_delay_samples", -5, "command_delay_samples must be a whole number >= 0, got -5"),
    ("command_limit", 2.5, "command_limit must be a whole number >= 1"),
])
def test_a_model_file_with_an_impossible_count_parameter_is_refused_naming_it(tmp_path, field, value, problem) -> None:
    """Counts and samples are whole numbers (0 counts per turn used to pass and fail after homing
    with division warnings; -5 delay samples failed naming another parameter)."""
    path = save_model(tmp_path / "m.json", FalconModel())
    data = json.loads(path.read_text())
    data["params"][field] = value
    path.write_text(json.dumps(data))
    with pytest.raises(InvalidParameterError, match=re.escape(f"{path}: parameter {problem}")):
        read_model_file(path)


def test_a_model_file_missing_a_parameter_says_the_papers_value_is_used(tmp_path, caplog) -> None:
    path = save_model(tmp_path / "m.json", FalconModel())
    data = json.loads(path.read_text())
    del data["params"]["b_m"]
    path.write_text(json.dumps(data))
    with caplog.at_level("WARNING", logger="falcon_plan.model.modelfile"):
        model = read_model_file(path).model
    assert model.params.b_m == FalconModel().params.b_m
    assert "parameter(s) b_m not given: the paper's values (acra2009) are used" in caplog.text
