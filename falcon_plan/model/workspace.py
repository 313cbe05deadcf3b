"""The Falcon's workspace: joint limits, singularity margins and the workspace predicate.

The paper gives no leg-angle range, so the limits below are the project's choice, each with
where it comes from:

- ``theta1`` in [-20 deg, 80 deg]: the paper gives no range; we keep the leg from folding
  far toward the base plate or passing the vertical; PLANNING-NOTES found that ordinary moves (for
  example from (0, 0.03, 0.10) m) need theta1 down to about -14 deg, so 0 deg is too narrow.
  On the z axis the range spans z = 0.078 m (theta1 = -20 deg) to 0.181 m (80 deg), a 10 cm
  stroke.
- knee angle ``theta2 - theta1`` in [20 deg, 160 deg]: at 0 or 180 deg leg and shin are
  aligned, the inverse-kinematic (serial) singularity where dtheta1/dp blows up
  (the Jacobian rows carry 1/sin(theta2 - theta1)).
- parallelogram angle ``theta3`` in [45 deg, 135 deg]: at 0 or 180 deg the bars lie along
  e_t and cot(theta3) in the Jacobian blows up; 45 deg keeps |cot(theta3)| <= 1.
- forward (parallel) singularity: the three unit bar directions must not become coplanar;
  we require |det[u_b0; u_b1; u_b2]| >= 0.2 (a right-handed triad gives 1).

All of these are smooth inequality constraints in the leg angles, so the planner imposes the
same set symbolically (:func:`workspace_constraint_values` is written over an "ops"
namespace for that reason).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from collections.abc import Sequence
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidParameterError, WorkspaceError
from falcon_plan.model.kinematics import NUMPY_OPS, LegAngles, inverse_kinematics, scalar_leg_frames
from falcon_plan.model.params import ACRA2009, FalconParams


@dataclass(frozen=True)
class WorkspaceLimits:
    """Joint limits and singularity margins that define the usable workspace [rad].

    Attributes
    ----------
    theta1_min_rad, theta1_max_rad : range of every leg angle theta1 [rad], min < max.
    knee_min_rad : the knee angle theta2 - theta1 stays in [knee_min, pi - knee_min] [rad];
        knee_min in [0, pi/2).
    theta3_min_rad : the parallelogram angle theta3 stays in [theta3_min, pi - theta3_min]
        [rad]; theta3_min in [0, pi/2).
    min_forward_det : least |det| of the three unit bar directions, in [0, 1).
    """

    theta1_min_rad: float = math.radians(-20.0)
    theta1_max_rad: float = math.radians(80.0)
    knee_min_rad: float = math.radians(20.0)
    """Minimum of theta2 - theta1 (and of pi minus it)."""
    theta3_min_rad: float = math.radians(45.0)
    """Minimum of theta3 (and of pi minus it)."""
    min_forward_det: float = 0.2
    """Minimum |det| of the three unit bar directions (forward-singularity margin)."""

    def __post_init__(self) -> None:
        if not self.theta1_min_rad < self.theta1_max_rad:
            raise InvalidParameterError("theta1_min_rad must be below theta1_max_rad")
        if not 0.0 <= self.knee_min_rad < math.pi / 2:
            raise InvalidParameterError("knee_min_rad must be in [0, pi/2)")
        if not 0.0 <= self.theta3_min_rad < math.pi / 2:
            raise InvalidParameterError("theta3_min_rad must be in [0, pi/2)")
        if not 0.0 <= self.min_forward_det < 1.0:
            raise InvalidParameterError("min_forward_det must be in [0, 1)")

    def scaled(self, margin_rad: float) -> "WorkspaceLimits":
        """Limits tightened by ``margin_rad`` on every angle (for guards with slack, use < 0)."""
        return WorkspaceLimits(self.theta1_min_rad + margin_rad, self.theta1_max_rad - margin_rad,
                               self.knee_min_rad + margin_rad, self.theta3_min_rad + margin_rad,
                               self.min_forward_det)

    def to_dict(self) -> dict[str, float]:
        """Limits in degrees (and the determinant margin), for reports."""
        return {"theta1_min_deg": math.degrees(self.theta1_min_rad),
                "theta1_max_deg": math.degrees(self.theta1_max_rad),
                "knee_min_deg": math.degrees(self.knee_min_rad),
                "theta3_min_deg": math.degrees(self.theta3_min_rad),
                "min_forward_det": self.min_forward_det}


DEFAULT_LIMITS = WorkspaceLimits()

CONSTRAINT_NAMES = ("theta1_low", "theta1_high", "knee", "theta3", "forward_det")
"""Names of the rows of :func:`workspace_constraint_values` (per leg except forward_det)."""


def bar_determinant(theta2: Sequence[Any], theta3: Sequence[Any], params: FalconParams = ACRA2009,
                    ops: Any = NUMPY_OPS) -> Any:
    """det[u_b0; u_b1; u_b2] of the three unit bar directions (signed; 0 at a forward singularity).

    u_b = sin th3 (cos th2 e_r + sin th2 e_z) + cos th3 e_t per leg (e_r, e_t the leg's radial
    and tangential unit vectors, horizontal). ``theta2`` and ``theta3`` [rad] hold one entry
    per leg (floats, numpy arrays of any batch shape or CasADi expressions); ``ops`` supplies
    sin and cos (:data:`~falcon_plan.model.kinematics.NUMPY_OPS`, ``MATH_OPS`` or
    ``CASADI_OPS``); ``params`` gives the legs' directions. The one definition used by the
    batch check, the symbolic margins and the executor's scalar workspace guard.
    """
    rows = []
    for (erx, ery, etx, ety), th2, th3 in zip(scalar_leg_frames(params), theta2, theta3):
        s3, c3, c2 = ops.sin(th3), ops.cos(th3), ops.cos(th2)
        rows.append((s3 * c2 * erx + c3 * etx, s3 * c2 * ery + c3 * ety, s3 * ops.sin(th2)))
    (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = rows
    return a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)


def forward_singularity_measure(angles: LegAngles, params: FalconParams = ACRA2009) -> np.ndarray:
    """|det| of the three unit bar directions (:func:`bar_determinant`), shape (...), for the
    leg ``angles`` of points of batch shape (...) (from inverse kinematics with ``params``)."""
    legs = range(3)
    return np.abs(bar_determinant([np.asarray(angles.theta2)[..., i] for i in legs],
                                  [np.asarray(angles.theta3)[..., i] for i in legs], params))


ANGLE_MARGIN_NAMES = ("leg angle", "knee", "parallelogram")
"""The angle margins of :func:`angle_margins_deg`, in its order."""


def angle_margins_deg(position_m: Any, model: Any) -> tuple[np.ndarray, np.ndarray]:
    """How far each leg of ``model`` (a FalconModel: params and limits) is from each angle
    limit at the points ``position_m`` (n, 3) [m], base frame: (n, 3 margins, 3 legs) [deg]
    in :data:`ANGLE_MARGIN_NAMES` order (leg angle to the nearer end of its range, knee and
    parallelogram angles to theirs), and the forward-singularity measure above its floor
    (n,) [unitless]. Negative = outside; NaN where a point is unreachable. Degrees for people
    (reports and plots); the planner constrains the smooth rows of
    :func:`workspace_constraint_values` instead, in mixed units."""
    limits = model.limits
    angles = inverse_kinematics(np.asarray(position_m, dtype=float), model.params, strict=False)
    th1, knee, th3 = (np.degrees(a) for a in (angles.theta1, angles.theta2 - angles.theta1, angles.theta3))
    lo1, hi1 = np.degrees([limits.theta1_min_rad, limits.theta1_max_rad])
    knee_min, th3_min = np.degrees([limits.knee_min_rad, limits.theta3_min_rad])
    margins = np.stack([np.minimum(th1 - lo1, hi1 - th1), np.minimum(knee - knee_min, 180 - knee_min - knee),
                        np.minimum(th3 - th3_min, 180 - th3_min - th3)], axis=-2)
    return margins, forward_singularity_measure(angles, model.params) - limits.min_forward_det


def workspace_margins_deg(position_m: Any, model: Any) -> dict[str, np.ndarray]:
    """Distance to each workspace limit of ``model`` along a path ``position_m`` (n, 3) [m],
    base frame, the worst leg at each point: leg angle, knee and parallelogram angles [deg],
    and the forward-singularity measure above its floor (unitless). Negative = outside."""
    margins, forward = angle_margins_deg(position_m, model)
    worst = np.nanmin(margins, axis=-1)
    return {**{f"{name} [deg]": worst[..., i] for i, name in enumerate(ANGLE_MARGIN_NAMES)},
            "forward singularity": forward}


def workspace_constraint_values(theta1: Any, theta2: Any, theta3: Any, forward_det: Any,
                                limits: WorkspaceLimits = DEFAULT_LIMITS, ops: Any = NUMPY_OPS) -> list[Any]:
    """Margins that must all be >= 0 inside the workspace, in :data:`CONSTRAINT_NAMES` order.

    ``theta1``, ``theta2``, ``theta3`` are leg angles [rad] (one leg or an array of legs),
    ``forward_det`` the |det| of :func:`bar_determinant` (broadcast against them), ``limits``
    the limits to keep and ``ops`` supplies sin (numpy, math or CasADi, as for
    :func:`bar_determinant`). theta1 margins are in radians. The knee and parallelogram
    margins are sines: sin(knee) >= sin(knee_min) holds exactly for knee in
    [knee_min, pi - knee_min] (modulo 2 pi), and likewise for theta3 in (0, pi), so one smooth
    row covers both ends. The last one is |det| - min_forward_det. Works for numpy arrays and
    CasADi expressions.
    """
    return [
        theta1 - limits.theta1_min_rad,
        limits.theta1_max_rad - theta1,
        ops.sin(theta2 - theta1) - math.sin(limits.knee_min_rad),
        ops.sin(theta3) - math.sin(limits.theta3_min_rad),
        forward_det - limits.min_forward_det,
    ]


@dataclass(frozen=True)
class WorkspaceCheck:
    """Result of :func:`check_workspace` for points of batch shape (...).

    Attributes
    ----------
    reachable, within_leg_range, away_from_singularities : boolean masks, shape (...) (each
        described at its field).
    angles : the points' leg angles from inverse kinematics (NaN where unreachable).
    limits : the limits checked against.
    """

    reachable: np.ndarray
    """Every leg has a real inverse-kinematic solution."""
    within_leg_range: np.ndarray
    """theta1 of every leg inside [theta1_min, theta1_max]."""
    away_from_singularities: np.ndarray
    """Knee, parallelogram and forward-singularity margins all respected."""
    angles: LegAngles
    limits: "WorkspaceLimits" = DEFAULT_LIMITS
    """The limits checked against (named in :meth:`reason`)."""

    @property
    def inside(self) -> np.ndarray:
        """True where the point is usable: reachable, in range and away from singularities."""
        return self.reachable & self.within_leg_range & self.away_from_singularities

    def reason(self, index: int = 0) -> str:
        """Plain-language reason why the flat ``index``-th point is outside ('' if inside)."""
        flat = lambda a: np.asarray(a).reshape(-1)  # noqa: E731
        if not flat(self.reachable)[index]:
            return "not reachable by the legs (beyond the reach of leg plus shin)"
        if not flat(self.within_leg_range)[index]:
            th1 = np.degrees(self.angles.theta1.reshape(-1, 3)[index])
            lo, hi = np.degrees([self.limits.theta1_min_rad, self.limits.theta1_max_rad])
            return (f"a leg angle theta1 {np.round(th1, 1).tolist()} deg is outside the allowed range "
                    f"[{lo:g}, {hi:g}] deg")
        if not flat(self.away_from_singularities)[index]:
            lim = self.limits
            return (f"too close to a singular configuration (allowed: knee angle within "
                    f"[{math.degrees(lim.knee_min_rad):g}, {180 - math.degrees(lim.knee_min_rad):g}] deg, "
                    f"parallelogram angle within [{math.degrees(lim.theta3_min_rad):g}, "
                    f"{180 - math.degrees(lim.theta3_min_rad):g}] deg, forward-singularity measure "
                    f">= {lim.min_forward_det:g})")
        return ""


def check_workspace(p: Any, params: FalconParams = ACRA2009,
                    limits: WorkspaceLimits = DEFAULT_LIMITS) -> WorkspaceCheck:
    """Classify end-effector point(s) ``p`` [m, base frame], shape (..., 3), against the
    workspace of the parameter set ``params`` within ``limits``."""
    angles = inverse_kinematics(p, params, strict=False)
    reachable = angles.reachable.all(axis=-1)
    with np.errstate(invalid="ignore"):
        th1, th2, th3 = angles.theta1, angles.theta2, angles.theta3
        in_range = ((th1 >= limits.theta1_min_rad) & (th1 <= limits.theta1_max_rad)).all(axis=-1)
        det = forward_singularity_measure(angles, params)
        margins = workspace_constraint_values(th1, th2, th3, det[..., None], limits)
        away = np.ones(reachable.shape, dtype=bool)
        for m in margins[2:]:
            away &= (np.asarray(m) >= 0.0).all(axis=-1)
    return WorkspaceCheck(reachable, in_range & reachable, away & reachable, angles, limits)


def in_workspace(p: Any, params: FalconParams = ACRA2009, limits: WorkspaceLimits = DEFAULT_LIMITS) -> np.ndarray:
    """Boolean mask, shape (...): point(s) ``p`` [m, base frame], shape (..., 3), inside the
    usable workspace of ``params`` within ``limits``."""
    return check_workspace(p, params, limits).inside


def require_in_workspace(p: Any, params: FalconParams = ACRA2009,
                         limits: WorkspaceLimits = DEFAULT_LIMITS, what: str = "point") -> None:
    """Raise :class:`WorkspaceError` naming the first of the point(s) ``p`` [m, base frame],
    shape (..., 3), outside the workspace of ``params`` within ``limits``, and why (also
    when they are not finite 3-vectors); ``what`` names the points in the message (e.g.
    "goal", "trajectory point")."""
    pts = np.asarray(p, dtype=float)
    if pts.shape[-1:] != (3,) or not np.all(np.isfinite(pts)):
        raise WorkspaceError(f"{what} must be 3 finite coordinates in metres, got {pts.tolist()}")
    check = check_workspace(pts, params, limits)
    inside = check.inside.reshape(-1)
    if not inside.all():
        idx = int(np.argmin(inside))
        reason = check.reason(idx)
        point = pts.reshape(-1, 3)[idx]
        raise WorkspaceError(f"{what} {point.tolist()} m is outside the workspace: {reason}; "
                             f"{extent_hint(point, params, limits)}", [reason])


MM_HINT_LIMIT_M = 1.0
"""A coordinate beyond this [m] is far outside the device: probably given in millimetres."""


@functools.lru_cache(maxsize=8)
def workspace_extent_m(params: FalconParams = ACRA2009,
                       limits: WorkspaceLimits = DEFAULT_LIMITS) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (low, high) [m] of the usable workspace of ``params`` within ``limits``,
    from 20 000 sampled points (a slight underestimate, within about a millimetre)."""
    pts = sample_workspace(20_000, np.random.default_rng(0), params, limits)
    return pts.min(axis=0), pts.max(axis=0)


