"""FalconParams: the paper's tables, immutability, persistence, the libnifalcon set."""
from __future__ import annotations

import dataclasses
import math

import pytest

from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.params import ACRA2009, LIBNIFALCON, FalconParams, get_params

# Table 1 of the paper [mm], every entry.
TABLE1_MM = {"a_m": 60.0, "b_m": 102.5, "c_m": 15.7, "d_m": 11.5, "e_m": 11.5, "f_m": 26.2,
             "g_m": 27.9, "r_m": 36.6, "s_m": 27.2}


@pytest.mark.parametrize("key,mm", sorted(TABLE1_MM.items()))
def test_table1_geometry(key: str, mm: float) -> None:
    assert getattr(ACRA2009, key) == pytest.approx(mm * 1e-3, rel=1e-12)


def test_table2_inertial_properties() -> None:
    p = ACRA2009
    assert p.leg_mass_kg == pytest.approx(89.59e-3)
    assert p.leg_com_m == pytest.approx((-3.19e-3, 23.34e-3))
    assert p.leg_izz_kgm2 == pytest.approx(140e-6)
    assert p.shin_bar_mass_kg == pytest.approx(8.37e-3)
    assert p.shin_bar_com_m == pytest.approx(56.35e-3)
    assert p.shin_bar_inertia_kgm2 == pytest.approx(8.5e-6)
    assert p.shin_joint_mass_kg == pytest.approx(10.42e-3)
    assert p.shin_joint_com_m == pytest.approx(15.61e-3)
    assert p.shin_joint_inertia_kgm2 == pytest.approx(0.7e-6)
    assert p.effector_mass_kg == pytest.approx(82.73e-3)
    assert p.effector_com_m == pytest.approx((15.7e-3, 26.2e-3, 48.78e-3))


def test_table3_motor_and_drive() -> None:
    p = ACRA2009
    assert (p.kd_Nms, p.ks_Nm, p.motor_inertia_kgm2) == (1.3779e-8, 1.9835e-5, 1e-5)
    assert p.encoder_counts_per_rev == 320 * 4
    assert p.drive_ratio == 7.62
    assert math.degrees(p.theta_home_rad) == pytest.approx(40.0)
    assert (p.command_limit, p.command_saturation) == (4096, 2500)
    assert p.leg_azimuth_deg == (105.0, -15.0, -135.0)
    # derived: 1280 * 7.62 counts per leg turn; reflected motor inertia Im N^2 in the leg's
    assert p.counts_per_rad == pytest.approx(1280 * 7.62 / (2 * math.pi))
    cx, cy = p.leg_com_m
    assert p.leg_inertia_about_pivot_kgm2 == pytest.approx(
        140e-6 + 89.59e-3 * (cx * cx + cy * cy) + 1e-5 * 7.62 ** 2)


def test_immutable() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        ACRA2009.a_m = 0.1  # type: ignore[misc]
    changed = ACRA2009.replace(a_m=0.07)
    assert changed.a_m == 0.07 and ACRA2009.a_m == 0.06


def test_round_trip_dict_and_file(tmp_path) -> None:
    for params in (ACRA2009, LIBNIFALCON):
        assert FalconParams.from_dict(params.to_dict()) == params
        path = tmp_path / f"{params.name}.json"
        params.save(path)
        loaded = FalconParams.load(path)
        assert loaded == params and loaded.leg_com_m == params.leg_com_m
        assert get_params(str(path)) == params


def test_unknown_key_names_it() -> None:
    data = ACRA2009.to_dict() | {"shin_lenght_m": 0.1}
    with pytest.raises(InvalidParameterError, match="shin_lenght_m"):
        FalconParams.from_dict(data)


def test_invalid_values_rejected() -> None:
    with pytest.raises(InvalidParameterError, match="a_m"):
        ACRA2009.replace(a_m=-1.0)
    with pytest.raises(InvalidParameterError, match="command_saturation"):
        ACRA2009.replace(command_saturation=5000)
    with pytest.raises(InvalidParameterError, match="allowed"):
        get_params("no-such-set")


def test_libnifalcon_differences() -> None:
    fields = {f.name for f in dataclasses.fields(FalconParams)} - {"name", "notes"}
    differing = {k for k in fields if getattr(ACRA2009, k) != getattr(LIBNIFALCON, k)}
    assert differing == {"c_m", "d_m", "e_m", "r_m", "s_m", "theta_home_rad"}
    assert (LIBNIFALCON.a_m, LIBNIFALCON.b_m) == (60e-3, 102.5e-3)
    assert LIBNIFALCON.c_m == pytest.approx(14.43e-3)
    assert LIBNIFALCON.d_m == LIBNIFALCON.e_m == pytest.approx(11.25e-3)
    assert LIBNIFALCON.r_m == pytest.approx(40.0e-3)
    assert LIBNIFALCON.tangential_offset_m == pytest.approx(1.91e-3, abs=1e-12)
    assert ACRA2009.tangential_offset_m == pytest.approx(1.0e-3, abs=1e-12)
    assert get_params("libnifalcon") is LIBNIFALCON and get_params() is ACRA2009
