"""The inverse dynamics a fit evaluates: composed from the rigid-body terms read once per problem
and the friction and motor laws (``ResidualProblem.evaluate``), it must be the compiled
Function's (``evaluate_compiled``, the symbolic model itself) at any effect vector, value and
Jacobian, for every entry of the vector."""
from __future__ import annotations

import numpy as np

from falcon_plan.discrepancy.excitation import design_trajectory
from falcon_plan.discrepancy.identify import ResidualProblem
from falcon_plan.discrepancy.motion import estimate_motion
from falcon_plan.discrepancy.synth import synthesize_log
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import SMOOTH_EFFECT_FIELDS, Effects

RANGES = {   # wider than the candidates' ranges: the composition must hold anywhere
    "coulomb_Nm": (0.0, 0.03), "viscous_Nms": (0.0, 0.002), "stribeck_Nm": (0.0, 0.02),
    "stribeck_velocity_rad_s": (0.03, 2.0), "payload_kg": (-0.05, 0.2), "motor_gain": (0.5, 1.5),
    "gravity_tilt_x_rad": (-0.8, 0.8), "gravity_tilt_z_rad": (-0.8, 0.8), "kd_sign": (-1.0, 1.0),
    "link_mass_scale": (0.3, 2.5), "encoder_offset_rad": (-0.2, 0.2), "friction_smoothing_rad_s": (0.005, 0.5),
}


def _draw(rng: np.random.Generator, base: np.ndarray) -> np.ndarray:
    eff = base.copy()
    for i, field in enumerate(SMOOTH_EFFECT_FIELDS):
        if field.startswith("coulomb_leg"):
            eff[i] = rng.uniform(0.0, 0.02)
        elif field.startswith("motor_gain_leg"):
            eff[i] = rng.uniform(0.7, 1.3)
        else:
            eff[i] = rng.uniform(*RANGES[field])
    return eff


def test_the_composed_inverse_dynamics_is_the_compiled_one() -> None:
    model = FalconModel()
    trajectory = design_trajectory("mixed", 2.0, seed=3, rate_hz=1000.0)
    log = synthesize_log(Effects(coulomb_Nm=0.004), trajectory, rate_hz=1000.0)
    problem = ResidualProblem(model, estimate_motion(log, 1000.0, model.params), 2.5)
    assert problem.rows.size > 300
    problem.rigid_terms          # read now: every evaluation below is composed (the first few would not be)
    rng = np.random.default_rng(7)
    varied = np.zeros(len(SMOOTH_EFFECT_FIELDS), bool)
    for _ in range(25):
        eff = _draw(rng, model.effect_vector)
        varied |= eff != model.effect_vector
        tc, jac = problem.evaluate(eff)
        tc_ref, jac_ref = problem.evaluate_compiled(eff)
        np.testing.assert_allclose(tc, tc_ref, rtol=0, atol=1e-9 * np.abs(tc_ref).max())
        np.testing.assert_allclose(jac, jac_ref, rtol=0, atol=1e-9 * np.abs(jac_ref).max())
    assert varied.all()      # every entry of the vector moved: none can be missed by the composition
    # and at the nominal vector, where every fit starts
    tc, jac = problem.evaluate(model.effect_vector)
    tc_ref, jac_ref = problem.evaluate_compiled(model.effect_vector)
    np.testing.assert_allclose(tc, tc_ref, rtol=0, atol=1e-9 * np.abs(tc_ref).max())
    np.testing.assert_allclose(jac, jac_ref, rtol=0, atol=1e-9 * np.abs(jac_ref).max())