def extent_hint(point: Any, params: FalconParams = ACRA2009, limits: WorkspaceLimits = DEFAULT_LIMITS) -> str:
    """What is allowed, for an error about ``point`` [m]: the bounding box in mm of the
    workspace of ``params`` within ``limits``, and a units hint when the point looks like
    millimetres."""
    lo, hi = workspace_extent_m(params, limits)
    box = ", ".join(f"{a} {1e3 * lo[i]:.0f}..{1e3 * hi[i]:.0f}" for i, a in enumerate("xyz"))
    centre = np.round((lo + hi) / 2, 3) + 0.0  # no "-0"
    text = f"the workspace spans {box} mm (centre about {','.join(f'{c:g}' for c in centre)} m)"
    point = np.asarray(point, dtype=float)
    if np.abs(point).max() > MM_HINT_LIMIT_M:
        text += f"; points are in metres: did you mean {','.join(f'{round(v / 1000, 4) + 0.0:g}' for v in point)}?"
    return text


def sample_workspace(n: int, rng: np.random.Generator, params: FalconParams = ACRA2009,
                     limits: WorkspaceLimits = DEFAULT_LIMITS,
                     box_m: tuple[tuple[float, float, float], tuple[float, float, float]] = (
                         (-0.09, -0.09, 0.04), (0.09, 0.09, 0.20))) -> np.ndarray:
    """``n`` points drawn uniformly with ``rng`` from the usable workspace of ``params`` within
    ``limits``, shape (n, 3) [m]: rejection sampling in the box ``box_m`` = (low corner, high
    corner) [m], which must enclose that workspace."""
    lo, hi = np.asarray(box_m[0]), np.asarray(box_m[1])
    out: list[np.ndarray] = []
    count = 0
    while count < n:
        cand = rng.uniform(lo, hi, size=(max(2 * (n - count), 1024), 3))
        keep = cand[in_workspace(cand, params, limits)]
        out.append(keep)
        count += len(keep)
    return np.concatenate(out)[:n]
