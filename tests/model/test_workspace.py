"""Workspace: known inside and outside points, reasons, input checks."""
from __future__ import annotations

import math

import numpy as np
import pytest

from falcon_plan.errors import InvalidParameterError, WorkspaceError
from falcon_plan.model.kinematics import inverse_kinematics
from falcon_plan.model.workspace import (
    DEFAULT_LIMITS, WorkspaceLimits, check_workspace, in_workspace, require_in_workspace,
    sample_workspace)

CENTRE = (0.0, 0.0, 0.12)


def test_known_inside_points() -> None:
    pts = np.array([CENTRE, [0.02, -0.02, 0.11], [-0.03, 0.03, 0.13], [0.0, 0.0, 0.1448]])
    assert in_workspace(pts).all()
    require_in_workspace(pts)  # does not raise


@pytest.mark.parametrize("point,fragment", [
    ((0.0, 0.0, 0.30), "not reachable"),
    ((0.0, 0.0, 0.183), "outside the allowed range"),         # legs past 80 deg
    ((0.0, 0.06, 0.08), "outside the allowed range"),         # top leg below -20 deg
    ((0.0, -0.09, 0.09), "too close to a singular"),
])
def test_known_outside_points_and_reasons(point, fragment) -> None:
    check = check_workspace(np.array(point))
    assert not bool(check.inside)
    assert fragment in check.reason(0)
    with pytest.raises(WorkspaceError, match=fragment) as info:
        require_in_workspace(point, what="goal")
    assert str(info.value).startswith("goal ") and info.value.reasons == [check.reason(0)]


def test_leg_range_reason_reports_the_angles() -> None:
    check = check_workspace(np.array([0.0, 0.0, 0.183]))
    th1 = np.degrees(inverse_kinematics([0.0, 0.0, 0.183]).theta1)
    assert (th1 > 80).all()
    assert str(np.round(th1, 1).tolist()[0]) in check.reason(0)


def test_require_rejects_nan_and_wrong_shape() -> None:
    with pytest.raises(WorkspaceError, match="3 finite coordinates"):
        require_in_workspace([0.0, np.nan, 0.12])
    with pytest.raises(WorkspaceError, match="3 finite coordinates"):
        require_in_workspace([0.0, 0.12])
    with pytest.raises(ValueError):
        require_in_workspace([[0.0, 0.0, np.inf]])


def test_limits_are_enforced_on_sampled_points() -> None:
    pts = sample_workspace(3000, np.random.default_rng(11))
    angles = inverse_kinematics(pts)
    assert (angles.theta1 >= DEFAULT_LIMITS.theta1_min_rad).all()
    assert (angles.theta1 <= DEFAULT_LIMITS.theta1_max_rad).all()
    assert (np.sin(angles.theta2 - angles.theta1) >= math.sin(DEFAULT_LIMITS.knee_min_rad) - 1e-12).all()
    assert (np.sin(angles.theta3) >= math.sin(DEFAULT_LIMITS.theta3_min_rad) - 1e-12).all()
    # the default workspace is a strict subset of the box and of geometric reachability
    assert (np.abs(pts[:, :2]) < 0.09).all() and (pts[:, 2] > 0.04).all()


def test_tighter_limits_give_a_subset() -> None:
    pts = np.random.default_rng(12).uniform((-0.09, -0.09, 0.04), (0.09, 0.09, 0.2), (20000, 3))
    wide = in_workspace(pts)
    narrow = in_workspace(pts, limits=DEFAULT_LIMITS.scaled(math.radians(10)))
    assert narrow.sum() < wide.sum() and not (narrow & ~wide).any()


def test_invalid_limits_rejected() -> None:
    with pytest.raises(InvalidParameterError, match="theta1_min_rad"):
        WorkspaceLimits(theta1_min_rad=1.0, theta1_max_rad=0.5)
    with pytest.raises(InvalidParameterError, match="min_forward_det"):
        WorkspaceLimits(min_forward_det=1.5)
