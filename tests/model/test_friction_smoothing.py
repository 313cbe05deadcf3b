"""The friction smoothing speed (Effects.friction_smoothing_rad_s): validation, the model file,
the symbolic dynamics against a plain numpy tanh, the planner's clamp and the plant's substeps."""
from __future__ import annotations

import math

import numpy as np
import pytest

import falcon_plan as fp
from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.effects import COULOMB_SMOOTHING_RAD_S, SMOOTH_EFFECT_FIELDS, Effects
from falcon_plan.model.modelfile import planning_effects, read_model_file, save_model, unplannable_effect_notes
from falcon_plan.sim.equations import SUBSTEPS_RIGID, friction_substeps
from falcon_plan.sim.plant import SimPlant

SHARP = Effects(coulomb_Nm=0.006, coulomb_leg1_Nm=0.003, stribeck_Nm=0.004, stribeck_velocity_rad_s=0.01,
                viscous_Nms=0.01, friction_smoothing_rad_s=0.002)


def test_field_default_validation_and_dict() -> None:
    assert Effects().friction_smoothing_rad_s == COULOMB_SMOOTHING_RAD_S == 0.02
    assert "friction_smoothing_rad_s" in SMOOTH_EFFECT_FIELDS
    assert "friction_smoothing_rad_s" not in Effects().to_dict()
    assert SHARP.to_dict()["friction_smoothing_rad_s"] == 0.002
    assert Effects.from_dict(SHARP.to_dict()) == SHARP
    for bad in (0.0, -0.01, math.inf, math.nan):
        with pytest.raises(InvalidParameterError, match="friction_smoothing_rad_s"):
            Effects(friction_smoothing_rad_s=bad)


def test_model_file_round_trip(tmp_path) -> None:
    save_model(tmp_path / "m.json", fp.FalconModel(effects=SHARP))
    loaded = read_model_file(tmp_path / "m.json").model
    assert loaded.effects == SHARP
    p, v, a = np.array([0.0, 0.0, 0.125]), np.array([0.001, 0.0005, 0.0]), np.zeros(3)
    np.testing.assert_allclose(loaded.inverse_dynamics(p, v, a), fp.FalconModel(effects=SHARP).inverse_dynamics(p, v, a))


@pytest.mark.parametrize("speed", [0.0004, 0.003, 0.05])
def test_symbolic_friction_is_the_numpy_tanh(speed: float) -> None:
    """The extra commands that the friction needs, times the motor law, = the friction law
    evaluated in numpy with the sharper tanh, at leg speeds inside and beyond the smoothing band."""
    p = np.array([0.01, -0.005, 0.12])
    direction = np.array([0.6, -0.3, 0.74])
    model = fp.FalconModel(effects=SHARP)
    jac = np.asarray(model.functions.jacobian(p, model.effect_vector))
    v = direction * speed / np.abs(jac @ direction).max()
    a = np.zeros(3)
    w = jac @ v
    coulomb = SHARP.coulomb_Nm + np.array([0.0, SHARP.coulomb_leg1_Nm, 0.0])
    stribeck = SHARP.stribeck_Nm * np.exp(-(w / SHARP.stribeck_velocity_rad_s) ** 2)
    expected = SHARP.viscous_Nms * w + (coulomb + stribeck) * np.tanh(w / 0.002)
    # the commands' extra torque through the conventions' motor law (numpy, gains nominal)
    params = model.params
    per_command = -params.drive_ratio * (params.ks_Nm - params.kd_Nms * params.drive_ratio * w)
    extra = model.inverse_dynamics(p, v, a) - fp.FalconModel().inverse_dynamics(p, v, a)
    np.testing.assert_allclose(extra * per_command, expected, rtol=1e-9, atol=1e-12)
    # the default smoothing differs inside the band: the parameter really enters
    if speed < 0.01:
        wide = fp.FalconModel(effects=SHARP.replace(friction_smoothing_rad_s=0.02))
        assert np.abs(wide.inverse_dynamics(p, v, a) - model.inverse_dynamics(p, v, a)).max() > 0.1


def test_planner_clamps_a_sharp_smoothing_and_says_so() -> None:
    assert planning_effects(Effects()) == Effects()
    assert planning_effects(SHARP) == SHARP.replace(friction_smoothing_rad_s=COULOMB_SMOOTHING_RAD_S)
    assert unplannable_effect_notes(Effects(coulomb_Nm=0.01)) == []
    (note,) = unplannable_effect_notes(SHARP)
    assert "friction smoothing 0.002 rad/s" in note and "feed-forward uses the fitted value" in note


def test_plant_substeps_follow_the_smoothing() -> None:
    params = fp.FalconModel().params
    assert friction_substeps(Effects(coulomb_Nm=0.008), params, 800.0) == SUBSTEPS_RIGID
    assert friction_substeps(Effects(friction_smoothing_rad_s=0.001), params, 800.0) == SUBSTEPS_RIGID
    counts = [friction_substeps(Effects(coulomb_Nm=0.014, friction_smoothing_rad_s=w), params, 800.0)
              for w in (0.02, 0.005, 0.002, 0.001)]
    assert counts == sorted(counts) and counts[0] == 1 < counts[-1]
    assert SimPlant(effects=Effects(coulomb_Nm=0.014, friction_smoothing_rad_s=0.001), compile=False).layout.substeps \
        == counts[-1]


def test_plan_with_a_sharp_model_file(tmp_path, capsys) -> None:
    """A model file with a sharp smoothing plans (with the default width) and the report's
    notes say so; the plan's feed-forward is the clamped model's inverse dynamics."""
    import json

    from falcon_plan.cli import main
    from falcon_plan.trajectory import Trajectory

    save_model(tmp_path / "m.json", fp.FalconModel(effects=SHARP))
    assert main(["plan", "--from=-0.03,0,0.12", "--to", "0.03,0.01,0.13", "--fast", "--json",
                 "--model", str(tmp_path / "m.json"), "--out", str(tmp_path / "t.json")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert unplannable_effect_notes(SHARP)[0] in report["notes"]
    t = Trajectory.from_json(tmp_path / "t.json")
    clamped = fp.FalconModel(effects=planning_effects(SHARP))
    ff = clamped.inverse_dynamics(t.position_m, t.velocity_m_s, t.acceleration_m_s2)
    assert np.abs(t.commands - ff).max() < 1e-6 * 4096
