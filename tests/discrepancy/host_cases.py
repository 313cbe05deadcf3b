"""The cases of issue 26 on logs a real host records (:mod:`.host_world`): the independent
world's physics behind a busy real-time host (jitter, stalls that skip ticks, a fractional
transport delay measured as ``doctor`` would), at 1 kHz, with hidden effects of sizes not
used by the clean sets. Shared by the tests and ``benchmarks/bench_identification_host.py``.

Each case gives the world, the host's extra effects outside the library (dead band, gain
drift), and the names the workflow must give: ``("none",)`` with ``unexplained`` True for
the cases outside the library.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

from falcon_plan.discrepancy.excitation import design_trajectory
from falcon_plan.falconlog import FalconLog

from .host_world import BUSY, HostTiming, simulate_host_log
from .independent_world import World

RATE_HZ = 1000.0
TRAIN_S, HELDOUT_S = 6.0, 4.0
DEG = math.radians(1.0)


@dataclass(frozen=True)
class HostCase:
    world: World
    names: tuple[str, ...]
    unexplained: bool = False
    deadband: float = 0.0
    gain_drift: float = 0.0
    timing: HostTiming = BUSY
    extra: dict[str, Any] = field(default_factory=dict)


HOST_CASES: dict[str, HostCase] = {
    "none": HostCase(World(), ("none",)),
    "coulomb_friction": HostCase(World(coulomb_Nm=(0.006,) * 3), ("coulomb_friction",)),
    "viscous_friction": HostCase(World(viscous_Nms=0.015), ("viscous_friction",)),
    # break-away 0.012 N.m over a Coulomb level of 0.004: both are named
    "stribeck_friction": HostCase(World(coulomb_Nm=(0.004,) * 3, static_Nm=(0.012,) * 3,
                                        stribeck_speed_rad_s=0.15), ("coulomb_friction", "stribeck_friction")),
    "command_delay": HostCase(World(extra_delay=2), ("command_delay",)),
    "backlash": HostCase(World(backlash_rad=0.02), ("backlash",)),
    "cable_compliance": HostCase(World(cable_stiffness_Nm_rad=40.0), ("cable_compliance",)),
    "payload_mass": HostCase(World(payload_kg=0.04), ("payload_mass",)),
    "motor_gain": HostCase(World(gain=(0.88,) * 3), ("motor_gain",)),
    "gravity_tilt": HostCase(World(tilt_x_rad=4 * DEG), ("gravity_tilt",)),
    "kd_sign": HostCase(World(kd_sign=-1.0), ("kd_sign",)),
    "leg_friction": HostCase(World(coulomb_Nm=(0.0, 0.006, 0.012)), ("leg_friction",)),
    "leg_motor_gain": HostCase(World(gain=(1.0, 0.85, 1.12)), ("leg_motor_gain",)),
    "encoder_offset": HostCase(World(encoder_offset_rad=3 * DEG), ("encoder_offset",)),
    "link_mass": HostCase(World(link_scale=1.4), ("link_mass",)),
    "coulomb+payload": HostCase(World(coulomb_Nm=(0.006,) * 3, payload_kg=0.04),
                                ("coulomb_friction", "payload_mass")),
    "backlash+payload": HostCase(World(backlash_rad=0.02, payload_kg=0.04), ("backlash", "payload_mass")),
    "viscous+motor_gain": HostCase(World(viscous_Nms=0.015, gain=(0.88,) * 3),
                                   ("viscous_friction", "motor_gain")),
    "cogging (outside)": HostCase(World(cogging_Nm=(0.02,) * 3), ("none",), unexplained=True),
    "command dead band (outside)": HostCase(World(), ("none",), unexplained=True, deadband=150.0),
    "gain drift (outside)": HostCase(World(), ("none",), unexplained=True, gain_drift=-0.25),
}
"""Every case, named as the table reports them."""


def host_logs(case: HostCase) -> tuple[FalconLog, FalconLog]:
    """(training, held-out) logs of a case: a ``mixed`` excitation and a ``fourier`` one,
    each with its own host timing draw."""
    logs = []
    for kind, duration, seed in (("mixed", TRAIN_S, 11), ("fourier", HELDOUT_S, 23)):
        ref = design_trajectory(kind, duration, seed=seed, rate_hz=RATE_HZ).counts
        logs.append(simulate_host_log(case.world, ref, RATE_HZ, timing=case.timing, seed=seed,
                                      deadband=case.deadband, gain_drift=case.gain_drift))
    return logs[0], logs[1]


_reports: dict[str, Any] = {}


def host_report(name: str) -> Any:
    """The workflow's report on a case (once per process); ``timings_s["wall_s"]`` is the wall
    time of find_discrepancy."""
    if name not in _reports:
        from falcon_plan.discrepancy.workflow import find_discrepancy

        train, held = host_logs(HOST_CASES[name])
        start = time.perf_counter()
        report = find_discrepancy(train, held)
        report.timings_s["wall_s"] = time.perf_counter() - start
        _reports[name] = report
    return _reports[name]
