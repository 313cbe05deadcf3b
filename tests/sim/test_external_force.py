"""The plant's external force at the grip (for disturbance tests): at rest under the commands
that hold the device against gravity, a force F accelerates the end effector by M^-1 F
(Newton's law with the model's mass matrix), and it is off by default."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.sim.plant import SimPlant


def test_a_push_at_the_grip_accelerates_by_the_inverse_mass_matrix() -> None:
    model = FalconModel()
    plant = SimPlant(model, rate_hz=1000.0, saturation=False)
    p = np.array([0.01, -0.005, 0.125])
    x = np.concatenate([p, np.zeros(3)])
    hold = np.asarray(model.holding_commands(p))
    rhs = plant.functions.rhs
    eff = model.effect_vector
    still = np.asarray(rhs(x, hold, eff, plant._pp)).ravel()[3:]
    np.testing.assert_allclose(still, 0.0, atol=1e-9)          # no force: held still
    force = np.array([0.5, -0.2, 0.3])
    plant.set_external_force(force)
    pushed = np.asarray(rhs(x, hold, eff, plant._pp)).ravel()[3:]
    np.testing.assert_allclose(pushed, np.linalg.solve(model.mass_matrix(p), force), rtol=1e-9, atol=1e-12)
    # and the step uses it: the plant starts moving along M^-1 F
    plant.reset(p, commands=hold)
    plant.set_external_force(force)
    for _ in range(5):
        plant.step(hold)
    moved = plant.position_m - p
    expected = 0.5 * np.linalg.solve(model.mass_matrix(p), force) * (5e-3) ** 2
    np.testing.assert_allclose(moved, expected, rtol=0.05)
    with pytest.raises(Exception, match="force_N"):
        plant.set_external_force([1.0, 2.0])
