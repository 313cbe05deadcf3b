"""The library of candidate effects: each a small parametric model with a physical meaning.

Every candidate is named as in :data:`falcon_plan.model.effects.EFFECT_NAMES` and owns one or
two fields of :class:`~falcon_plan.model.effects.Effects`. How its evidence is measured
depends on how it enters the model:

- ``smooth``: the parameter is an entry of the smooth-effect vector ``eff`` of the CasADi
  dynamics, so it changes the inverse dynamics; evidence and fit use the inverse-dynamics
  residual (logged commands minus the commands the model needs for the measured motion).
  ``kd_sign`` is fitted as a continuous factor ``s`` on the Kd term (the dynamics are
  smooth in it) and rounded to +-1 for the corrected model.
- ``delay``: extra samples of transport delay; changes which logged command is compared with
  the motion (a discrete search over whole samples).
- ``encoder``: the encoder home-angle offset; it changes no dynamics but the map from counts
  to leg angles, so the motion is re-estimated from the counts for each trial offset (a
  bounded scalar search) and the smooth parameters of the set are refitted on it.
- ``replay``: the plant-only signal-path effects (backlash, cable compliance) that need
  extra states; evidence and fit use the error of replaying the training log through the
  simulated plant.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from falcon_plan.model.effects import (EFFECT_NAMES, LEG_COULOMB_FIELDS, LEG_GAIN_FIELDS,
                                      SMOOTH_EFFECT_FIELDS)


@dataclass(frozen=True)
class EffectParameter:
    """One fitted parameter of a candidate effect.

    ``field`` is the Effects field it sets, ``unit`` its unit (text) (for cable compliance the fitted quantity is the
    compliance 1/k [rad/N.m], ``field`` the stiffness); ``nominal`` its value in the nominal
    model, ``lower``/``upper`` its bounds in the fit, ``scale`` a typical magnitude (used to
    condition the fit and to start nonlinear searches).
    """

    field: str
    unit: str
    nominal: float
    lower: float
    upper: float
    scale: float


@dataclass(frozen=True)
class CandidateEffect:
    """A named candidate effect: its ``name`` (an EFFECT_NAMES entry), kind (``smooth``,
    ``delay``, ``encoder``, ``replay``), parameters and a one-line physical meaning."""

    name: str
    kind: str
    parameters: tuple[EffectParameter, ...]
    meaning: str

    @property
    def n_parameters(self) -> int:
        """Number of fitted parameters (the penalty count of the information criterion)."""
        return len(self.parameters)


LIBRARY: tuple[CandidateEffect, ...] = (
    CandidateEffect("coulomb_friction", "smooth",
                    (EffectParameter("coulomb_Nm", "N.m", 0.0, 0.0, 0.2, 0.005),),
                    "constant friction torque at each leg pivot, opposing motion"),
    CandidateEffect("viscous_friction", "smooth",
                    (EffectParameter("viscous_Nms", "N.m.s/rad", 0.0, 0.0, 0.5, 0.01),),
                    "friction torque at each pivot proportional to the leg's angular rate"),
    CandidateEffect("stribeck_friction", "smooth",
                    (EffectParameter("stribeck_Nm", "N.m", 0.0, 0.0, 0.2, 0.005),
                     EffectParameter("stribeck_velocity_rad_s", "rad/s", 0.5, 0.03, 1.5, 0.3)),
                    "break-away friction that decays with speed (Stribeck curve)"),
    CandidateEffect("command_delay", "delay",
                    (EffectParameter("extra_delay_samples", "samples", 0.0, 0.0, 6.0, 1.0),),
                    "transport delay beyond the nominal 2 samples"),
    CandidateEffect("backlash", "replay",
                    (EffectParameter("backlash_rad", "rad", 0.0, 0.0, 0.04, 0.005),),
                    "cable slop between motor (encoder) and leg"),
    CandidateEffect("cable_compliance", "replay",
                    (EffectParameter("cable_stiffness_Nm_rad", "N.m/rad", math.inf, 0.5, math.inf, 20.0),),
                    "elastic cable between motor (encoder) and leg"),
    CandidateEffect("payload_mass", "smooth",
                    (EffectParameter("payload_kg", "kg", 0.0, 0.0, 1.0, 0.02),),
                    "extra point mass carried at the end effector"),
    CandidateEffect("motor_gain", "smooth",
                    (EffectParameter("motor_gain", "1", 1.0, 0.3, 3.0, 0.1),),
                    "motor torque constant Ks (and Kd) off by a common factor"),
    CandidateEffect("gravity_tilt", "smooth",
                    (EffectParameter("gravity_tilt_x_rad", "rad", 0.0, -0.6, 0.6, 0.05),
                     EffectParameter("gravity_tilt_z_rad", "rad", 0.0, -0.6, 0.6, 0.05)),
                    "device base tilted: gravity rotated about x and z"),
    CandidateEffect("kd_sign", "smooth",
                    (EffectParameter("kd_sign", "1", 1.0, -3.0, 3.0, 1.0),),
                    "the speed term Kd of the motor model with the opposite sign"),
    CandidateEffect("leg_friction", "smooth",
                    tuple(EffectParameter(f, "N.m", 0.0, 0.0, 0.2, 0.005) for f in LEG_COULOMB_FIELDS),
                    "Coulomb friction that differs from leg to leg (one torque per pivot)"),
    CandidateEffect("leg_motor_gain", "smooth",
                    tuple(EffectParameter(f, "1", 1.0, 0.3, 3.0, 0.1) for f in LEG_GAIN_FIELDS),
                    "motor torque constant off by a different factor on each motor"),
    CandidateEffect("encoder_offset", "encoder",
                    (EffectParameter("encoder_offset_rad", "rad", 0.0, -0.25, 0.25, 0.02),),
                    "encoder home angle off the parameter set's (counts start elsewhere)"),
    CandidateEffect("link_mass", "smooth",
                    (EffectParameter("link_mass_scale", "1", 1.0, 0.3, 3.0, 0.1),),
                    "the legs' mass and inertia off by a common factor (not a payload at p)"),
)
"""Every candidate, in :data:`EFFECT_NAMES` order."""

CANDIDATES: dict[str, CandidateEffect] = {c.name: c for c in LIBRARY}

assert tuple(CANDIDATES) == EFFECT_NAMES, "the library must cover EFFECT_NAMES in order"
assert all(p.field in SMOOTH_EFFECT_FIELDS for c in LIBRARY if c.kind in ("smooth", "encoder")
           for p in c.parameters)


def candidate(name: str) -> CandidateEffect:
    """The candidate named ``name``; ValueError listing the names otherwise."""
    if name not in CANDIDATES:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECT_NAMES)}")
    return CANDIDATES[name]


PARAMETER_BOUNDS: dict[str, tuple[float, float]] = {
    p.field: (p.lower, p.upper) for c in LIBRARY for p in c.parameters}
"""Every fitted Effects field -> its (lower, upper) bounds in the fit (same unit as the field)."""


def clip_to_bounds(values: dict[str, float]) -> dict[str, float]:
    """``values`` (Effects field -> fitted value) with each value clipped into its candidate's
    bounds (:data:`PARAMETER_BOUNDS`; fields without bounds pass unchanged). A bounded solver
    stops within its tolerance of a bound (a Coulomb torque of -1.8e-14 N.m, say): a bound is
    a bound, so the model is built from the clipped values and no fit can fail to build it."""
    out = {}
    for fld, value in values.items():
        lo, hi = PARAMETER_BOUNDS.get(fld, (-math.inf, math.inf))
        out[fld] = float(min(max(float(value), lo), hi))
    return out


def effect_fields(name: str) -> list[str]:
    """The Effects fields the candidate ``name`` sets (``command_delay``: the extra delay)."""
    return ["extra_delay_samples"] if name == "command_delay" else [p.field for p in CANDIDATES[name].parameters]
