"""The cases run on the independent world (:mod:`.independent_world`), shared by the tests and
``benchmarks/bench_discrepancy.py``: one per candidate effect, none, a pair, an effect outside
the library, and the loop variants (1 kHz, lost samples, other PD gains).

Each case gives the world, the names the workflow must give, and checks of the fitted
parameters: ``checked`` maps an Effects field to (true value, relative tolerance). The Stribeck
case compares friction torques instead (the world's curve is exponential, the model's
Gaussian; see :func:`stribeck_torque`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from falcon_plan.discrepancy.excitation import design_trajectory
from falcon_plan.falconlog import FalconLog

from .independent_world import World, simulate_log

TRAIN_S, HELDOUT_S = 6.0, 4.0


@dataclass(frozen=True)
class WorldCase:
    world: World
    names: tuple[str, ...]
    checked: dict[str, tuple[float, float]] = field(default_factory=dict)
    rate_hz: float = 800.0
    gains: tuple[float, float] = (10.0, 0.1)
    lost_fraction: float = 0.0


DEG = math.radians(1.0)
WORLD_CASES: dict[str, WorldCase] = {
    "none": WorldCase(World(), ("none",)),
    "coulomb_friction": WorldCase(World(coulomb_Nm=(0.008,) * 3), ("coulomb_friction",),
                                  {"coulomb_Nm": (0.008, 0.2)}),
    "viscous_friction": WorldCase(World(viscous_Nms=0.02), ("viscous_friction",), {"viscous_Nms": (0.02, 0.2)}),
    # break-away 0.008 N.m falling to zero with speed over 0.1 rad/s (low break-away speed)
    "stribeck_friction": WorldCase(World(static_Nm=(0.008,) * 3, stribeck_speed_rad_s=0.1),
                                   ("stribeck_friction",)),
    "command_delay": WorldCase(World(extra_delay=2), ("command_delay",), {"extra_delay_samples": (2, 0.0)}),
    "backlash": WorldCase(World(backlash_rad=0.025), ("backlash",), {"backlash_rad": (0.025, 0.3)}),
    "cable_compliance": WorldCase(World(cable_stiffness_Nm_rad=30.0), ("cable_compliance",),
                                  {"cable_stiffness_Nm_rad": (30.0, 0.2)}),
    "payload_mass": WorldCase(World(payload_kg=0.05), ("payload_mass",), {"payload_kg": (0.05, 0.2)}),
    "motor_gain": WorldCase(World(gain=(0.85,) * 3), ("motor_gain",), {"motor_gain": (0.85, 0.05)}),
    "gravity_tilt": WorldCase(World(tilt_x_rad=5 * DEG), ("gravity_tilt",), {"gravity_tilt_x_rad": (5 * DEG, 0.2)}),
    "kd_sign": WorldCase(World(kd_sign=-1.0), ("kd_sign",), {"kd_sign": (-1.0, 0.0)}),
    "leg_friction": WorldCase(World(coulomb_Nm=(0.002, 0.008, 0.014)), ("leg_friction",),
                              {"coulomb_leg0_Nm": (0.002, 0.3), "coulomb_leg1_Nm": (0.008, 0.2),
                               "coulomb_leg2_Nm": (0.014, 0.2)}),
    "leg_motor_gain": WorldCase(World(gain=(1.0, 0.8, 1.15)), ("leg_motor_gain",),
                                {"motor_gain_leg0": (1.0, 0.05), "motor_gain_leg1": (0.8, 0.05),
                                 "motor_gain_leg2": (1.15, 0.05)}),
    "encoder_offset": WorldCase(World(encoder_offset_rad=4 * DEG), ("encoder_offset",),
                                {"encoder_offset_rad": (4 * DEG, 0.1)}),
    "link_mass": WorldCase(World(link_scale=1.5), ("link_mass",), {"link_mass_scale": (1.5, 0.1)}),
    "coulomb+payload": WorldCase(World(coulomb_Nm=(0.008,) * 3, payload_kg=0.05),
                                 ("coulomb_friction", "payload_mass"),
                                 {"coulomb_Nm": (0.008, 0.2), "payload_kg": (0.05, 0.2)}),
    # outside the library: cogging torque of the motors
    "cogging (unexplained)": WorldCase(World(cogging_Nm=(0.02,) * 3), ("none",)),
    # loop variants
    "payload_mass at 1 kHz": WorldCase(World(payload_kg=0.05), ("payload_mass",), {"payload_kg": (0.05, 0.2)},
                                       rate_hz=1000.0),
    "payload_mass, 2 % lost samples": WorldCase(World(payload_kg=0.05), ("payload_mass",),
                                                {"payload_kg": (0.05, 0.2)}, lost_fraction=0.02),
    "motor_gain, PD kp=20 kd=0.15": WorldCase(World(gain=(0.85,) * 3), ("motor_gain",),
                                              {"motor_gain": (0.85, 0.05)}, gains=(20.0, 0.15)),
}
"""Every case, named as the tests report them."""


def _lost(n: int, fraction: float, seed: int) -> np.ndarray:
    """Indices of lost samples: bursts of 1-5 samples at random places, ``fraction`` of n."""
    rng = np.random.default_rng(seed)
    lost: set[int] = set()
    while len(lost) < fraction * n:
        start = int(rng.integers(200, n - 200))
        lost.update(range(start, start + int(rng.integers(1, 6))))
    return np.array(sorted(lost))


def world_logs(case: WorldCase) -> tuple[FalconLog, FalconLog]:
    """(training, held-out) logs of a case: a ``mixed`` excitation and a ``fourier`` one."""
    logs = []
    for kind, duration, seed in (("mixed", TRAIN_S, 11), ("fourier", HELDOUT_S, 23)):
        ref = design_trajectory(kind, duration, seed=seed, rate_hz=case.rate_hz).counts
        drop = _lost(ref.shape[0], case.lost_fraction, seed) if case.lost_fraction else None
        logs.append(simulate_log(case.world, ref, case.rate_hz, kp=case.gains[0], kd=case.gains[1], drop=drop))
    return logs[0], logs[1]


def stribeck_torque(speed_rad_s: float, values: dict[str, float]) -> float:
    """Friction torque [N.m] of the model's Stribeck term at a leg speed (tanh ~ 1 there)."""
    return values["stribeck_Nm"] * math.exp(-(speed_rad_s / values["stribeck_velocity_rad_s"]) ** 2)


def world_stribeck_torque(speed_rad_s: float, world: World) -> float:
    """The world's friction above Coulomb at a leg speed [N.m] (leg 0)."""
    static = world.static_Nm if world.static_Nm is not None else world.coulomb_Nm
    return (static[0] - world.coulomb_Nm[0]) * math.exp(-speed_rad_s / world.stribeck_speed_rad_s)


_reports: dict[str, Any] = {}


def world_report(name: str) -> Any:
    """The workflow's report on a case (computed once per session); ``report.elapsed_s`` is
    the wall time of find_discrepancy."""
    if name not in _reports:
        from falcon_plan.discrepancy.workflow import find_discrepancy

        train, held = world_logs(WORLD_CASES[name])
        start = time.perf_counter()
        report = find_discrepancy(train, held)
        report.timings_s["wall_s"] = time.perf_counter() - start
        _reports[name] = report
    return _reports[name]
