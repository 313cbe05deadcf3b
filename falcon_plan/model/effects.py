"""Physical effects beyond the nominal rigid-body model (all off by default).

The nominal model (MODEL-CONVENTIONS "How each body moves") has no friction, slop,
compliance or extra delay. These named effects switch them on, in the simulated plant (to make
test data and to study sensitivity) and in the corrected model that the discrepancy workflow
fits (so the plant and the planner can load it).

Two kinds:

- *Smooth* effects enter the equations of motion and so the CasADi dynamics, inverse
  dynamics included (the planner can use them): friction at the leg pivots, payload,
  motor-gain error, gravity tilt, the sign of the Kd term. They are packed into the vector
  :meth:`Effects.smooth_vector` in :data:`SMOOTH_EFFECT_FIELDS` order, which is an input of
  every function of :mod:`falcon_plan.model.symbolic`.
- *Plant-only* effects change the signal path and need extra states or memory: extra command
  delay, backlash (cable slop) and cable compliance. The simulated plant implements them.

Every parameter is one scalar shared by the three legs (the legs are built alike), so each
effect has one number to identify. Units are in the field names.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidParameterError
from falcon_plan.validation import require_known_fields

COULOMB_SMOOTHING_RAD_S = 0.02
"""Velocity scale of the tanh that smooths the Coulomb and Stribeck sign(theta1_dot) [rad/s]."""

SMOOTH_EFFECT_FIELDS = (
    "coulomb_Nm", "viscous_Nms", "stribeck_Nm", "stribeck_velocity_rad_s", "payload_kg",
    "motor_gain", "gravity_tilt_x_rad", "gravity_tilt_z_rad", "kd_sign",
)
"""Order of the smooth-effect parameter vector passed to the symbolic dynamics."""

EFFECT_NAMES = (
    "coulomb_friction", "viscous_friction", "stribeck_friction", "command_delay", "backlash",
    "cable_compliance", "payload_mass", "motor_gain", "gravity_tilt", "kd_sign",
)
"""The named candidate effects (the discrepancy workflow's library uses these names)."""


@dataclass(frozen=True)
class Effects:
    """Extra effects on top of the nominal model; the defaults are the nominal model.

    Friction torques act at each leg pivot, opposing the leg's angular velocity theta1_dot:
    tau_f = -(viscous * w + (coulomb + stribeck * exp(-(w / v_s)^2)) * tanh(w / 0.02)).
    """

    coulomb_Nm: float = 0.0
    """Coulomb friction torque at each leg pivot [N.m]."""
    viscous_Nms: float = 0.0
    """Viscous friction coefficient at each leg pivot [N.m.s/rad]."""
    stribeck_Nm: float = 0.0
    """Extra break-away torque above Coulomb, decaying with speed [N.m]."""
    stribeck_velocity_rad_s: float = 0.5
    """Stribeck velocity v_s [rad/s] (only matters when stribeck_Nm > 0)."""
    payload_kg: float = 0.0
    """Extra point mass carried at the end effector [kg]."""
    motor_gain: float = 1.0
    """Multiplier on Ks (and Kd): the true motor gain over the paper's."""
    gravity_tilt_x_rad: float = 0.0
    """Rotation of the gravity vector about the base x axis (device tilted forward/back) [rad]."""
    gravity_tilt_z_rad: float = 0.0
    """Rotation of the gravity vector about the base z axis (device rolled sideways) [rad]."""
    kd_sign: float = 1.0
    """+1: the conventions' reading To = Tc (Ks + Kd w_m); -1: the opposite sign of Kd."""
    extra_delay_samples: int = 0
    """Command delay beyond the nominal 2 samples [control samples] (plant only)."""
    backlash_rad: float = 0.0
    """Total cable slop between motor (encoder) and leg, in leg angle [rad] (plant only)."""
    cable_stiffness_Nm_rad: float = math.inf
    """Stiffness of the cable between motor and leg, at the leg [N.m/rad]; inf = rigid
    (plant only)."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, (int, float)) or math.isnan(value):
                raise InvalidParameterError(f"effect {f.name} must be a number, got {value!r}")
        nonneg = ["coulomb_Nm", "viscous_Nms", "stribeck_Nm", "payload_kg", "backlash_rad",
                  "extra_delay_samples"]
        for name in nonneg:
            if getattr(self, name) < 0:
                raise InvalidParameterError(f"effect {name} must be >= 0, got {getattr(self, name)}")
        if self.stribeck_velocity_rad_s <= 0:
            raise InvalidParameterError("stribeck_velocity_rad_s must be > 0")
        if self.motor_gain <= 0:
            raise InvalidParameterError("motor_gain must be > 0")
        if self.kd_sign not in (1.0, -1.0):
            raise InvalidParameterError(f"kd_sign must be +1 or -1, got {self.kd_sign}")
        if self.cable_stiffness_Nm_rad <= 0:
            raise InvalidParameterError("cable_stiffness_Nm_rad must be > 0 (inf for rigid)")
        if int(self.extra_delay_samples) != self.extra_delay_samples:
            raise InvalidParameterError("extra_delay_samples must be a whole number of samples")

    @property
    def is_nominal(self) -> bool:
        """True when every effect is at its nominal (off) value."""
        return self == Effects()

    def smooth_vector(self) -> np.ndarray:
        """The smooth effects as the parameter vector of the symbolic dynamics."""
        return np.array([float(getattr(self, name)) for name in SMOOTH_EFFECT_FIELDS])

    def replace(self, **changes: Any) -> "Effects":
        """A copy with some effects changed."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, float]:
        """Only the effects that differ from nominal, JSON-ready (inf written as a string)."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value != f.default:
                out[f.name] = "inf" if value == math.inf else value
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Effects":
        """Inverse of :meth:`to_dict`; unknown keys are an error naming them."""
        require_known_fields(cls, data, InvalidParameterError)
        return cls(**{k: (math.inf if v == "inf" else v) for k, v in data.items()})


NOMINAL = Effects()
