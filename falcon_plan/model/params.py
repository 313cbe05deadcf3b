"""Physical parameters of the Novint Falcon.

Every number comes from the characterisation paper (Martin & Hillier, ACRA 2009, in
``shared/seed``) as read by ``shared/MODEL-CONVENTIONS.md``. SI units throughout; the unit of
each field is in its name (``_m``, ``_kg``, ``_kgm2``, ``_rad``) or its docstring.

Two named, immutable sets are provided:

- :data:`ACRA2009` -- the paper's Tables 1-3, encoder, drive ratio, home angle and command
  range. This is the project's default.
- :data:`LIBNIFALCON` -- the geometry the libnifalcon driver uses (for comparison only); all
  non-geometric values are the paper's.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from falcon_plan.errors import InvalidParameterError
from falcon_plan.validation import require_known_fields

GRAVITY_M_S2 = 9.81
"""Magnitude of gravity [m/s^2]; it points along -y in the base frame."""


@dataclass(frozen=True)
class FalconParams:
    """One complete, immutable parameter set of the Falcon.

    Frame (MODEL-CONVENTIONS "Frame"): origin at the centre of the base plate, x right, y up,
    z out of the device toward the user. Legs 0 (top), 1 (right), 2 (left).

    Attributes
    ----------
    name : the set's name; trajectories and logs record it, and a trajectory only runs
        with the set it was planned with.
    a_m, b_m, c_m, d_m, e_m, f_m, g_m, r_m, s_m : the paper's Table 1 link lengths and
        offsets [m] (each described at its field); a, b, d, e > 0.
    leg_azimuth_deg : azimuth of legs 0, 1, 2 from +x in the x-y plane [deg].
    encoder_counts_per_rev : encoder counts per motor turn; drive_ratio : motor turns per leg
        turn (> 0); theta_home_rad : leg angle theta1 at encoder count 0 [rad].
    ks_Nm, kd_Nms : static [N.m per command unit] (> 0) and speed-dependent [N.m.s/rad per
        command unit] motor torque gains (Table 3); motor_inertia_kgm2 : motor inertia
        [kg.m^2].
    command_limit : largest |command| the firmware takes [command units];
        command_saturation : the static torque stops growing past this |command|, in
        (0, command_limit].
    leg_mass_kg, leg_com_m, leg_izz_kgm2 : leg mass [kg] (> 0), centre of mass in the leg's
        frame [m], inertia about the pivot axis through the centre of mass [kg.m^2]
        (Table 2).
    shin_bar_mass_kg, shin_bar_com_m, shin_bar_inertia_kgm2 : the same for one shin bar.
    shin_joint_mass_kg, shin_joint_com_m, shin_joint_inertia_kgm2 : the same for one shin
        joint.
    effector_mass_kg, effector_com_m : end-effector mass [kg] (> 0) and centre of mass [m].
    nominal_rate_hz : the device's nominal loop rate [Hz], > 0.
    command_delay_samples : samples from issuing a command to it acting on the motors.
    link_delay_samples : further samples by which a host loop's readings trail its commands
        (the USB path; fractional, >= 0; measured by ``doctor``).
    command_hold_s : the simulated firmware drops the force this long after the last
        command [s].
    notes : free text on where the values come from (not compared).
    """

    name: str

    # --- Table 1 geometry [m] -----------------------------------------------------------
    a_m: float = 60.0e-3
    """Leg length: base pivot to knee."""
    b_m: float = 102.5e-3
    """Shin-bar length of the parallelogram."""
    c_m: float = 15.7e-3
    """Radial offset of the end-effector joint (enters as r - c)."""
    d_m: float = 11.5e-3
    """Knee to the bars' knee-side end, along the shin."""
    e_m: float = 11.5e-3
    """Bars' effector-side end to the end-effector joint, along the shin."""
    f_m: float = 26.2e-3
    """Tangential offset of the end-effector joint (enters as s - f)."""
    g_m: float = 27.9e-3
    """Table 1's g. It has no role in the kinematic equations (nor in public code that uses
    the paper's values); kept so that the set is the paper's table, complete."""
    r_m: float = 36.6e-3
    """Radius of the leg pivot from the base centre."""
    s_m: float = 27.2e-3
    """Tangential offset of the leg pivot (enters as s - f)."""
    leg_azimuth_deg: tuple[float, float, float] = (105.0, -15.0, -135.0)
    """Azimuth of each leg's radial direction, from +x in the x-y plane [deg]."""

    # --- encoders and drive --------------------------------------------------------------
    encoder_counts_per_rev: int = 1280
    """320 lines x 4 states per motor turn."""
    drive_ratio: float = 7.62
    """Cable drive ratio N, leg to motor (motor turns N times per leg turn)."""
    theta_home_rad: float = math.radians(40.0)
    """Leg angle theta1 at encoder count 0: 40 deg from the base plane (the paper's ~50 deg
    between line a and the z axis)."""

    # --- Table 3 motor model: To = Tc (Ks + Kd w_m) ---------------------------------------
    ks_Nm: float = 1.9835e-5
    """Static torque gain Ks [N.m of motor torque per command unit]."""
    kd_Nms: float = 1.3779e-8
    """Dynamic torque gain Kd [N.m.s/rad per command unit]."""
    motor_inertia_kgm2: float = 1.0e-5
    """Motor inertia Im; reflected to the leg as Im N^2."""
    command_limit: int = 4096
    """|Tc| never exceeds this (the firmware's command range)."""
    command_saturation: int = 2500
    """Static saturation: To stopped growing past |Tc| = 2500 in static tests."""

    # --- Table 2 inertial properties (per leg unless said) ---------------------------------
    leg_mass_kg: float = 89.59e-3
    leg_com_m: tuple[float, float] = (-3.19e-3, 23.34e-3)
    """Leg centre of mass in the leg's frame: x along line a (pivot to knee), y the way the
    knee moves as theta1 grows."""
    leg_izz_kgm2: float = 140.0e-6
    """Leg inertia about its centre of mass, about the pivot axis."""
    shin_bar_mass_kg: float = 8.37e-3
    """Mass of one shin bar (two per leg)."""
    shin_bar_com_m: float = 56.35e-3
    """Distance of a bar's centre of mass from its knee-side end C, along the bar."""
    shin_bar_inertia_kgm2: float = 8.5e-6
    """Transverse inertia of one bar about its centre of mass (Iyy = Izz)."""
    shin_joint_mass_kg: float = 10.42e-3
    """Mass of one shin joint (two per leg: knee side and effector side)."""
    shin_joint_com_m: float = 15.61e-3
    """Table 2's shin-joint centre-of-mass offset; unused by the nominal model, which treats
    the joint as a point mass at its hinge (MODEL-CONVENTIONS)."""
    shin_joint_inertia_kgm2: float = 0.7e-6
    """Inertia of one shin joint about its hinge axis."""
    effector_mass_kg: float = 82.73e-3
    effector_com_m: tuple[float, float, float] = (15.7e-3, 26.2e-3, 48.78e-3)
    """End-effector centre of mass; it only translates, so this offset adds only a constant
    to the potential energy."""

    # --- timing (MODEL-CONVENTIONS "Time and communication") --------------------------------
    nominal_rate_hz: float = 1000.0
    """The device's nominal loop rate; real links reach 800-1000 Hz."""
    command_delay_samples: int = 2
    """Samples between a command being issued and it acting on the motors (the paper's
    simulation)."""
    command_hold_s: float = 0.1
    """The firmware drops the force this long after the last command."""
    link_delay_samples: float = field(default=0.0, compare=False)
    """Control samples by which the readings a host loop gets trail its commands beyond
    ``command_delay_samples``: the USB path (frames, the FTDI latency timer, the driver's I/O
    threads) as the loop sees it; fractional, >= 0; 0 when each reading answers its own command
    (the simulated plant). Measured by ``falcon-plan doctor``, which writes it into its model
    file. Not part of the set's identity: the dynamics do not depend on it."""

    notes: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        positive = ["a_m", "b_m", "d_m", "e_m", "drive_ratio", "ks_Nm", "leg_mass_kg",
                    "effector_mass_kg", "nominal_rate_hz"]
        for key in positive:
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidParameterError(f"parameter {key} must be a finite number > 0, got {value!r}")
        for key in ("encoder_counts_per_rev", "command_delay_samples", "command_limit"):
            value = getattr(self, key)
            low = 0 if key == "command_delay_samples" else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise InvalidParameterError(f"parameter {key} must be a whole number >= {low}, got {value!r}")
        link = self.link_delay_samples
        if isinstance(link, bool) or not (isinstance(link, (int, float)) and math.isfinite(link) and link >= 0):
            raise InvalidParameterError(f"parameter link_delay_samples must be a finite number >= 0 "
                                        f"[control samples], got {link!r}")
        if len(self.leg_azimuth_deg) != 3:
            raise InvalidParameterError("leg_azimuth_deg must hold exactly 3 angles")
        if not 0 < self.command_saturation <= self.command_limit:
            raise InvalidParameterError(
                f"command_saturation must be in (0, command_limit={self.command_limit}], "
                f"got {self.command_saturation}")

    # --- derived quantities ----------------------------------------------------------------
    @property
    def counts_per_rad(self) -> float:
        """Encoder counts per radian of leg angle theta1 (1280 N / 2 pi ~ 1552.3)."""
        return self.encoder_counts_per_rev * self.drive_ratio / (2.0 * math.pi)

    @property
    def radial_offset_m(self) -> float:
        """r - c: the constant in the radial leg equation [m]."""
        return self.r_m - self.c_m

    @property
    def tangential_offset_m(self) -> float:
        """s - f: the constant in the tangential leg equation [m]."""
        return self.s_m - self.f_m

    @property
    def leg_inertia_about_pivot_kgm2(self) -> float:
        """Izz + m |cm|^2 + Im N^2: the leg's inertia about its pivot with the reflected motor."""
        cx, cy = self.leg_com_m
        return (self.leg_izz_kgm2 + self.leg_mass_kg * (cx * cx + cy * cy)
                + self.motor_inertia_kgm2 * self.drive_ratio ** 2)

    def replace(self, **changes: Any) -> "FalconParams":
        """A copy with the fields named in ``changes`` set to their values (the set itself is
        immutable; the copy is validated)."""
        return dataclasses.replace(self, **changes)

    # --- persistence -----------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict of every field."""
        out = dataclasses.asdict(self)
        for key, value in out.items():
            if isinstance(value, tuple):
                out[key] = list(value)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "FalconParams":
        """Build from ``data``, :meth:`to_dict` output (lists become tuples); unknown keys are
        an error naming them."""
        require_known_fields(cls, data, InvalidParameterError)
        kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        return cls(**kwargs)

    def save(self, path: str | Path) -> None:
        """Write as JSON to ``path``."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | Path) -> "FalconParams":
        """Read ``path``, a JSON file written by :meth:`save`."""
        return cls.from_dict(json.loads(Path(path).read_text()))


ACRA2009 = FalconParams(
    name="acra2009",
    notes="Martin & Hillier, ACRA 2009, Tables 1-3, read per MODEL-CONVENTIONS.md",
)
"""The paper's parameter set: the project's default."""

LIBNIFALCON = FalconParams(
    name="libnifalcon",
    c_m=14.43e-3,
    d_m=11.25e-3,
    e_m=11.25e-3,
    r_m=40.0e-3,
    # Only s - f enters the equations; libnifalcon's is 1.91 mm. f is kept at the paper's
    # value and s chosen to give that difference.
    s_m=26.2e-3 + 1.91e-3,
    # The paper reports libnifalcon's look-up tables use a 30 deg home offset against the
    # measured 50 deg, both from the z axis; from the base plane that is 60 deg.
    theta_home_rad=math.radians(60.0),
    notes="libnifalcon's kinematic constants; everything else as acra2009",
)
"""libnifalcon's geometry, kept for comparison."""

PARAMETER_SETS: dict[str, FalconParams] = {p.name: p for p in (ACRA2009, LIBNIFALCON)}


def get_params(name_or_path: str | FalconParams = "acra2009") -> FalconParams:
    """The parameter set ``name_or_path`` names: a set's name (``acra2009``, ``libnifalcon``),
    the path of a ``.json`` file written by :meth:`FalconParams.save`, or a FalconParams
    (returned as it is)."""
    if isinstance(name_or_path, FalconParams):
        return name_or_path
    if name_or_path in PARAMETER_SETS:
        return PARAMETER_SETS[name_or_path]
    path = Path(name_or_path)
    if path.suffix == ".json" and path.exists():
        return FalconParams.load(path)
    raise InvalidParameterError(
        f"unknown parameter set {name_or_path!r}; allowed: {sorted(PARAMETER_SETS)} or a .json file")
