"""The discrepancy workflow on logs with hidden effects: it must name them, fit them within
20 %, shrink the held-out replay error, and answer "none" on nominal data."""
from __future__ import annotations

import json
import math

import pytest

from falcon_plan.discrepancy.checks import FRICTION_EFFECTS, PRACTICAL_MIN_COUNTS
from falcon_plan.discrepancy.workflow import find_discrepancy
from falcon_plan.errors import LogFormatError
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import COULOMB_SMOOTHING_RAD_S, EFFECT_NAMES, Effects

from .conftest import CASES, case_report


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_names_fits_and_shrinks(name: str) -> None:
    case = CASES[name]
    report = case_report(name)
    assert tuple(sorted(report.effects)) == tuple(sorted(case.names)), report.evidence
    assert all(e in EFFECT_NAMES for e in report.effects if e != "none")
    for fld, true in case.checked.items():
        if fld == "extra_delay_samples":
            assert report.corrected.extra_delay_samples == true
            continue
        fitted = report.parameters[fld]
        assert abs(fitted.value - true) <= 0.2 * abs(true), (fld, fitted, true)
        assert fitted.std > 0 and math.isfinite(fitted.std)
    before, after = report.heldout_before.rms_counts_all, report.heldout_after.rms_counts_all
    if case.names == ("none",):
        assert report.corrected.is_nominal
        assert after == pytest.approx(before)
    else:
        assert after < 0.7 * before, (before, after)
        for leg in range(3):
            assert report.heldout_after.rms_mm[leg] <= report.heldout_before.rms_mm[leg] + 1e-9


def test_report_json_and_corrected_model_round_trip(tmp_path) -> None:
    """--json keys; the corrected Effects loads into the planner's model and the plant."""
    from falcon_plan.discrepancy.report import write_report
    from falcon_plan.sim.plant import SimPlant

    report = case_report("coulomb+payload")
    paths = write_report(report, tmp_path / "out")
    data = json.loads(paths["json"].read_text())
    for key in ("effects", "parameters", "evidence", "heldout_rms_before", "heldout_rms_after"):
        assert key in data
    assert {row["effect"] for row in data["evidence"]} == set(EFFECT_NAMES)
    assert data["parameters"]["payload_kg"]["std"] > 0
    effects = Effects.from_dict(json.loads(paths["effects"].read_text()))
    assert effects == report.corrected
    model = FalconModel(effects=effects)
    assert model.effect_vector[0] == pytest.approx(report.parameters["coulomb_Nm"].value)
    SimPlant(model, effects=effects).step((0, 0, 0))
    md = paths["markdown"].read_text()
    assert "coulomb_friction" in md and (tmp_path / "out" / "residual_vs_velocity.png").stat().st_size > 1000


def test_missing_metadata_names_the_options(nominal_logs) -> None:
    train, held = nominal_logs
    bare = FalconLog(train.t_s, train.enc, train.tc, train.ref, {})
    with pytest.raises(LogFormatError, match="--rate"):
        find_discrepancy(bare, held)
    with pytest.raises(LogFormatError, match="--controller"):
        find_discrepancy(bare, held, rate_hz=800.0)


FRICTION_CASES = [n for n in CASES if any(e in FRICTION_EFFECTS for e in CASES[n].names)]


@pytest.mark.slow
@pytest.mark.parametrize("name", FRICTION_CASES)
def test_own_plant_friction_keeps_the_default_smoothing(name: str) -> None:
    """The project's plant smooths its friction sign with the default speed scale: the fit
    of the smoothing runs (a friction effect is named; with a Stribeck curve, inside the
    curve's refit on the replay) but the replay gains nothing practical from a sharper sign,
    so the corrected model keeps the default."""
    report = case_report(name)
    if "stribeck_friction" in report.effects:
        assert report.settings["friction_smoothing"] is None
        refit = report.settings["stribeck_replay_refit"]
        assert not refit["kept"] or refit["after"]["friction_smoothing_rad_s"] == COULOMB_SMOOTHING_RAD_S, refit
    else:
        details = report.settings["friction_smoothing"]
        assert details is not None and not details["kept"], details
        assert details["rms_default"] - details["rms_fitted"] < PRACTICAL_MIN_COUNTS
    assert report.corrected.friction_smoothing_rad_s == COULOMB_SMOOTHING_RAD_S
    assert "friction_smoothing_rad_s" not in report.parameters


@pytest.mark.slow
def test_no_smoothing_fit_without_a_friction_effect() -> None:
    """Without a named friction effect the smoothing is not touched (no extra replays)."""
    report = case_report("payload_mass")
    assert report.settings["friction_smoothing"] is None
    assert report.corrected.friction_smoothing_rad_s == COULOMB_SMOOTHING_RAD_S
