"""Synthetic falcon logs: the simulated plant, with any effects switched on, in closed loop
with a :class:`~falcon_plan.control.Controller` (default the paper's encoder PD) tracking an
excitation reference.

The log holds what a real run would: whole encoder counts (the plant quantises them), the
integer commands and the reference. It does not record which effects were on (the
discrepancy workflow must find them). Optional measurement noise adds a zero-mean Gaussian
of ``noise_counts`` [counts] to each reading before rounding; the controller sees the noisy
counts too, as it would on a device.
"""
from __future__ import annotations

import numpy as np

from falcon_plan.control import Controller
from falcon_plan.errors import InvalidParameterError
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import angles_to_counts
from falcon_plan.trajectory import Trajectory
from falcon_plan.sim.plant import SimPlant

DEFAULT_CONTROLLER = "pd kp=10 kd=0.1"


def synthesize_log(effects: Effects, trajectory: Trajectory, *, rate_hz: float = 800.0,
                   seed: int = 0, noise_counts: float = 0.0,
                   controller: str | Controller = DEFAULT_CONTROLLER,
                   model: FalconModel | None = None) -> FalconLog:
    """Run ``trajectory``'s encoder counts as the reference of ``controller`` (a Controller,
    or its ``controller`` metadata text; its rate is set to ``rate_hz``) on a SimPlant with
    ``effects``; the controller's feed-forward, if any, uses ``model`` (default nominal).

    The trajectory must be sampled at ``rate_hz`` [Hz] (one reference row per period). The
    plant starts at rest at the trajectory's first point. ``noise_counts`` is the standard
    deviation [counts] of the measurement noise added to each reading before rounding (see
    the module docstring; 0: none); ``seed`` drives it.
    """
    if noise_counts < 0:
        raise InvalidParameterError(f"noise_counts must be >= 0, got {noise_counts}")
    dt = np.diff(trajectory.t_s)
    if not np.allclose(dt, 1.0 / rate_hz, rtol=1e-6, atol=1e-9):
        raise InvalidParameterError(f"the trajectory is not sampled at {rate_hz:g} Hz; use "
                                    "Trajectory.sample(rate_hz) first")
    model = model or FalconModel()
    if isinstance(controller, str):
        controller = Controller.from_meta({}, text=controller, rate_hz=rate_hz)
    controller = controller.replace(rate_hz=rate_hz)
    plant = SimPlant(model.with_effects(Effects()), rate_hz=rate_hz, effects=effects, seed=seed)
    plant.reset(trajectory.position_m[0])
    ref = trajectory.counts
    if noise_counts == 0.0:
        run = controller.run_on(plant, ref, model)
        enc, tc = run.counts, run.commands
    else:
        law = controller.tracker(ref, model)
        rng = np.random.default_rng(seed)
        enc = np.zeros((ref.shape[0], 3), dtype=np.int64)
        tc = np.zeros((ref.shape[0], 3), dtype=np.int64)
        for k in range(ref.shape[0]):
            exact = angles_to_counts(plant.motor_angle_rad, model.params)
            noisy = np.floor(exact + rng.normal(0.0, noise_counts, 3) + 0.5).astype(np.int64)
            enc[k] = noisy
            if k == 0:
                law.start(noisy)
            tc[k] = law.update(k, noisy)
            plant.step(tc[k])
    meta = {**controller.to_meta(), "params": model.params.name,
            "source": "falcon-plan experiment synth",
            "trajectory": str(trajectory.meta.get("kind", trajectory.source)),
            "seed": str(seed)}
    if noise_counts:
        meta["noise_counts"] = f"{noise_counts:g}"
    return FalconLog(trajectory.t_s, enc, tc, ref, meta)
