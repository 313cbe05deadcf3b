"""Physical effects beyond the nominal rigid-body model (all off by default).

The nominal model (MODEL-CONVENTIONS "How each body moves") has no friction, slop,
compliance or extra delay. These named effects switch them on, in the simulated plant (to make
test data and to study sensitivity) and in the corrected model that the discrepancy workflow
fits (so the plant and the planner can load it).

Two kinds:

- *Smooth* effects enter the equations of motion and so the CasADi dynamics, inverse
  dynamics included (the planner can use them): friction at the leg pivots (shared and
  per leg), payload, link mass error, motor-gain error (shared and per leg), gravity tilt,
  the sign of the Kd term, and the encoder home-angle offset (it changes no dynamics, only
  the map from counts to leg angles: ``encoder_params``). They are packed into the vector
  :meth:`Effects.smooth_vector` in :data:`SMOOTH_EFFECT_FIELDS` order, which is an input of
  every function of :mod:`falcon_plan.model.symbolic`.
- *Plant-only* effects change the signal path and need extra states or memory: extra command
  delay, backlash (cable slop) and cable compliance. The simulated plant implements them.

Most parameters are one scalar shared by the three legs (the legs are built alike). The
per-leg terms (the paper found the saturation "changed slightly depending on the motor and
unit") are separate scalars per leg, ``*_leg0`` (top), ``*_leg1`` (right), ``*_leg2`` (left),
on top of the shared one. Units are in the field names.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.params import FalconParams
from falcon_plan.validation import require_known_fields

COULOMB_SMOOTHING_RAD_S = 0.02
"""Default velocity scale of the tanh that smooths the Coulomb and Stribeck sign(theta1_dot)
[rad/s] (the :attr:`Effects.friction_smoothing_rad_s` default)."""

LEG_COULOMB_FIELDS = ("coulomb_leg0_Nm", "coulomb_leg1_Nm", "coulomb_leg2_Nm")
"""Per-leg extra Coulomb friction fields, leg order."""
LEG_GAIN_FIELDS = ("motor_gain_leg0", "motor_gain_leg1", "motor_gain_leg2")
"""Per-leg motor-gain multipliers, leg order."""

SMOOTH_EFFECT_FIELDS = (
    "coulomb_Nm", "viscous_Nms", "stribeck_Nm", "stribeck_velocity_rad_s", "payload_kg",
    "motor_gain", "gravity_tilt_x_rad", "gravity_tilt_z_rad", "kd_sign",
    *LEG_COULOMB_FIELDS, *LEG_GAIN_FIELDS, "link_mass_scale", "encoder_offset_rad",
    "friction_smoothing_rad_s",
)
"""Order of the smooth-effect parameter vector passed to the symbolic dynamics."""

EFFECT_NAMES = (
    "coulomb_friction", "viscous_friction", "stribeck_friction", "command_delay", "backlash",
    "cable_compliance", "payload_mass", "motor_gain", "gravity_tilt", "kd_sign",
    "leg_friction", "leg_motor_gain", "encoder_offset", "link_mass",
)
"""The named candidate effects (the discrepancy workflow's library uses these names)."""


@dataclass(frozen=True)
class Effects:
    """Extra effects on top of the nominal model; the defaults are the nominal model.

    Friction torques act at each leg pivot i, opposing the leg's angular velocity theta1_dot:
    tau_f = -(viscous * w + (coulomb + coulomb_leg_i + stribeck * exp(-(w / v_s)^2)) * tanh(w / w_s)),
    w_s = friction_smoothing_rad_s.
    The motor torque of leg i is scaled by motor_gain * motor_gain_leg_i.

    Attributes
    ----------
    coulomb_Nm, viscous_Nms, stribeck_Nm : friction at every leg pivot: Coulomb [N.m],
        viscous [N.m.s/rad] and Stribeck break-away [N.m] torques, all >= 0;
        stribeck_velocity_rad_s : v_s [rad/s], > 0.
    friction_smoothing_rad_s : w_s [rad/s], > 0, the speed scale of the friction's smoothed
        sign (a parameter of the Coulomb, Stribeck and per-leg friction effects, not an effect
        of its own; smaller is closer to stick-slip).
    coulomb_leg0_Nm, coulomb_leg1_Nm, coulomb_leg2_Nm : extra Coulomb friction of legs 0
        (top), 1 (right), 2 (left) [N.m], >= 0.
    motor_gain, motor_gain_leg0, motor_gain_leg1, motor_gain_leg2 : shared and per-leg
        multipliers on the motor gains Ks and Kd, > 0.
    payload_kg : point mass at the end effector [kg], >= 0; link_mass_scale : multiplier on
        each leg body's mass and inertia, > 0.
    gravity_tilt_x_rad, gravity_tilt_z_rad : rotation of gravity about the base x / z axis
        [rad]; kd_sign : +1 or -1, the sign of the Kd term.
    encoder_offset_rad : true home angle minus the parameter set's [rad], within +-0.5.
    extra_delay_samples : command delay beyond the nominal 2 samples (whole, >= 0);
        backlash_rad : cable slop in leg angle [rad], >= 0; cable_stiffness_Nm_rad : cable
        stiffness at the leg [N.m/rad], > 0, inf for rigid (these three: plant only).
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
    coulomb_leg0_Nm: float = 0.0
    """Extra Coulomb friction at the top leg's pivot (on top of coulomb_Nm) [N.m]."""
    coulomb_leg1_Nm: float = 0.0
    """Extra Coulomb friction at the right leg's pivot [N.m]."""
    coulomb_leg2_Nm: float = 0.0
    """Extra Coulomb friction at the left leg's pivot [N.m]."""
    motor_gain_leg0: float = 1.0
    """Multiplier on the top leg's motor gain (on top of motor_gain)."""
    motor_gain_leg1: float = 1.0
    """Multiplier on the right leg's motor gain."""
    motor_gain_leg2: float = 1.0
    """Multiplier on the left leg's motor gain."""
    link_mass_scale: float = 1.0
    """Multiplier on each leg body's mass and inertia about its pivot (Table 2's 89.59 g leg;
    the reflected motor inertia is not scaled): a link mass error, unlike a payload at p."""
    encoder_offset_rad: float = 0.0
    """True home angle minus the parameter set's theta_home [rad] (the paper measured about
    50 deg where libnifalcon assumes 30): theta1 = theta_home + offset + counts / counts_per_rad."""
    friction_smoothing_rad_s: float = COULOMB_SMOOTHING_RAD_S
    """Speed scale w_s of the tanh(w / w_s) that smooths the sign of the Coulomb, Stribeck and
    per-leg friction torques [rad/s]; sharper than the default 0.02 needs more plant RK4
    substeps (:func:`falcon_plan.sim.equations.friction_substeps`)."""
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
                  "extra_delay_samples", *LEG_COULOMB_FIELDS]
        for name in nonneg:
            if getattr(self, name) < 0:
                raise InvalidParameterError(f"effect {name} must be >= 0, got {getattr(self, name)}")
        if self.stribeck_velocity_rad_s <= 0:
            raise InvalidParameterError("stribeck_velocity_rad_s must be > 0")
        if not (0 < self.friction_smoothing_rad_s < math.inf):
            raise InvalidParameterError("friction_smoothing_rad_s must be a finite speed > 0 [rad/s], "
                                        f"got {self.friction_smoothing_rad_s}")
        for name in ("motor_gain", *LEG_GAIN_FIELDS, "link_mass_scale"):
            if getattr(self, name) <= 0:
                raise InvalidParameterError(f"{name} must be > 0, got {getattr(self, name)}")
        if abs(self.encoder_offset_rad) > 0.5:
            raise InvalidParameterError("encoder_offset_rad must be within +-0.5 rad, "
                                        f"got {self.encoder_offset_rad}")
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

    def encoder_params(self, params: FalconParams) -> FalconParams:
        """``params`` with the home angle corrected by :attr:`encoder_offset_rad` (use it
        wherever counts are turned into angles or points, and back)."""
        if self.encoder_offset_rad == 0.0:
            return params
        return params.replace(theta_home_rad=params.theta_home_rad + self.encoder_offset_rad)

    def replace(self, **changes: Any) -> "Effects":
        """A copy with the effects named in ``changes`` set to their values (validated)."""
        return dataclasses.replace(self, **changes)

    def for_linear_design(self) -> "Effects":
        """These effects without the friction that switches with the sign of the leg speed
        (Coulomb, per-leg Coulomb, Stribeck), for a controller's linearisation: the smoothed
        sign's slope at rest, (coulomb + stribeck) / w_s, is not damping (0.5 N.m.s/rad for
        0.01 N.m at the default w_s, gone once a leg moves faster than w_s); a design that took
        it for damping would drop its own (measured: the hold rang at the command limit on the
        emulated Falcon). That friction is left to the feed-forward and to the observer's
        disturbance estimate."""
        return dataclasses.replace(self, coulomb_Nm=0.0, stribeck_Nm=0.0,
                                   **{name: 0.0 for name in LEG_COULOMB_FIELDS})

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
        """Inverse of :meth:`to_dict`: the effects in ``data`` (name -> value, "inf"
        allowed), the others nominal; unknown keys are an error naming them."""
        require_known_fields(cls, data, InvalidParameterError)
        return cls(**{k: (math.inf if v == "inf" else v) for k, v in data.items()})


NOMINAL = Effects()
