"""The Section 5 characterisation and the ``characterise`` command."""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest

from falcon_plan import cli
from falcon_plan.commands import characterise as command
from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.characterise import (
    MAKER_VOLUME_M3, PAPER_VOLUME_M3, binomial_ci95, characterise, reach_box_m)
from falcon_plan.model.kinematics import inverse_kinematics, jacobian
from falcon_plan.model.params import ACRA2009


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Run the command once with small sample counts (through its own registered parser)."""
    out = tmp_path_factory.mktemp("characterise")
    parser = argparse.ArgumentParser()
    command.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["characterise", "--out", str(out), "--samples", "40000",
                              "--map-points", "1500", "--seed", "3"])
    assert args.func(args) == 0
    return out


@pytest.fixture(scope="module")
def summary(run_dir: Path) -> dict:
    return json.loads((run_dir / "summary.json").read_text())


def test_registered_with_the_dispatcher() -> None:
    assert "characterise" in cli.COMMAND_MODULES
    parser = argparse.ArgumentParser()
    command.register(parser.add_subparsers(dest="command"))
    with pytest.raises(SystemExit):
        parser.parse_args(["characterise", "--out", "x", "--samples", "-5"])


def test_summary_keys(summary: dict) -> None:
    assert {"params", "limits", "seed", "workspace_volume", "resolution", "torque_for_3N",
            "encoder_zero_pose", "runtime_s"} <= set(summary)
    volume = summary["workspace_volume"]
    for key in ("default_limits", "geometric_reachability", "geometric_reachability_front_of_base"):
        est = volume[key]
        assert est["ci95_m3"][0] <= est["volume_m3"] <= est["ci95_m3"][1]
        assert est["box_encloses"] and est["samples"] == 40000
    assert volume["paper_m3"] == PAPER_VOLUME_M3
    assert volume["maker_4in_cube_m3"] == pytest.approx(1.0488e-3, rel=1e-4)
    assert "4-inch" in volume["explanation"] and "7.90e-05" in volume["explanation"]
    assert {"x", "y", "z"} <= set(summary["torque_for_3N"])


def test_volumes_are_ordered_and_explained(summary: dict) -> None:
    volume = summary["workspace_volume"]
    ours = volume["default_limits"]["volume_m3"]
    # the project's limits give about the maker's cube; geometric reach is far larger
    assert 0.85 * MAKER_VOLUME_M3 < ours < 1.2 * MAKER_VOLUME_M3
    assert volume["geometric_reachability_front_of_base"]["volume_m3"] > 2 * ours
    assert volume["geometric_reachability"]["volume_m3"] > volume["geometric_reachability_front_of_base"]["volume_m3"]
    # the leg-range table grows with the range, and brackets the paper's value
    rows = volume["leg_range_table"]
    symmetric = [r["volume_m3"] for r in rows if math.isclose(r["theta1_min_deg"] + r["theta1_max_deg"], 80.0)]
    assert all(a < b for a, b in zip(symmetric, symmetric[1:]))
    assert symmetric[0] < PAPER_VOLUME_M3 < symmetric[-1]
    assert 10.0 < volume["paper_range_half_width_deg"] < 30.0
    # the table's row for the default range re-estimates the default volume from other samples
    # in another box: the two agree within their sampling error
    default_row = next(r for r in rows if (r["theta1_min_deg"], r["theta1_max_deg"]) == (-20.0, 80.0))
    assert default_row["volume_m3"] == pytest.approx(ours, rel=0.08)


def test_resolution_near_the_papers_30_counts_per_mm(run_dir: Path, summary: dict) -> None:
    res = summary["resolution"]
    alternatives = res["alternatives_counts_per_mm"]
    assert res["statistic"] == "norm" and res["mean_counts_per_mm"] == alternatives["norm"]
    # the mean counts per mm, computed independently to first order from the Jacobian over
    # the same points (the norm of the 3-leg count change of a 1 mm step, averaged over axes)
    points = np.load(run_dir / "maps.npz")["points_m"]
    linear = np.linalg.norm(jacobian(points), axis=-2).mean(axis=-1) * ACRA2009.counts_per_rad * 1e-3
    expected = float(linear.mean())
    assert res["mean_counts_per_mm"] == pytest.approx(expected, rel=0.01)
    # the claim against the paper's 30 counts/mm follows from that value, and says so
    within = abs(expected / 30.0 - 1.0) <= 0.15
    assert res["within_15_percent"] == within
    assert ("(within 15 %)" in res["explanation"]) == within
    assert ("outside 15 %" in res["explanation"]) == (not within)
    # the readings are ordered as they must be for non-negative leg changes
    assert (alternatives["mean_per_leg"] <= alternatives["max_leg"] <= alternatives["norm"]
            <= alternatives["sum_over_legs"])
    assert res["neighbours_unreachable"] == 0


def test_resolution_map_matches_the_jacobian(run_dir: Path) -> None:
    """For a 1 mm step the count change is linear to first order: the map must be close to
    the mean over axes of |J e_k| counts_per_rad 1e-3."""
    maps = np.load(run_dir / "maps.npz")
    jac = jacobian(maps["points_m"])
    linear = np.linalg.norm(jac, axis=-2).mean(axis=-1) * ACRA2009.counts_per_rad * 1e-3
    assert np.allclose(maps["counts_per_mm"], linear, rtol=0.02)


def test_torque_maps_equal_inverse_transpose_jacobian(run_dir: Path, summary: dict) -> None:
    maps = np.load(run_dir / "maps.npz")
    points = maps["points_m"]
    inv_t = np.swapaxes(np.linalg.inv(jacobian(points)), -1, -2)
    for axis, name in enumerate("xyz"):
        force = np.zeros(3)
        force[axis] = 3.0
        expected = inv_t @ force
        assert np.allclose(maps[f"torque_{name}_Nm"], expected, rtol=1e-10, atol=1e-14)
        rms = np.sqrt(np.mean(expected ** 2, axis=-1))
        assert np.allclose(maps[f"rms_torque_{name}_Nm"], rms, rtol=1e-12)
        assert summary["torque_for_3N"][name]["rms_torque_mean_Nm"] == pytest.approx(rms.mean(), rel=1e-9)
        assert summary["torque_for_3N"][name]["max_leg_command"] == pytest.approx(
            np.abs(expected).max() / (ACRA2009.drive_ratio * ACRA2009.ks_Nm), rel=1e-9)


def test_encoder_zero_pose(summary: dict) -> None:
    home = summary["encoder_zero_pose"]
    x, y, z = home["position_m"]
    assert abs(x) < 1e-12 and abs(y) < 1e-12 and 0.10 < z < 0.18
    assert home["angle_line_a_to_z_axis_deg"] == pytest.approx(50.0)
    assert np.allclose(inverse_kinematics(home["position_m"]).theta1, ACRA2009.theta_home_rad, atol=1e-12)
    assert home["inside_workspace"]


def test_pngs_written(run_dir: Path) -> None:
    for name in ("fig4_workspace.png", "fig5_resolution.png", "fig6_torque_z.png",
                 "fig7_torque_x.png", "fig8_torque_y.png"):
        data = (run_dir / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000


def test_progress_and_errors(capsys: pytest.CaptureFixture[str]) -> None:
    messages: list[str] = []
    result = characterise(samples=500, map_points=20, seed=1, progress=messages.append)
    assert len(messages) == 5 and "resolution" in messages[3]
    assert result.map_points_m.shape == (20, 3) and result.torques_Nm["x"].shape == (20, 3)
    assert capsys.readouterr().err == ""  # the library itself prints nothing
    with pytest.raises(InvalidParameterError, match="samples"):
        characterise(samples=10)


def test_binomial_interval() -> None:
    lo, hi = binomial_ci95(0, 1000)
    assert lo == 0.0 and hi == pytest.approx(1 - 0.025 ** (1 / 1000), rel=1e-9)
    lo, hi = binomial_ci95(500, 1000)
    assert lo == pytest.approx(1 - hi, rel=1e-9) and lo < 0.5 < hi and hi - lo == pytest.approx(0.063, abs=0.002)
    with pytest.raises(InvalidParameterError):
        binomial_ci95(5, 3)


def test_reach_box_holds_every_reachable_point() -> None:
    (lo, _, _), (hi, _, _) = reach_box_m(ACRA2009)
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    outside = directions * hi * 1.001  # on a sphere just outside the box's inscribed sphere
    assert not inverse_kinematics(outside, strict=False).reachable.all(axis=-1).any()
    assert lo == -hi
