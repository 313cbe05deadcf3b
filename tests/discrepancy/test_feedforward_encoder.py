"""A model file with an encoder home-angle offset must reach the executor: its reference counts
and its feed-forward are read from the corrected home angle (Effects.encoder_params)."""
from __future__ import annotations

import math

import numpy as np

from falcon_plan.control import Controller
from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.execution.executor import Executor
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import forward_kinematics
from falcon_plan.planning.quintic import quintic_trajectory

OFFSET_RAD = math.radians(4.0)


def test_feedforward_reads_the_reference_from_the_corrected_home_angle():
    """On a still reference the feed-forward is the gravity hold at the point the counts mean;
    with an offset model that point is forward kinematics of theta_home + offset + n / cpr
    (computed here from the angles, not through the controller's count conversion)."""
    nominal = FalconModel()
    corrected = nominal.with_effects(Effects(encoder_offset_rad=OFFSET_RAD))
    counts = np.array([150.0, -80.0, 40.0])
    ref = np.tile(counts, (6, 1))
    params = nominal.params
    theta = params.theta_home_rad + OFFSET_RAD + counts / params.counts_per_rad
    hold = corrected.inverse_dynamics(forward_kinematics(theta, params), np.zeros(3), np.zeros(3))
    got = Controller.executor_default(model=corrected).offsets(ref, nominal)
    np.testing.assert_allclose(got, np.tile(hold, (6, 1)), rtol=1e-6, atol=1e-6)
    nominal_ff = Controller.executor_default(model=nominal).offsets(ref, nominal)
    assert np.abs(got - nominal_ff).max() > 5.0   # the offset moves the gravity hold visibly


def test_executor_with_the_offset_model_reaches_the_planned_point():
    """A device whose true home angle is 4 deg off; the executor running the corrected model
    starts where the device is and ends at the planned point (true position, within 0.3 mm)."""
    corrected = FalconModel().with_effects(Effects(encoder_offset_rad=OFFSET_RAD))
    device = SimDevice(model=FalconModel(), effects=Effects(encoder_offset_rad=OFFSET_RAD), realtime=False)
    device.open()
    try:
        device.home()
        start = device.plant.position_m
        traj = quintic_trajectory(start, start + np.array([0.02, -0.01, 0.01]), corrected)
        report = Executor(device, corrected, preroll_s=0.3, settle_s=0.5).run(traj)
        assert report.status == "completed"
        assert np.linalg.norm(device.plant.position_m - traj.position_m[-1]) < 3e-4
    finally:
        device.close()
