"""Fitted values are clipped into their candidate's bounds before a model is built (issue 26,
item 5): a bounded solver that stops a hair outside a bound never ends the command."""
from __future__ import annotations

import math

import pytest

from falcon_plan.discrepancy.library import LIBRARY, PARAMETER_BOUNDS, clip_to_bounds
from falcon_plan.discrepancy.workflow import _effects_from_values
from falcon_plan.model.effects import Effects


def test_bounds_cover_every_fitted_field() -> None:
    fields = {p.field for c in LIBRARY for p in c.parameters}
    assert set(PARAMETER_BOUNDS) == fields
    assert PARAMETER_BOUNDS["coulomb_leg2_Nm"] == (0.0, 0.2)
    assert PARAMETER_BOUNDS["motor_gain"] == (0.3, 3.0)


def test_clip_to_bounds_clips_and_passes_inside_values() -> None:
    out = clip_to_bounds({"coulomb_leg2_Nm": -1.8e-14, "motor_gain": 3.0000001, "payload_kg": 0.04,
                          "not_a_bounded_field": -5.0})
    assert out == {"coulomb_leg2_Nm": 0.0, "motor_gain": 3.0, "payload_kg": 0.04, "not_a_bounded_field": -5.0}


def test_a_hair_below_zero_builds_a_model() -> None:
    """The crash of issue 26: a per-leg Coulomb fit at -1.8e-14 N.m."""
    with pytest.raises(ValueError, match="coulomb_leg2_Nm must be >= 0"):
        Effects(coulomb_leg2_Nm=-1.8e-14)
    effects = _effects_from_values({"coulomb_leg0_Nm": 0.003, "coulomb_leg2_Nm": -1.8e-14,
                                    "stribeck_velocity_rad_s": 0.0, "kd_sign": -0.7}, extra_delay=1)
    assert effects.coulomb_leg2_Nm == 0.0 and effects.coulomb_leg0_Nm == 0.003
    assert effects.stribeck_velocity_rad_s == 0.03  # the candidate's lower bound, > 0
    assert effects.kd_sign == -1.0 and effects.extra_delay_samples == 1
    assert math.isinf(effects.cable_stiffness_Nm_rad)


def test_the_bounded_step_is_the_unconstrained_one_inside_its_bounds_and_osqps_at_a_bound() -> None:
    """The Gauss-Newton step of every fit: with no bound active it is the least-squares
    solution (taken without OSQP); with one active, OSQP's, on the bound. Checked against an
    independent solve (numpy's lstsq; scipy's bounded least squares)."""
    import numpy as np
    from scipy.optimize import lsq_linear

    from falcon_plan.discrepancy.identify import _bounded_least_squares

    rng = np.random.default_rng(3)
    jac, r = rng.normal(size=(400, 3)) * [1.0, 1e-3, 50.0], rng.normal(size=400)
    scale = np.array([1.0, 1e3, 0.02])
    free = np.linalg.lstsq(jac, r, rcond=None)[0]
    wide = _bounded_least_squares(jac, r, -10 * np.abs(free) - 1, 10 * np.abs(free) + 1, scale)
    assert np.allclose(wide, free, rtol=1e-9, atol=0.0)
    upper = np.array([np.inf, np.inf, 0.5 * free[2]]) if free[2] > 0 else np.array([np.inf] * 3)
    lower = np.array([-np.inf, -np.inf, -np.inf]) if free[2] > 0 else np.array([-np.inf, -np.inf, 0.5 * free[2]])
    bounded = _bounded_least_squares(jac, r, lower, upper, scale)
    reference = lsq_linear(jac, r, bounds=(lower, upper), tol=1e-12).x
    assert bounded[2] == pytest.approx(0.5 * free[2], rel=1e-6)
    assert np.allclose(bounded, reference, rtol=1e-5, atol=1e-9)
