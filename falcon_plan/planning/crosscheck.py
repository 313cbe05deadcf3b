"""Independent references for the planner: toppra on a fixed path, ruckig in leg-angle space.

toppra (time-optimal path parameterisation, same command limit)
---------------------------------------------------------------
- *Same path*: the planner's own geometric path, taken **exactly** (:class:`PiecewiseQuadraticPath`
  with the path parameter s = the planner's time: p(s) is the planner's piecewise quadratic,
  no spline through the nodes), gridded at the planner's nodes (optionally subdivided). The
  planner's own timing is s' = 1, so toppra can only match it or find a faster timing of that
  path: agreement within ~1 % says the optimiser converged.
- *Straight line* (polyline through via points, at rest at the corners): the planner, free to
  bend the path, must be no slower.

The command limit as toppra's second-order constraint. With s' the path speed, x = s'^2 and
u = s'': pivot torques tau = a(s) u + b(s) x + c(s) (a = J^-T M p', b = J^-T (M p'' + h(p, p')),
c = J^-T g, from the model's ``leg_torques``), and |Tc_j| <= tc_max reads

    |tau_j - f_j| <= tc_max N gain (Ks - sign Kd N theta1'_j s')        (f: friction)

The Kd term is linear in s' = sqrt(x), not in x, so toppra's linear form cannot hold it. We
replace sqrt(x) by a *conservative linear bound* and iterate:
- where the Kd term shrinks the limit (beta_j = tc_max N^2 gain sign Kd theta1'_j > 0), by the
  tangent at the previous solution x0: sqrt(x) <= (x0 + x) / (2 sqrt(x0)), exact at x0;
- where it widens the limit (beta_j < 0), by the chord below it on [0, x_hi]:
  sqrt(x) >= x / sqrt(x_hi), with x <= x_hi = 1.05^2 x0 added as a bound (x_hi = x0 where a
  boundary condition fixes x). The first linearisation point is the planner's own timing
  (same path: x0 = 1) or an optimistic probe pass without the speed terms (straight line).
Every pass is therefore feasible for the true constraint (sound), and the passes converge to
within a fraction of a percent (the chord loses <= 5 % of the helping Kd term, itself <= 10 %
of the command). Friction is bounded by |f| <= viscous |theta1'| s' + Coulomb + Stribeck.
The constraint is imposed at both ends of every grid interval (toppra's "interpolation"
idea, with the path's one-sided derivatives at the ends), like the planner; the duration uses
the ConstAccel parametrisation. At an end where the planner is at rest, toppra starts at path
speed 0.995 instead of 1 (the planner's first command sits exactly on the limit, leaving no
round-off room): it costs ~0.05 %. Measured over the 37 benchmark problems: planner / toppra
within -0.3 % .. +0.5 %, median -0.03 %. (Before: sd = 0 at rest ends cost 6 %, since p' = 0
there; a spline through the nodes instead of the exact path cost up to 4 %, per the notes.)

ruckig (leg-angle space, safe limits): the third reference is the planner's fallback,
:func:`falcon_plan.planning.fallback.ruckig_reference` (its own module).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import toppra
import toppra.algorithm as toppra_algo
from toppra.constraint import DiscretizationType, LinearConstraint
from toppra.interpolator import AbstractGeometricPath

from falcon_plan.errors import CrosscheckError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import jacobian
from falcon_plan.model.symbolic import torque_per_command
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)
logging.getLogger("toppra").setLevel(logging.ERROR)

TOPPRA_PASSES = 4
"""Linearisation passes for the Kd term (each one a full toppra solve, ~2-5 ms)."""
REST_END_PATH_SPEED = 0.995
"""Path speed of toppra-same-path at an end where the planner is at rest (see there)."""
CHORD_HEADROOM = 1.05
"""x_hi = (CHORD_HEADROOM^2) x0 for the chord bound where the Kd term helps."""


# --------------------------------------------------------------------------------------------
# paths
class PiecewiseQuadraticPath(AbstractGeometricPath):
    """p(s) = p_k + d_k ds + e_k ds^2 / 2 + f_k ds^3 / 6 on [s_k, s_k+1], ds = s - s_k,
    shape (3,) [m] (quadratic unless a cubic term f is given).

    The planner's path (s = time, d = v_k, e = a_k, f = the jerk of a linear acceleration
    profile) or a polyline (s = arc length, d = unit direction, e = 0).
    :meth:`eval_side` gives one-sided derivatives at the knots.
    """

    def __init__(self, knots: np.ndarray, p: np.ndarray, d: np.ndarray, e: np.ndarray,
                 f: np.ndarray | None = None) -> None:
        self.knots = np.asarray(knots, float)
        self._p, self._d, self._e = (np.asarray(x, float) for x in (p, d, e))
        self._f = np.zeros_like(self._e) if f is None else np.asarray(f, float)

    @property
    def dof(self) -> int:
        return 3

    @property
    def path_interval(self) -> np.ndarray:
        return np.array([self.knots[0], self.knots[-1]])

    def eval_side(self, s: np.ndarray, order: int, side: str = "right") -> np.ndarray:
        """Derivative ``order`` (0-2) at path positions s, shape (len(s), 3); at a knot,
        ``side`` chooses the piece after ("right") or before ("left") it."""
        s = np.atleast_1d(np.asarray(s, float))
        k = np.searchsorted(self.knots, s, side="right" if side == "right" else "left") - 1
        k = np.clip(k, 0, len(self.knots) - 2)
        ds = (s - self.knots[k])[:, None]
        e, f = self._e[k], self._f[k]
        if order == 0:
            return self._p[k] + (self._d[k] + (0.5 * e + f * ds / 6.0) * ds) * ds
        if order == 1:
            return self._d[k] + (e + 0.5 * f * ds) * ds
        if order == 2:
            return e + f * ds
        raise ValueError(f"path derivative order must be 0, 1 or 2, got {order}")

    def __call__(self, path_positions: Any, order: int = 0) -> np.ndarray:
        scalar = np.ndim(path_positions) == 0
        out = self.eval_side(path_positions, order)
        return out[0] if scalar else out

    @classmethod
    def from_trajectory(cls, traj: Trajectory) -> "PiecewiseQuadraticPath":
        """The path of the planner's trajectory ``traj`` exactly (s = its time), for either
        acceleration interpolation."""
        acc = traj.acceleration_m_s2
        jerk = np.diff(acc, axis=0) / np.diff(traj.t_s)[:, None] if traj.interpolation == "linear" else None
        return cls(traj.t_s, traj.position_m[:-1], traj.velocity_m_s[:-1], acc[:-1], jerk)

    @classmethod
    def polyline(cls, points: np.ndarray) -> "PiecewiseQuadraticPath":
        """Straight segments through ``points`` (k, 3) [m], s = arc length [m]."""
        pts = np.asarray(points, float)
        seg = np.diff(pts, axis=0)
        length = np.linalg.norm(seg, axis=1)
        if np.any(length < 1e-9):
            raise CrosscheckError("polyline has a zero-length segment")
        knots = np.concatenate([[0.0], np.cumsum(length)])
        return cls(knots, pts[:-1], seg / length[:, None], np.zeros_like(seg))


# --------------------------------------------------------------------------------------------
# the command constraint for toppra
class CommandConstraint(LinearConstraint):
    """|Tc_j| <= tc_max for the three motors, at both ends of every grid interval, with the
    Kd (and viscous) term linearised conservatively around ``x_ref`` (see module doc).

    Rows per grid point i (stage i, from s_i to s_i+1): for each end (start, end) and motor
    j, +tau_j and -tau_j, written as a_i u + b_i x + c_i <= g (F = identity); the end rows
    use x_i+1 = x_i + 2 delta_i u_i (toppra's interpolation scheme).

    ``model``: the dynamics and effects (friction bound, motor law); ``tc_max``: the command
    limit [command units]; ``x_ref``: the linearisation point, s'^2 per grid point (None: the
    optimistic probe without the speed terms); ``corner_stops``: grid indices where the path
    must be at rest (the polyline's corners); ``pinned``: grid indices whose x is fixed by a
    boundary condition (there the chord bound uses x_hi = x0).
    """

    def __init__(self, model: FalconModel, tc_max: float, x_ref: np.ndarray | None,
                 corner_stops: np.ndarray | None = None, pinned: tuple[int, ...] = ()) -> None:
        super().__init__()
        self.model, self.tc_max = model, float(tc_max)
        self.x_ref = None if x_ref is None else np.asarray(x_ref, float)
        self.corner_stops = corner_stops
        self.pinned = pinned
        """Grid indices where x is fixed by a boundary condition (x = x_ref there): the chord
        is anchored at x_ref itself (exact), not at CHORD_HEADROOM^2 x_ref."""
        self.discretization_type = DiscretizationType.Interpolation
        self.identical = True
        self.dof = 3

    def _end_terms(self, path: PiecewiseQuadraticPath, s: np.ndarray, side: str, x0: np.ndarray | None,
                   headroom: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(a, b, c, beta) of the 6 rows (+tau_j, -tau_j) at path points s, one-sided
        derivatives from ``side``: the speed term beta_j s' enters through its linear bound
        alpha0 + alpha1 x (into c and b); beta (n, 3) [N.m per unit path speed] is returned
        so the caller knows where the chord (beta < 0) needs its x bound."""
        model, prm, eff = self.model, self.model.params, self.model.effects
        p, dp, ddp = (path.eval_side(s, k, side) for k in range(3))
        zero = np.zeros_like(p)
        c = model.leg_torques(p, zero, zero)
        a = model.leg_torques(p, zero, dp) - c
        b = model.leg_torques(p, dp, ddp) - c
        dth = np.einsum("nij,nj->ni", jacobian(p, prm), dp)          # theta1' [rad per s]
        # the speed-dependent part of the motor law at tc_max (its Kd term)
        beta = (self.tc_max * (torque_per_command(dth, eff, prm) - torque_per_command(0.0, eff, prm))
                + eff.viscous_Nms * np.abs(dth))
        # linear bound of s' = sqrt(x): s' ~ alpha0 + alpha1 x (conservative, see module doc);
        # without a reference (the probe pass) the speed terms are left out (optimistic)
        if x0 is None:
            beta = np.zeros_like(beta)
            alpha0 = alpha1 = np.zeros_like(beta)
        else:
            xr = np.maximum(x0, 1e-9)[:, None] * np.ones_like(beta)
            alpha0 = np.where(beta > 0, 0.5 * np.sqrt(xr), 0.0)
            alpha1 = np.where(beta > 0, 0.5 / np.sqrt(xr), 1.0 / (headroom[:, None] * np.sqrt(xr)))
        rows_a = np.hstack([a, -a])
        rows_b = np.hstack([b + beta * alpha1, -b + beta * alpha1])
        rows_c = np.hstack([c + beta * alpha0, -c + beta * alpha0])
        return rows_a, rows_b, rows_c, beta

    def compute_constraint_params(self, path: PiecewiseQuadraticPath, gridpoints: np.ndarray,
                                  *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        prm, eff = self.model.params, self.model.effects
        grid = np.asarray(gridpoints, float)
        deltas = np.diff(grid)
        x0 = self.x_ref
        s_end = np.append(grid[1:], grid[-1])
        x_end = None if x0 is None else np.append(x0[1:], x0[-1])
        headroom = np.full(len(grid), CHORD_HEADROOM)
        headroom[list(self.pinned)] = 1.0
        a0, b0, c0, beta0 = self._end_terms(path, grid, "right", x0, headroom)
        a1, b1, c1, beta1 = self._end_terms(path, s_end, "left", x_end, np.append(headroom[1:], headroom[-1]))
        d = np.append(deltas, 0.0)[:, None]
        a_rows = np.hstack([a0, a1 + 2.0 * d * b1])
        b_rows = np.hstack([b0, b1])
        c_rows = np.hstack([c0, c1])
        # per leg: the torque tc_max gives at rest, less the friction it must overcome
        limit = -self.tc_max * torque_per_command(0.0, eff, prm) - eff.coulomb_Nm - eff.stribeck_Nm
        m = a_rows.shape[1]
        F = np.eye(m)
        g = np.tile(limit, m // 3)
        # chord bounds hold only for x <= x_hi: add it where a helping Kd term was used
        x_hi = np.full(len(grid), np.inf)
        if x0 is not None:
            helped = (beta0 < 0).any(axis=1) | (beta1 < 0).any(axis=1)
            x_hi = np.where(helped, headroom**2 * np.maximum(x0, 1e-9), np.inf)
        xbound = np.stack([np.zeros(len(grid)), np.minimum(x_hi, 1e8)], axis=1)
        if self.corner_stops is not None:
            xbound[self.corner_stops, 1] = 0.0
        return a_rows, b_rows, c_rows, F, g, None, xbound


@dataclass(frozen=True)
class ToppraResult:
    """A toppra reference: ``duration_s`` [s] (None if infeasible), ``solve_time_s`` [s] of
    all passes, the number of conservative ``passes``, the ``gridpoints`` of the path
    parameter and the path speed ``sd`` there (None if infeasible), the ``path``, and a
    ``note`` on what was adapted (e.g. a boundary path speed)."""

    duration_s: float | None
    solve_time_s: float
    passes: int
    gridpoints: np.ndarray = field(repr=False)
    sd: np.ndarray | None = field(repr=False)
    path: PiecewiseQuadraticPath | None = field(repr=False, default=None)
    note: str = ""

    def trajectory(self, model: FalconModel, rate_hz: float = 2000.0) -> Trajectory:
        """The timed path sampled at ``rate_hz`` (positions, velocities and accelerations from
        toppra's ConstAccel parametrisation, exact at the samples; commands by ``model``)."""
        if self.duration_s is None or self.sd is None or self.path is None:
            raise CrosscheckError(f"no toppra trajectory: {self.note}")
        timed = toppra.parametrizer.ParametrizeConstAccel(self.path, self.gridpoints, self.sd)
        t = np.linspace(0.0, timed.duration, max(int(timed.duration * rate_hz), 2) + 1)
        pos, vel, acc = timed(t, 0), timed(t, 1), timed(t, 2)
        return Trajectory(t, pos, vel, acc, model.inverse_dynamics(pos, vel, acc),
                          model.params.name, "toppra")


def _toppra_once(constraint: CommandConstraint, path: PiecewiseQuadraticPath, grid: np.ndarray,
                 sd_start: float, sd_end: float) -> np.ndarray | None:
    instance = toppra_algo.TOPPRA([constraint], path, gridpoints=grid, solver_wrapper="seidel",
                                  parametrizer="ParametrizeConstAccel")
    _, sd, _ = instance.compute_parameterization(sd_start, sd_end)
    if sd is None:
        return None
    sd = np.asarray(sd, float)
    # toppra takes sqrt of x; a round-off negative x gives NaN: a zero speed there
    if np.any(np.isnan(sd[1:-1])):
        return None
    return np.nan_to_num(np.maximum(sd, 0.0), nan=0.0)


def toppra_on_path(model: FalconModel, path: PiecewiseQuadraticPath, grid: np.ndarray, tc_max: float,
                   *, x_ref: np.ndarray | None = None, sd_start: float = 0.0, sd_end: float = 0.0,
                   corner_stops: np.ndarray | None = None, passes: int = TOPPRA_PASSES) -> ToppraResult:
    """Time-optimal timing of ``path`` under |Tc| <= tc_max (the model's inverse dynamics,
    Kd term linearised conservatively and iterated; see the module doc).

    ``x_ref`` is the first linearisation point (s'^2 per grid point); without it an
    optimistic probe pass without the speed terms gives one (the probe is not reported:
    only passes with the conservative bounds are). ``model``: the dynamics; ``grid``: the
    path parameters where the constraint is imposed; ``tc_max``: the command limit [command
    units]; ``sd_start``/``sd_end``: the path speed at the ends; ``corner_stops``: grid
    indices where the path must stop; ``passes``: linearisation passes.
    """
    t0 = time.perf_counter()
    if x_ref is None:
        probe = _toppra_once(CommandConstraint(model, tc_max, None, corner_stops), path, grid,
                             sd_start, sd_end)
        x_ref = np.full(len(grid), 1.0) if probe is None else np.maximum(probe**2, 1e-6)
    sd = None
    done = 0
    pinned = tuple(i for i, sd_end_value in ((0, sd_start), (len(grid) - 1, sd_end)) if sd_end_value > 0)
    for _ in range(passes):
        x_ref = x_ref.copy()
        x_ref[0], x_ref[-1] = (sd_start**2 if sd_start > 0 else x_ref[0]), (sd_end**2 if sd_end > 0 else x_ref[-1])
        trial = _toppra_once(CommandConstraint(model, tc_max, x_ref, corner_stops, pinned), path, grid,
                             sd_start, sd_end)
        done += 1
        if trial is None:
            break
        sd = trial
        x_new = np.maximum(sd**2, 1e-8)
        if np.max(np.abs(x_new - x_ref) / np.maximum(x_ref, 1e-6)) < 1e-3:
            break
        x_ref = x_new
    elapsed = time.perf_counter() - t0
    if sd is None:
        return ToppraResult(None, elapsed, done, grid, None, path, "toppra found the path uncontrollable")
    duration = float(toppra.parametrizer.ParametrizeConstAccel(path, grid, sd).duration)
    return ToppraResult(duration, elapsed, done, grid, sd, path)


def toppra_same_path(model: FalconModel, traj: Trajectory, tc_max: float, subdivide: int = 2) -> ToppraResult:
    """toppra on the exact path of the planner's trajectory ``traj``, gridded at its nodes
    (each interval split in ``subdivide``), starting the linearisation at the planner's own
    timing (s' = 1), under the command limit ``tc_max`` [command units] with ``model``'s
    dynamics. The path's own derivative carries the end velocities, so the path speed is 1
    at both ends."""
    path = PiecewiseQuadraticPath.from_trajectory(traj)
    knots = traj.t_s
    grid = np.concatenate([np.linspace(knots[k], knots[k + 1], subdivide + 1)[:-1]
                           for k in range(len(knots) - 1)] + [[knots[-1]]])
    # s = the planner's time, so a moving end needs path speed exactly 1 (velocity = p' s').
    # At a rest end p' = 0 and any path speed means rest; there the planner's start
    # acceleration p'' s'^2 sits exactly on the limit, so toppra would need x = 1 with no
    # round-off room: start (end) at REST_END_PATH_SPEED instead (costs ~0.05 %).
    # A moving end whose command sits on the limit can be just out of reach of the
    # conservative Kd bound; then that end also starts at REST_END_PATH_SPEED (0.5 % slower
    # boundary speed; said in the note).
    moving = [bool(np.any(traj.velocity_m_s[i])) for i in (0, -1)]
    ends = [1.0 if mv else REST_END_PATH_SPEED for mv in moving]
    result = toppra_on_path(model, path, grid, tc_max, x_ref=np.ones(len(grid)), sd_start=ends[0], sd_end=ends[1])
    if result.duration_s is None and any(moving):
        result = toppra_on_path(model, path, grid, tc_max, x_ref=np.ones(len(grid)),
                                sd_start=REST_END_PATH_SPEED, sd_end=REST_END_PATH_SPEED)
        result = dataclasses.replace(result, note=f"moving end(s) at {REST_END_PATH_SPEED} of the planner's speed")
    return result


def toppra_straight(model: FalconModel, problem: PlanProblem, tc_max: float,
                    points_per_segment: int = 60) -> ToppraResult:
    """toppra on the straight line of ``problem`` (polyline through its via points, stopping
    at each, ``points_per_segment`` grid points per segment), rest to rest, under the command
    limit ``tc_max`` [command units] with ``model``'s dynamics; not applicable (duration
    None) with moving ends."""
    if not problem.is_rest_to_rest:
        return ToppraResult(None, 0.0, 0, np.zeros(0), None, None,
                            "straight-line reference needs rest at both ends")
    path = PiecewiseQuadraticPath.polyline(problem.waypoints_m)
    knots = path.knots
    grid = np.concatenate([np.linspace(knots[k], knots[k + 1], points_per_segment + 1)[:-1]
                           for k in range(len(knots) - 1)] + [[knots[-1]]])
    corners = np.array([k * points_per_segment for k in range(1, len(knots) - 1)], dtype=int)
    return toppra_on_path(model, path, grid, tc_max, corner_stops=corners if corners.size else None)


__all__ = ["PiecewiseQuadraticPath", "CommandConstraint", "ToppraResult", "toppra_on_path",
           "toppra_same_path", "toppra_straight"]
