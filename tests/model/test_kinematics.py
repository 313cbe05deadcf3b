"""Kinematics: IK/FK round trips, the Jacobian, the two theta1 formulas, encoder maps."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.errors import WorkspaceError
from falcon_plan.model.kinematics import (
    angles_to_counts, counts_to_angles, counts_to_position, forward_kinematics,
    forward_kinematics_point, inverse_kinematics, jacobian, leg_torques_for_force,
    position_to_counts, theta1_half_angle)
from falcon_plan.model.params import ACRA2009, LIBNIFALCON
from falcon_plan.model.workspace import sample_workspace


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    """10,000 points drawn uniformly from the default workspace [m]."""
    return sample_workspace(10_000, np.random.default_rng(2024))


def test_ik_then_fk_returns_the_point(points: np.ndarray) -> None:
    theta1 = inverse_kinematics(points).theta1
    back = forward_kinematics(theta1)
    assert back.shape == points.shape
    assert np.abs(back - points).max() < 1e-10


def test_ik_then_fk_libnifalcon_geometry() -> None:
    pts = sample_workspace(500, np.random.default_rng(3), LIBNIFALCON)
    back = forward_kinematics(inverse_kinematics(pts, LIBNIFALCON).theta1, LIBNIFALCON)
    assert np.abs(back - pts).max() < 1e-10


def test_fk_batch_shape_is_kept(points: np.ndarray) -> None:
    theta1 = inverse_kinematics(points[:12].reshape(3, 4, 3)).theta1
    assert forward_kinematics(theta1).shape == (3, 4, 3)


def test_single_point_fk_agrees_with_batch(points: np.ndarray) -> None:
    pts = points[:200]
    theta1 = inverse_kinematics(pts).theta1
    batch = forward_kinematics(theta1)
    for th, p_batch in zip(theta1, batch):
        cold = forward_kinematics_point(tuple(th))
        assert isinstance(cold[0], float)
        assert np.abs(np.array(cold) - p_batch).max() < 1e-10
    # warm start from a point 1 mm away, as in a control loop
    for th, p in zip(theta1[:50], pts[:50]):
        warm = forward_kinematics_point(tuple(th), seed_m=tuple(p + 1e-3))
        assert np.abs(np.array(warm) - p).max() < 1e-10


def test_jacobian_matches_finite_differences(points: np.ndarray) -> None:
    pts = points[:2000]
    jac = jacobian(pts)
    step = 1e-6
    fd = np.empty_like(jac)
    for axis in range(3):
        dp = np.zeros(3)
        dp[axis] = step
        fd[..., axis] = (inverse_kinematics(pts + dp).theta1 - inverse_kinematics(pts - dp).theta1) / (2 * step)
    rel = np.linalg.norm(jac - fd, axis=(-2, -1)) / np.linalg.norm(jac, axis=(-2, -1))
    assert rel.max() < 1e-6


def test_half_angle_formula_agrees(points: np.ndarray) -> None:
    """Two formulas for the same root agree to rounding (the half-angle form is evaluated in
    its conjugate form; the textbook (w - sqrt(.)) / (K + u) lost up to 1e-9 rad near 0)."""
    for params in (ACRA2009, LIBNIFALCON):
        pts = sample_workspace(2000, np.random.default_rng(5), params) if params is LIBNIFALCON else points
        atan2_form = inverse_kinematics(pts, params).theta1
        assert np.abs(theta1_half_angle(pts, params) - atan2_form).max() < 1e-12


def test_integer_counts_to_angles_and_back_exact() -> None:
    counts = np.random.default_rng(7).integers(-3000, 3000, size=(5000, 3))
    back = angles_to_counts(counts_to_angles(counts))
    assert np.abs(back - counts).max() < 1e-9
    assert np.array_equal(np.rint(back).astype(np.int64), counts)
    assert counts_to_angles(np.zeros(3)) == pytest.approx(np.full(3, ACRA2009.theta_home_rad))
    # one leg turn is 1280 N counts
    assert counts_to_angles(1280 * 7.62) - counts_to_angles(0) == pytest.approx(2 * np.pi)


def test_counts_to_position_and_back_exact(points: np.ndarray) -> None:
    counts = position_to_counts(points[:3000], whole=True)
    assert counts.dtype == np.int64
    again = position_to_counts(counts_to_position(counts), whole=True)
    assert np.array_equal(again, counts)


def test_leg_torques_equal_inverse_transpose_jacobian(points: np.ndarray) -> None:
    pts = points[:500]
    force = np.random.default_rng(9).normal(size=(500, 3))
    tau = leg_torques_for_force(pts, force)
    expected = np.einsum("nji,nj->ni", np.linalg.inv(jacobian(pts)), force)  # J^-T F
    assert np.allclose(tau, expected, rtol=1e-12, atol=1e-15)
    # and F = J^T tau: the force is recovered
    assert np.allclose(np.einsum("nji,nj->ni", jacobian(pts), tau), force, rtol=1e-10, atol=1e-12)


def test_unreachable_point_raises_with_reason() -> None:
    with pytest.raises(WorkspaceError, match="not reachable") as info:
        inverse_kinematics([0.0, 0.0, 0.30])
    assert info.value.reasons and "beyond the reach" in info.value.reasons[0]
    with pytest.raises(WorkspaceError) as info:
        inverse_kinematics([0.0, 0.2, 0.1])
    assert any("tangential offset" in r for r in info.value.reasons)


def test_non_strict_gives_nan_and_mask() -> None:
    pts = np.array([[0.0, 0.0, 0.12], [0.0, 0.0, 0.30], [0.01, -0.02, 0.11]])
    angles = inverse_kinematics(pts, strict=False)
    assert angles.reachable.all(axis=-1).tolist() == [True, False, True]
    assert np.isnan(angles.theta1[1]).all() and np.isfinite(angles.theta1[[0, 2]]).all()


def test_bad_shape_is_rejected() -> None:
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        inverse_kinematics([0.0, 0.1])
    with pytest.raises(ValueError, match="theta1"):
        forward_kinematics(np.zeros(4))


def test_home_pose_is_on_the_axis() -> None:
    """At encoder zero all legs sit at 40 deg, so by symmetry the effector is on the z axis."""
    home = counts_to_position(np.zeros(3))
    assert np.abs(home[:2]).max() < 1e-12
    assert 0.10 < home[2] < 0.18


def test_the_angles_cosines_and_sines_found_algebraically_are_those_of_the_angles(points: np.ndarray) -> None:
    """leg_equations' cos/sin of theta1, theta2 (from u/rho, w/rho, K/rho and the knee-to-joint
    line over the shin length) and theta3, which the symbolic dynamics use instead of the
    angles, equal numpy's cos and sin of the angles over 10,000 workspace points."""
    from falcon_plan.model.kinematics import leg_equations, leg_frames

    e_r, e_t = leg_frames(ACRA2009)
    eq = leg_equations(points @ e_r.T, points @ e_t.T, np.repeat(points[:, 2:3], 3, axis=1), ACRA2009)
    for k in (1, 2, 3):
        theta = eq[f"theta{k}"]
        cos = eq["cos_theta3"] if k == 3 else eq[f"cos_theta{k}"]
        np.testing.assert_allclose(cos, np.cos(theta), atol=1e-12)
        np.testing.assert_allclose(eq[f"sin_theta{k}"], np.sin(theta), atol=1e-12)
