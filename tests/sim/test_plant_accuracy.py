"""Integration accuracy of SimPlant's one-RK4-step-per-period against scipy's DOP853.

Experiment: 1 s of the paper's PD step at 800 Hz (hold for 0.1 s, then a step of several
hundred counts that saturates the commands). The reference integrates the same ODE (the
plant's ``rhs`` Function) with DOP853 at rtol 1e-12 between samples, with the same firmware,
saturation rule and encoder rounding in the loop.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import position_to_counts
from falcon_plan.control import EncoderPD
from falcon_plan.sim.plant import SimPlant

RATE_HZ = 800.0
START_M = np.array([0.0, 0.0, 0.125])
GOAL_M = np.array([0.02, 0.01, 0.13])


def _dop853_period(plant: SimPlant, x: np.ndarray, acting: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One period by DOP853 from x under the acting command; returns (x_next, motor command)."""
    fns, eff, pp = plant.functions, plant._eff, plant._pp
    motor = np.asarray(fns.motor_command(x, acting, eff, pp)).ravel()

    def f(_t: float, y: np.ndarray) -> Any:
        return np.asarray(fns.rhs(y, motor, eff, pp)).ravel()

    sol = solve_ivp(f, (0.0, plant.dt_s), x, method="DOP853", rtol=1e-12, atol=1e-14)
    assert sol.success
    return sol.y[:, -1], motor


def _encoder(plant: SimPlant, x: np.ndarray) -> np.ndarray:
    return np.asarray(plant.functions.encoder(x, plant._eff)[0]).ravel()


@pytest.fixture(scope="module")
def runs(model: FalconModel) -> dict[str, np.ndarray]:
    k_total = int(RATE_HZ)
    ref = np.tile(position_to_counts(START_M, model.params), (k_total, 1))
    ref[80:] = position_to_counts(GOAL_M, model.params)
    plant = SimPlant(model, rate_hz=RATE_HZ)
    plant.reset(START_M)
    # RK4 plant, with the one-period DOP853 error from the same start state alongside
    pd, n = EncoderPD(RATE_HZ), plant.counts
    xs, local, motors, acting = [plant._x.copy()], [], [], []
    for k in range(k_total):
        x0 = plant._x.copy()
        n = plant.step(pd.update(n, ref[k]))
        x_ref, _ = _dop853_period(plant, x0, plant.acting_commands)
        local.append(x_ref - plant._x)
        xs.append(plant._x.copy())
        motors.append(plant.motor_commands)
        acting.append(plant.acting_commands)
    # closed-loop DOP853 reference (its own firmware: a second plant used for bookkeeping only)
    shadow = SimPlant(model, rate_hz=RATE_HZ)
    shadow.reset(START_M)
    pd, x = EncoderPD(RATE_HZ), shadow._x.copy()
    n = shadow.counts
    xr = [x]
    for k in range(k_total):
        acting = shadow._firmware.push(shadow._issue(pd.update(n, ref[k])))
        x, _ = _dop853_period(plant, x, acting)
        n = np.floor(_encoder(plant, x) + 0.5).astype(np.int64)
        xr.append(x)
    return {"rk4": np.array(xs), "dop853": np.array(xr), "local": np.array(local),
            "motor": np.array(motors), "acting": np.array(acting)}


def test_the_experiment_exercises_saturation(runs: dict[str, np.ndarray]) -> None:
    motor, acting = np.abs(runs["motor"]), np.abs(runs["acting"])
    assert motor.max() > 3000  # the lifted limit was used
    assert np.any(motor < acting - 500)  # and the static one clipped the start of the step


def test_one_period_error_is_negligible(runs: dict[str, np.ndarray]) -> None:
    assert np.abs(runs["local"][:, :3]).max() < 1e-8  # [m]


def test_closed_loop_position_error_over_1s(model: FalconModel, runs: dict[str, np.ndarray]) -> None:
    plant = SimPlant(model, rate_hz=RATE_HZ)
    err_m = np.abs(runs["rk4"][:, :3] - runs["dop853"][:, :3]).max()
    err_counts = max(np.abs(_encoder(plant, a) - _encoder(plant, b)).max()
                     for a, b in zip(runs["rk4"], runs["dop853"]))
    print(f"RK4 (1 step/period) vs DOP853 over 1 s: max {err_m * 1e3:.2e} mm, {err_counts:.2e} counts")
    assert err_m < 1e-6  # 1 micrometre
    assert err_counts < 0.01
