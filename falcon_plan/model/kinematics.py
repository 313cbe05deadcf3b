"""Kinematics of the Falcon: inverse and forward kinematics, the Jacobian, encoder maps.

Conventions (MODEL-CONVENTIONS "Legs and kinematics", Stamper's parameterisation): for leg i
with radial unit vector e_r, tangential e_t and e_z = (0, 0, 1), and end-effector point p [m]:

    radial:      a cos(th1) + L cos(th2) = p.e_r - (r - c)
    depth:       a sin(th1) + L sin(th2) = p.z
    tangential:  b cos(th3)              = p.e_t - (s - f)
    L = d + e + b sin(th3)

th1 is the actuated leg angle [rad] from the base plane toward +z; th2 the direction of the
line from knee to end-effector joint; th3 the parallelogram angle, taken in (0, pi).

Inverse kinematics is closed form. With u = p.e_r - (r - c), w = p.z, rho = |(u, w)| and
K = (u^2 + w^2 + a^2 - L^2) / (2a), the leg equations reduce to u cos th1 + w sin th1 = K,
whose two roots are th1 = atan2(w, u) -+ acos(K / rho). We take the minus root: the knee
outward (away from the base axis), the branch libnifalcon takes. It equals the root
t = (w - sqrt(u^2 + w^2 - K^2)) / (K + u) of the half-angle substitution t = tan(th1 / 2);
:func:`theta1_half_angle` computes that form and a test checks they agree.

The Jacobian dth1/dp has rows n_i / (a sin(th2 - th1)) with n_i = cos th2 e_r + sin th2 e_z
+ cot th3 e_t, the bar direction divided by sin th3 (derived by implicit differentiation of
the leg's loop equation; checked against finite differences in the tests).

All numeric functions broadcast over any leading batch shape: points are ``(..., 3)`` and leg
angles ``(..., 3)`` (leg index last). The same equations are written once over an "ops"
namespace so that :mod:`falcon_plan.model.symbolic` can build CasADi expressions from them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import KinematicsError, WorkspaceError
from falcon_plan.model.params import ACRA2009, FalconParams

if TYPE_CHECKING:
    from falcon_plan.compiled import BufferedFunction

NUMPY_OPS = SimpleNamespace(sin=np.sin, cos=np.cos, sqrt=np.sqrt, atan2=np.arctan2, acos=np.arccos,
                            fmin=np.minimum, fmax=np.maximum)
"""Elementwise operations used to write the kinematic equations once for numpy and CasADi."""
MATH_OPS = SimpleNamespace(sin=math.sin, cos=math.cos, sqrt=math.sqrt, atan2=math.atan2, acos=math.acos,
                           fmin=min, fmax=max)
"""The same operations on plain floats (one point, no numpy overhead: control loops); they
raise ValueError outside their domain (an unreachable point)."""

FK_TOLERANCE_M = 1e-10
"""Forward kinematics stops when the Newton step is below this [m]."""


def leg_frames(params: FalconParams = ACRA2009) -> tuple[np.ndarray, np.ndarray]:
    """Radial and tangential unit vectors of the three legs, each shape (3 legs, 3 xyz), in
    the base frame, from the legs' azimuths in ``params`` (the device's parameter set)."""
    phi = np.radians(np.asarray(params.leg_azimuth_deg, dtype=float))
    e_r = np.stack([np.cos(phi), np.sin(phi), np.zeros(3)], axis=-1)
    e_t = np.stack([-np.sin(phi), np.cos(phi), np.zeros(3)], axis=-1)
    return e_r, e_t


@dataclass(frozen=True)
class LegAngles:
    """Angles of the three legs [rad], each array of shape (..., 3) with the leg index last.

    ``theta1``: the actuated leg angle from the base plane toward +z; ``theta2``: the
    direction of the line from knee to end-effector joint; ``theta3``: the parallelogram angle,
    in (0, pi) (module docstring). ``reachable`` is False where the point has no real solution
    for that leg (then the angles there are NaN).
    """

    theta1: np.ndarray
    theta2: np.ndarray
    theta3: np.ndarray
    reachable: np.ndarray


def leg_equations(p_radial: Any, p_tangential: Any, p_z: Any, params: FalconParams,
                  ops: Any = NUMPY_OPS) -> dict[str, Any]:
    """One leg's inverse kinematics from the point's leg-frame coordinates [m]: ``p_radial``
    = p.e_r, ``p_tangential`` = p.e_t and ``p_z`` = p.z, with the geometry of ``params``.

    Returns a dict with ``theta1``, ``theta2``, ``theta3`` [rad], the shin length ``L`` [m],
    the reachability quantities ``cos_theta3`` (needs |.| < 1) and ``cos_knee`` = K/rho
    (needs |.| <= 1), and the cosines and sines of the three angles (``cos_theta1``,
    ``sin_theta1``, ``cos_theta2``, ``sin_theta2``, ``sin_theta3``), found algebraically: theta1 =
    phi - psi with phi = atan2(w, u) and psi = acos(K / rho) gives cos and sin of theta1 from
    u / rho, w / rho, K / rho and sqrt(1 - (K / rho)^2); the knee-to-joint line has the shin's
    length L, so cos and sin of theta2 are its components over L. (The symbolic dynamics use
    only these: the transcendental calls of a forward-dynamics evaluation went from 49 to 19, 9
    square roots, the friction's 3 exp and 3 tanh and the tilt's 2 sin and 2 cos.) Works elementwise for numpy arrays and for
    CasADi expressions (pass ``ops`` with sin, cos, sqrt, atan2, acos).
    """
    a, b = params.a_m, params.b_m
    cos_theta3 = (p_tangential - params.tangential_offset_m) / b
    sin_theta3 = ops.sqrt(1.0 - cos_theta3 * cos_theta3)
    theta3 = ops.acos(cos_theta3)
    shin = params.d_m + params.e_m + b * sin_theta3
    u = p_radial - params.radial_offset_m
    w = p_z
    rho = ops.sqrt(u * u + w * w)
    k = (u * u + w * w + a * a - shin * shin) / (2.0 * a)
    cos_knee = k / rho
    sin_knee = ops.sqrt(1.0 - cos_knee * cos_knee)          # psi in [0, pi]: its sine >= 0
    cos_phi, sin_phi = u / rho, w / rho
    cos_theta1 = cos_phi * cos_knee + sin_phi * sin_knee
    sin_theta1 = sin_phi * cos_knee - cos_phi * sin_knee
    theta1 = ops.atan2(w, u) - ops.acos(cos_knee)
    to_joint_u, to_joint_w = u - a * cos_theta1, w - a * sin_theta1   # knee -> joint, length L
    theta2 = ops.atan2(to_joint_w, to_joint_u)
    return {"theta1": theta1, "theta2": theta2, "theta3": theta3, "L": shin,
            "cos_theta3": cos_theta3, "cos_knee": cos_knee, "sin_theta3": sin_theta3,
            "cos_theta1": cos_theta1, "sin_theta1": sin_theta1,
            "cos_theta2": to_joint_u / shin, "sin_theta2": to_joint_w / shin}


def _leg_coordinates(p: np.ndarray, params: FalconParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    e_r, e_t = leg_frames(params)
    return p @ e_r.T, p @ e_t.T, np.repeat(p[..., 2:3], 3, axis=-1)


def _as_points(p: Any) -> np.ndarray:
    arr = np.asarray(p, dtype=float)
    if arr.shape[-1:] != (3,):
        raise ValueError(f"points must have shape (..., 3) [m], got shape {arr.shape}")
    return arr


def inverse_kinematics(p: Any, params: FalconParams = ACRA2009, *, strict: bool = True) -> LegAngles:
    """Leg angles of end-effector point(s) ``p`` [m, base frame], shape (..., 3), for the
    geometry of ``params`` (the device's parameter set).

    With ``strict`` (the default) an unreachable point raises :class:`WorkspaceError` naming
    the first such point and why; otherwise its angles are NaN and ``reachable`` is False.
    Reachability here is geometric only; see :mod:`falcon_plan.model.workspace` for the
    leg-angle limits and singularity margins.
    """
    pts = _as_points(p)
    p_r, p_t, p_z = _leg_coordinates(pts, params)
    with np.errstate(invalid="ignore"):
        eq = leg_equations(p_r, p_t, p_z, params)
        reachable = (np.abs(eq["cos_theta3"]) < 1.0) & (np.abs(eq["cos_knee"]) <= 1.0)
    reachable = reachable & np.isfinite(eq["theta1"])
    if strict and not np.all(reachable):
        flat_pts = pts.reshape(-1, 3)
        flat = reachable.reshape(-1, 3)
        idx = int(np.argmin(flat.all(axis=-1)))
        legs = [int(i) for i in np.flatnonzero(~flat[idx])]
        ct = eq["cos_theta3"].reshape(-1, 3)[idx]
        reasons = []
        for leg in legs:
            if not abs(ct[leg]) < 1.0:
                reasons.append(f"leg {leg}: tangential offset exceeds the shin-bar length b")
            else:
                reasons.append(f"leg {leg}: point beyond the reach of leg plus shin")
        raise WorkspaceError(
            f"point {flat_pts[idx].tolist()} m is not reachable ({'; '.join(reasons)})", reasons)
    nan = np.where(reachable, 0.0, np.nan)
    return LegAngles(theta1=eq["theta1"] + nan, theta2=eq["theta2"] + nan,
                     theta3=eq["theta3"] + nan, reachable=reachable)


def theta1_half_angle(p: Any, params: FalconParams = ACRA2009) -> np.ndarray:
    """theta1 [rad] of point(s) ``p`` [m], shape (..., 3), by the half-angle substitution (a
    second formulation, for checks), for the geometry of ``params``.

    t = tan(th1/2) solves (K + u) t^2 - 2 w t + (K - u) = 0; the knee-outward root is
    t = (w - sqrt(u^2 + w^2 - K^2)) / (K + u), evaluated in the equal conjugate form
    t = (K - u) / (w + sqrt(u^2 + w^2 - K^2)), which does not cancel near theta1 = 0 (w > 0 in
    front of the base) nor divide by zero at K + u = 0.
    """
    pts = _as_points(p)
    p_r, p_t, p_z = _leg_coordinates(pts, params)
    a, b = params.a_m, params.b_m
    shin = params.d_m + params.e_m + b * np.sqrt(1.0 - ((p_t - params.tangential_offset_m) / b) ** 2)
    u = p_r - params.radial_offset_m
    w = p_z
    k = (u * u + w * w + a * a - shin * shin) / (2.0 * a)
    t = (k - u) / (w + np.sqrt(u * u + w * w - k * k))
    return 2.0 * np.arctan(t)


def _row_vectors(angles: LegAngles, params: FalconParams) -> np.ndarray:
    """n_i = cos th2 e_r + sin th2 e_z + cot th3 e_t, shape (..., 3 legs, 3 xyz)."""
    e_r, e_t = leg_frames(params)
    e_z = np.array([0.0, 0.0, 1.0])
    th2 = angles.theta2[..., None]
    cot3 = (np.cos(angles.theta3) / np.sin(angles.theta3))[..., None]
    return np.cos(th2) * e_r + np.sin(th2) * e_z + cot3 * e_t


def jacobian(p: Any, params: FalconParams = ACRA2009, angles: LegAngles | None = None) -> np.ndarray:
    """J = d theta1 / d p [rad/m] at point(s) ``p`` [m], shape (..., 3 legs, 3 xyz):
    theta1_dot = J @ p_dot. ``params``: the geometry; ``angles``: the points' inverse
    kinematics if already known (else computed).

    Leg torques tau [N.m] and the end-effector force F [N] relate by F = J^T tau.
    """
    if angles is None:
        angles = inverse_kinematics(p, params)
    rows = _row_vectors(angles, params)
    denom = params.a_m * np.sin(angles.theta2 - angles.theta1)
    return rows / denom[..., None]


def inverse_jacobian(p: Any, params: FalconParams = ACRA2009, angles: LegAngles | None = None) -> np.ndarray:
    """J^-1 = d p / d theta1 [m/rad] at point(s) ``p`` [m], shape (..., 3 xyz, 3 legs);
    ``params`` and ``angles`` as for :func:`jacobian`."""
    return np.linalg.inv(jacobian(p, params, angles))


def leg_torques_for_force(p: Any, force_N: Any, params: FalconParams = ACRA2009) -> np.ndarray:
    """Leg-pivot torques [N.m] (theta1 sense) that produce the end-effector force ``force_N``
    [N, base frame] at point(s) ``p`` [m]: tau = J^-T F, for the geometry of ``params``.
    Shapes (..., 3)."""
    jac = jacobian(p, params)
    force = np.broadcast_to(np.asarray(force_N, dtype=float), jac.shape[:-1])
    return np.linalg.solve(np.swapaxes(jac, -1, -2), force[..., None])[..., 0]


# --- forward kinematics --------------------------------------------------------------------

_TABLE_RANGE_RAD = (math.radians(-40.0), math.radians(100.0))
_TABLE_BINS = 28  # 5 deg cells per leg


@dataclass(frozen=True)
class _SeedTable:
    """Look-up table of seed points [m] on a regular grid of the three leg angles."""

    points: np.ndarray  # (bins, bins, bins, 3)
    lo: float
    step: float


_seed_cache: dict[FalconParams, _SeedTable] = {}


def _geometry(params: FalconParams) -> FalconParams:
    """The key of the forward-kinematics caches: the parameters with the encoder's home angle
    zeroed (FK from leg angles does not depend on it; the identification re-reads logs with
    many trial home angles)."""
    return params.replace(theta_home_rad=0.0) if params.theta_home_rad != 0.0 else params


def _seed_table(params: FalconParams) -> _SeedTable:
    """The table mapping leg-angle cells to a point whose angles fall in that cell (built once
    per parameter set by :func:`_build_seed_points`, kept in memory and in the kernel cache
    folder: building it takes ~0.3 s with scipy.spatial's import, loading it ~1 ms). This is
    the "look-up table seed" of the paper's Section 5.2."""
    key = _geometry(params)
    if key not in _seed_cache:
        lo, hi = _TABLE_RANGE_RAD
        points = _cached_array(f"fk_seed_table-{_seed_table_key(key)}.npy", lambda: _build_seed_points(key))
        _seed_cache[key] = _SeedTable(points, lo, (hi - lo) / _TABLE_BINS)
    return _seed_cache[key]


def _seed_table_key(params: FalconParams) -> str:
    """What the table depends on: the geometry ``params``, the table's cells, this module's
    code (inverse kinematics and the acceptance rule) and numpy's version, hashed (20 hex digits)."""
    import hashlib
    from pathlib import Path

    text = "\n".join([repr(params), repr((_TABLE_RANGE_RAD, _TABLE_BINS)), np.__version__,
                      Path(__file__).read_text()])
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def _cached_array(name: str, build: Any) -> np.ndarray:
    """The array in the cache folder's file ``name`` (.npy), or ``build()`` written there
    (atomically; an unreadable or unwritable cache only costs the rebuild)."""
    import os
    import tempfile

    from falcon_plan.compiled.build import cache_dir

    path = cache_dir() / name
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        pass
    array = build()
    try:
        with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".npy", delete=False) as tmp:
            np.save(tmp, array, allow_pickle=False)
        os.replace(tmp.name, path)
    except OSError:
        pass
    return array


def _build_seed_points(params: FalconParams) -> np.ndarray:
    """Seed points (bins, bins, bins, 3) [m], from inverse kinematics of a dense grid of
    points; empty cells take the nearest filled cell's point."""
    lo, hi = _TABLE_RANGE_RAD
    step = (hi - lo) / _TABLE_BINS
    axis_xy = np.linspace(-0.12, 0.12, 61)
    axis_z = np.linspace(0.02, 0.24, 56)
    grid = np.stack(np.meshgrid(axis_xy, axis_xy, axis_z, indexing="ij"), axis=-1).reshape(-1, 3)
    ang = inverse_kinematics(grid, params, strict=False)
    with np.errstate(invalid="ignore"):
        ok = (ang.reachable.all(-1) & (np.sin(ang.theta3) > 0.3).all(-1)
              & (np.sin(ang.theta2 - ang.theta1) > 0.15).all(-1)
              & (ang.theta1 > lo).all(-1) & (ang.theta1 < hi).all(-1))
    cells = np.floor((ang.theta1[ok] - lo) / step).astype(int)
    flat = np.ravel_multi_index(cells.T, (_TABLE_BINS,) * 3)
    table = np.full((_TABLE_BINS ** 3, 3), np.nan)
    table[flat] = grid[ok]
    filled = np.flatnonzero(np.isfinite(table[:, 0]))
    centres = np.stack(np.unravel_index(np.arange(_TABLE_BINS ** 3), (_TABLE_BINS,) * 3), -1)
    empty = np.flatnonzero(~np.isfinite(table[:, 0]))
    from scipy.spatial import cKDTree  # scipy.spatial takes ~0.2 s to import: only to build the table

    _, nearest = cKDTree(centres[filled]).query(centres[empty])
    table[empty] = table[filled[nearest]]
    return table.reshape(_TABLE_BINS, _TABLE_BINS, _TABLE_BINS, 3)


def _seed_points(theta1: np.ndarray, params: FalconParams) -> np.ndarray:
    table = _seed_table(params)
    cells = np.clip(np.floor((theta1 - table.lo) / table.step).astype(int), 0, _TABLE_BINS - 1)
    return table.points[cells[:, 0], cells[:, 1], cells[:, 2]].copy()


@dataclass(frozen=True)
class _LegGeometry:
    """The constants of the loop closures as plain floats, looked up once per solve: per leg
    (e_r.x, e_r.y, e_t.x, e_t.y), and a, b, d + e, r - c, s - f [m]."""

    frames: tuple[tuple[float, float, float, float], ...]
    a_m: float
    b_m: float
    shin_base_m: float
    radial_offset_m: float
    tangential_offset_m: float


_leg_geometry_cache: dict[FalconParams, _LegGeometry] = {}


def _leg_geometry(params: FalconParams) -> _LegGeometry:
    if params not in _leg_geometry_cache:
        _leg_geometry_cache[params] = _LegGeometry(
            tuple(scalar_leg_frames(params)), params.a_m, params.b_m, params.d_m + params.e_m,
            params.radial_offset_m, params.tangential_offset_m)
    return _leg_geometry_cache[params]


FK_MAX_STEP_M = 0.02
"""Longest Newton step of forward kinematics [m] (a longer one is scaled down to this)."""


def _knees(theta1: Any, geo: _LegGeometry, ops: Any) -> list[tuple[Any, Any]]:
    """Per leg, the knee's position in the leg plane (radial from the leg pivot, z) [m] at the
    leg angles ``theta1`` (th_0, th_1, th_2) [rad]: fixed while Newton moves the point, so
    computed once per solve (``ops``: sin and cos of floats, numpy or CasADi)."""
    return [(geo.radial_offset_m + geo.a_m * ops.cos(th), geo.a_m * ops.sin(th)) for th in theta1]


def _closures(p: Any, knees: list[tuple[Any, Any]], geo: _LegGeometry, ops: Any) -> tuple[list[Any], list[Any]]:
    """The three loop closures at fixed leg angles, elementwise over plain floats, numpy
    arrays (one entry per point) or CasADi expressions alike.

    ``p``: the point as (x, y, z) [m, base frame]; ``knees``: the knee positions of the leg
    angles (:func:`_knees`); ``geo``: the parameter set's constants; ``ops``: the elementwise
    operations (:data:`NUMPY_OPS`, :data:`MATH_OPS` or CasADi's). Returns per leg
    the residual r_i = |knee -> effector joint in the leg plane| - L [m] and the gradient row
    n_i = dr_i/dp as an (x, y, z) tuple [1]."""
    px, py, pz = p
    b = geo.b_m
    residuals, rows = [], []
    for (erx, ery, etx, ety), (knee_r, knee_z) in zip(geo.frames, knees):
        cos3 = ops.fmin(ops.fmax((etx * px + ety * py - geo.tangential_offset_m) / b, -0.999999), 0.999999)
        sin3 = ops.sqrt(1.0 - cos3 * cos3)
        du = erx * px + ery * py - knee_r
        dw = pz - knee_z
        dist = ops.sqrt(du * du + dw * dw)
        residuals.append(dist - geo.shin_base_m - b * sin3)
        gr, gz, gt = du / dist, dw / dist, cos3 / sin3
        rows.append((gr * erx + gt * etx, gr * ery + gt * ety, gz))
    return residuals, rows


def _newton_step(residuals: list[Any], rows: list[Any]) -> tuple[Any, Any, Any]:
    """The Newton step s [m] with rows @ s = -residuals (:func:`_closures`), by Cramer's rule
    written out per component, so that it runs on floats, numpy arrays and CasADi alike: with
    the cofactor vectors k0 = n1 x n2, k1 = n2 x n0, k2 = n0 x n1 and det = n0 . k0,
    s = -(r0 k0 + r1 k1 + r2 k2) / det."""
    (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = rows
    k0 = (b1 * c2 - b2 * c1, b2 * c0 - b0 * c2, b0 * c1 - b1 * c0)
    k1 = (c1 * a2 - c2 * a1, c2 * a0 - c0 * a2, c0 * a1 - c1 * a0)
    k2 = (a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)
    det = a0 * k0[0] + a1 * k0[1] + a2 * k0[2]
    r0, r1, r2 = residuals
    return (-(r0 * k0[0] + r1 * k1[0] + r2 * k2[0]) / det, -(r0 * k0[1] + r1 * k1[1] + r2 * k2[1]) / det,
            -(r0 * k0[2] + r1 * k1[2] + r2 * k2[2]) / det)


FK_COMPILED_MIN_POINTS = 64
"""Batches at least this large use the compiled Newton iteration first."""
FK_CHUNK = 2048
"""Points per call of the compiled batch forward kinematics."""
FK_COMPILED_ITERATIONS = 5
"""Newton steps of the compiled batch forward kinematics (from a 5-degree table seed the error
falls below 1e-12 m in 4; points still off by more than the tolerance go to the numpy path)."""
_fk_compiled_cache: dict[FalconParams, BufferedFunction | None] = {}


def _fk_compiled(params: FalconParams) -> BufferedFunction | None:
    """Compiled (C, cached) Newton iteration of FK_CHUNK points: (theta1 (3, C), seed (3, C))
    -> (p (3, C), max |loop residual| (1, C)); None without a compiler."""
    key = _geometry(params)
    if key in _fk_compiled_cache:
        return _fk_compiled_cache[key]
    import casadi as ca

    from falcon_plan.compiled import BufferedFunction, build_library

    th, p0 = ca.SX.sym("theta1", 3), ca.SX.sym("seed", 3)
    p, residual = fk_newton_sx(th, p0, params, FK_COMPILED_ITERATIONS)
    one = ca.Function("fk_newton", [th, p0], [p, residual], {"cse": True})
    mapped = one.map("fk_newton_map", "serial", FK_CHUNK, [], [])
    ins = mapped.mx_in()
    fn = ca.Function(f"falcon_fk_{params.name}_{FK_CHUNK}", ins, mapped.call(ins))
    library = build_library(fn)
    result = BufferedFunction(fn, library) if library is not None else None
    _fk_compiled_cache[key] = result
    return result


def fk_newton_sx(theta1: Any, seed_m: Any, params: FalconParams, iterations: int) -> tuple[Any, Any]:
    """Forward kinematics as CasADi SX: ``iterations`` Newton steps (each capped at
    FK_MAX_STEP_M) on the loop closures from ``seed_m`` (3x1 SX) [m] at leg angles ``theta1``
    (3x1 SX) [rad], with the geometry of ``params``. Returns (p (3x1) [m], max |loop
    residual| (1x1) [m] at p) for compiled loops that check convergence themselves."""
    import casadi as ca

    ops = SimpleNamespace(sin=ca.sin, cos=ca.cos, sqrt=ca.sqrt, fmin=ca.fmin, fmax=ca.fmax)
    geo = _leg_geometry(params)
    p = [seed_m[i] for i in range(3)]
    knees = _knees([theta1[i] for i in range(3)], geo, ops)
    for _ in range(iterations):
        step = _newton_step(*_closures(p, knees, geo, ops))
        scale = ca.fmin(1.0, FK_MAX_STEP_M / ca.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2))
        p = [p[j] + scale * step[j] for j in range(3)]
    residual = ca.mmax(ca.fabs(ca.vertcat(*_closures(p, knees, geo, ops)[0])))
    return ca.vertcat(*p), residual


def _forward_kinematics_compiled(th: np.ndarray, seeds: np.ndarray, params: FalconParams,
                                 tol_m: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Batch FK through the compiled Newton iteration: (points (n, 3), converged (n,)), or
    None when there is no compiler."""
    fn = _fk_compiled(params)
    if fn is None:
        return None
    points, resid = fn.map_columns([th.T, seeds.T])
    out = points.T
    return out, np.isfinite(out).all(axis=1) & (resid[0] < tol_m * 1e-2)


def forward_kinematics(theta1: Any, params: FalconParams = ACRA2009, *, seed_m: Any = None,
                       tol_m: float = FK_TOLERANCE_M, max_iter: int = 40) -> np.ndarray:
    """End-effector point [m], shape (..., 3), from leg angles theta1 [rad], shape (..., 3).

    Newton's method on the three loop closures (:func:`_closures`, :func:`_newton_step`),
    seeded from a look-up table over the leg angles (5 deg cells, built once from inverse
    kinematics) unless ``seed_m`` [m] is given. ``params``: the device's geometry. Batches of
    at least FK_COMPILED_MIN_POINTS points first run a fixed number of plain Newton steps
    compiled to C (:func:`_fk_compiled`); the points that did not converge there (and small
    batches) take the guarded numpy iteration, with steps capped at FK_MAX_STEP_M (20 mm) and
    halved while they do not reduce the residual. It stops when every step is below
    ``tol_m`` (default 1e-10 m; the iteration converges quadratically, so the final error is
    far below that), or after ``max_iter`` numpy steps. Raises :class:`KinematicsError`
    naming the angles that did not converge.
    """
    th = np.asarray(theta1, dtype=float)
    if th.shape[-1:] != (3,):
        raise ValueError(f"theta1 must have shape (..., 3) [rad], got shape {th.shape}")
    batch = th.shape[:-1]
    th_flat = th.reshape(-1, 3)
    if seed_m is None:
        p = _seed_points(th_flat, params)
    else:
        p = np.broadcast_to(np.asarray(seed_m, dtype=float), th_flat.shape).copy()
    converged = np.zeros(th_flat.shape[0], dtype=bool)
    if th_flat.shape[0] >= FK_COMPILED_MIN_POINTS and np.isfinite(th_flat).all():
        compiled = _forward_kinematics_compiled(th_flat, p, params, tol_m)
        if compiled is not None:
            # converged points are final; the rest restart from their seeds on the numpy path
            p[compiled[1]] = compiled[0][compiled[1]]
            converged = compiled[1].copy()
    active = np.flatnonzero(~converged)
    geo = _leg_geometry(params)
    for _ in range(max_iter):
        if active.size == 0:
            break
        p_active, th_active = p[active].T, th_flat[active].T
        knees = _knees(th_active, geo, NUMPY_OPS)
        residuals, rows = _closures(p_active, knees, geo, NUMPY_OPS)
        step = np.stack(_newton_step(residuals, rows))
        norm = np.sqrt((step * step).sum(axis=0))
        scale = np.minimum(1.0, FK_MAX_STEP_M / np.maximum(norm, 1e-300))
        # Backtracking: halve the step where it does not reduce the residual.
        r0 = np.abs(residuals).max(axis=0)
        for _halving in range(6):
            trial = p_active + step * scale
            r1 = np.abs(_closures(trial, knees, geo, NUMPY_OPS)[0]).max(axis=0)
            worse = (r1 > r0) & (norm * scale > tol_m)
            if not worse.any():
                break
            scale = np.where(worse, 0.5 * scale, scale)
        p[active] += (step * scale).T
        done = norm < tol_m
        converged[active[done]] = True
        active = active[~done & np.isfinite(norm)]
    if not converged.all():
        bad = th_flat[int(np.argmin(converged))]
        raise KinematicsError(
            f"forward kinematics did not converge for theta1 = {bad.tolist()} rad "
            f"({int((~converged).sum())} of {converged.size} points); the angles may be outside "
            "the workspace")
    return p.reshape(*batch, 3)


def forward_kinematics_point(theta1: tuple[float, float, float], params: FalconParams = ACRA2009,
                             seed_m: tuple[float, float, float] | None = None,
                             tol_m: float = FK_TOLERANCE_M, max_iter: int = 40) -> tuple[float, float, float]:
    """Forward kinematics of one pose [rad] -> [m], in plain Python floats (no numpy).

    The fast path for control loops: pass the previous solution as ``seed_m`` [m] (a warm
    start converges in 2-3 Newton steps). Without a seed it uses the batch look-up table. The
    same Newton step as :func:`forward_kinematics` (:func:`_closures`, :func:`_newton_step`,
    here on floats: the numpy batch path costs ~30x more for one point), stopping when the
    step is below ``tol_m`` [m] or after ``max_iter`` steps (then :class:`KinematicsError`);
    ``theta1``: leg angles [rad]; ``params``: the device's parameter set.
    """
    if seed_m is None:
        seed_m = tuple(_seed_points(np.asarray([theta1], dtype=float), params)[0])
    px, py, pz = seed_m
    geo = _leg_geometry(params)
    knees = _knees(theta1, geo, MATH_OPS)
    prev = math.inf
    for _ in range(max_iter):
        sx, sy, sz = _newton_step(*_closures((px, py, pz), knees, geo, MATH_OPS))
        norm = math.sqrt(sx * sx + sy * sy + sz * sz)
        scale = min(1.0, FK_MAX_STEP_M / norm) if norm > 0 else 1.0
        if norm > prev and norm > 1e-6:  # a growing step: halve it (the cheap guard of one point)
            scale *= 0.5
        prev = norm
        px, py, pz = px + scale * sx, py + scale * sy, pz + scale * sz
        if norm < tol_m:
            return (px, py, pz)
    raise KinematicsError(f"forward kinematics did not converge for theta1 = {list(theta1)} rad")


class PositionTracker:
    """End-effector position [m, base frame] of successive encoder readings: forward
    kinematics (:func:`forward_kinematics_point`) warm-started from the previous solution, a
    few Newton steps (~10 µs) per call. For loops that follow a device's position (the
    executor's workspace guard, the service's state, homing and start-position reads).

    Parameters
    ----------
    params : the device's parameter set (encoder scale and geometry).
    """

    def __init__(self, params: FalconParams = ACRA2009) -> None:
        self.params = params
        self._seed: tuple[float, float, float] | None = None

    def position(self, counts: Any) -> np.ndarray:
        """Position [m] (3,) of encoder ``counts`` (3,); :class:`KinematicsError` (and a cold
        start next time) when the counts have no forward-kinematic solution."""
        theta1 = tuple(float(x) for x in counts_to_angles(counts, self.params))
        try:
            p = forward_kinematics_point(theta1, self.params, seed_m=self._seed)
        except KinematicsError:
            self._seed = None
            raise
        self._seed = (float(p[0]), float(p[1]), float(p[2]))
        return np.array(self._seed)


_frames_cache: dict[FalconParams, list[tuple[float, float, float, float]]] = {}


def scalar_leg_frames(params: FalconParams) -> list[tuple[float, float, float, float]]:
    """Per leg (e_r.x, e_r.y, e_t.x, e_t.y) of ``params``' leg azimuths as plain floats, cached
    (for scalar code paths)."""
    if params not in _frames_cache:
        e_r, e_t = leg_frames(params)
        _frames_cache[params] = [(float(r[0]), float(r[1]), float(t[0]), float(t[1])) for r, t in zip(e_r, e_t)]
    return _frames_cache[params]


# --- encoders --------------------------------------------------------------------------------

def angles_to_counts(theta1: Any, params: FalconParams = ACRA2009) -> np.ndarray:
    """Encoder counts (fractional) of leg angles theta1 [rad]: n = (th1 - th_home) * counts_per_rad,
    with the home angle and encoder scale of ``params``."""
    return (np.asarray(theta1, dtype=float) - params.theta_home_rad) * params.counts_per_rad


def counts_to_angles(counts: Any, params: FalconParams = ACRA2009) -> np.ndarray:
    """Leg angles theta1 [rad] of encoder counts: th1 = th_home + 2 pi n / (1280 N), with the
    home angle and encoder scale of ``params``."""
    return params.theta_home_rad + np.asarray(counts, dtype=float) / params.counts_per_rad


def counts_to_position(counts: Any, params: FalconParams = ACRA2009) -> np.ndarray:
    """End-effector point [m] of encoder counts, shape (..., 3), for the device ``params``
    describes (forward kinematics)."""
    return forward_kinematics(counts_to_angles(counts, params), params)


def position_to_counts(p: Any, params: FalconParams = ACRA2009, *, whole: bool = False) -> np.ndarray:
    """Encoder counts of end-effector point(s) ``p`` [m] for the device ``params`` describes;
    ``whole`` rounds to the nearest integer."""
    counts = angles_to_counts(inverse_kinematics(p, params).theta1, params)
    return np.rint(counts).astype(np.int64) if whole else counts


def encoder_resolution_m_per_count(p: Any, params: FalconParams = ACRA2009) -> np.ndarray:
    """Columns of dp/dn [m per count] at point(s) p [m]: shape (..., 3 xyz, 3 legs), for the
    device ``params`` describes."""
    return inverse_jacobian(p, params) / params.counts_per_rad

