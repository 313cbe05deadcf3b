"""The paper's Section 5 as a computation: workspace volume, resolution and force mapping.

Martin & Hillier (ACRA 2009) characterise the Falcon's kinematics by

- the workspace volume, from random points tested for reachability (Section 5.3: they give
  7.90e-5 m^3; Novint advertises a 4-inch cube, 1.05e-3 m^3);
- the 1 mm resolution map (Section 5.4, Figure 5): for random points, 6 neighbours 1 mm
  away along +-x, +-y, +-z, the change in encoder values, averaged ("30 counts per mm");
- the root-mean-square pivot torque needed for a 3 N force along z, x and y (Section 5.5,
  Figures 6-8), tau = J^-T F;
- the pose at encoder zero (Section 5: legs about 50 deg from the z axis).

:func:`characterise` reproduces each with this project's model. Everything is SI and in the
base frame (x right, y up, z toward the user). The maps (arrays per sampled point) stay in the
result for plotting and checks; :meth:`Characterisation.to_dict` is the JSON summary.

Two readings had to be fixed (and are reported in the summary):

- *Workspace volume.* The paper does not say which leg-angle range it allowed. The summary
  gives the volume under the project's limits, under pure geometric reachability, and a table
  of volume against a leg-angle range centred on the home angle, so one can see which range
  reproduces the paper's figure and which the maker's.
- *Resolution statistic.* "The corresponding change in encoder values" of one neighbour is a
  3-vector of counts. We take its Euclidean norm (the length of the move in encoder space)
  as the paper's quantity; the mean per leg, the sum over legs and the largest leg are
  reported beside it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from scipy.stats import beta

from falcon_plan.errors import InvalidParameterError
from falcon_plan.model.kinematics import (
    angles_to_counts, counts_to_position, inverse_kinematics, leg_torques_for_force)
from falcon_plan.model.effects import NOMINAL
from falcon_plan.model.params import ACRA2009, FalconParams
from falcon_plan.model.symbolic import torque_per_command
from falcon_plan.model.workspace import (
    DEFAULT_LIMITS, WorkspaceLimits, check_workspace, in_workspace, sample_workspace)

PAPER_VOLUME_M3 = 7.90e-5
"""Section 5.3's workspace volume."""
MAKER_VOLUME_M3 = (4 * 0.0254) ** 3
"""Novint's advertised 4 x 4 x 4 inch workspace [m^3] (1.049e-3)."""
PAPER_COUNTS_PER_MM = 30.0
"""Section 5.4: the average over the workspace, encoder counts per 1 mm move."""
RESOLUTION_TOLERANCE = 0.15
"""Relative agreement with the paper's 30 counts/mm that we call a reproduction."""
FORCE_N = 3.0
"""Section 5.5's force magnitude [N]."""
DEFAULT_BOX_M = ((-0.09, -0.09, 0.04), (0.09, 0.09, 0.20))
"""Sampling box of the default workspace [m] (the one :func:`sample_workspace` uses)."""
TABLE_BOX_M = ((-0.13, -0.13, 0.0), (0.13, 0.13, 0.22))
"""Sampling box for the leg-range table [m]: encloses the workspace of every listed range."""
TABLE_HALF_RANGES_DEG = (10.0, 15.0, 20.0, 25.0, 30.0, 40.0, 50.0)
"""Half-widths of the leg-angle ranges in the table, centred on the home angle (40 deg in
acra2009)."""

Progress = Callable[[str], None]


@dataclass(frozen=True)
class VolumeEstimate:
    """A Monte Carlo volume [m^3] with its 95 % Clopper-Pearson (exact binomial) interval.

    Attributes
    ----------
    label : what region was estimated (e.g. "default limits").
    volume_m3 : box volume x hits / samples [m^3]; ci95_m3 : its 95 % interval (low, high)
        [m^3].
    hits, samples : points inside the region, and points drawn uniformly in the box.
    box_m : the sampling box (low corner, high corner) [m, base frame].
    box_encloses : whether the box holds the whole region (no hit within 1 mm of a face).
    """

    label: str
    volume_m3: float
    ci95_m3: tuple[float, float]
    hits: int
    samples: int
    box_m: tuple[tuple[float, float, float], tuple[float, float, float]]
    box_encloses: bool
    """True when no hit lies within 1 mm of a box face (else the box may cut the region)."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {"label": self.label, "volume_m3": self.volume_m3, "ci95_m3": list(self.ci95_m3),
                "hits": self.hits, "samples": self.samples,
                "box_m": [list(self.box_m[0]), list(self.box_m[1])], "box_encloses": self.box_encloses}


def binomial_ci95(hits: int, samples: int) -> tuple[float, float]:
    """Exact (Clopper-Pearson) 95 % interval (low, high) of the binomial proportion
    ``hits`` / ``samples``; needs 0 <= hits <= samples and samples > 0."""
    if samples <= 0 or not 0 <= hits <= samples:
        raise InvalidParameterError(f"need 0 <= hits <= samples and samples > 0, got {hits}/{samples}")
    lo = 0.0 if hits == 0 else float(beta.ppf(0.025, hits, samples - hits + 1))
    hi = 1.0 if hits == samples else float(beta.ppf(0.975, hits + 1, samples - hits))
    return lo, hi


def volume_from_hits(label: str, points: np.ndarray, hits: np.ndarray,
                     box_m: tuple[tuple[float, float, float], tuple[float, float, float]]) -> VolumeEstimate:
    """Volume estimate named ``label`` from uniform ``points`` (n, 3) [m] in ``box_m`` and
    ``hits``, their (n,) boolean mask of points inside the region."""
    lo, hi = np.asarray(box_m[0], float), np.asarray(box_m[1], float)
    box_volume = float(np.prod(hi - lo))
    n, k = len(points), int(np.count_nonzero(hits))
    ci = binomial_ci95(k, n)
    inside = points[hits]
    encloses = bool(k == 0 or ((inside - lo).min() > 1e-3 and (hi - inside).min() > 1e-3))
    return VolumeEstimate(label, box_volume * k / n, (box_volume * ci[0], box_volume * ci[1]), k, n,
                          (tuple(map(float, lo)), tuple(map(float, hi))), encloses)


def reach_box_m(params: FalconParams) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """A cube (low corner, high corner) [m] that certainly holds every point the geometry of
    ``params`` can reach: its half-side is the sum of every length in the chain (pivot
    radius, offsets, leg, shin)."""
    reach = (params.r_m + abs(params.c_m) + params.a_m + params.d_m + params.e_m + params.b_m
             + abs(params.tangential_offset_m))
    return ((-reach, -reach, -reach), (reach, reach, reach))


def _uniform(rng: np.random.Generator, box_m, n: int) -> np.ndarray:
    return rng.uniform(np.asarray(box_m[0], float), np.asarray(box_m[1], float), size=(n, 3))


@dataclass(frozen=True)
class Characterisation:
    """Result of :func:`characterise`. Maps are per sampled point: ``map_points_m`` (n, 3) [m],
    ``counts_per_mm`` (n,) (the chosen statistic), ``torques_Nm[axis]`` (n, 3 legs) [N.m] for a
    3 N force along that axis, ``rms_torque_Nm[axis]`` (n,) [N.m].

    Attributes
    ----------
    params_name, limits, seed : the parameter set's name, the workspace limits and the random
        seed used.
    volume_default : the volume under ``limits``; volume_geometric : under geometric
        reachability alone; volume_geometric_front : the same in front of the base (z > 0).
    range_table : volume against leg-angle range, one row per range (``theta1_min_deg``,
        ``theta1_max_deg``, ``volume_m3``, ``ci95_m3``, ``box_encloses``).
    paper_range_half_width_deg : the half-width about home [deg] whose volume matches the
        paper's (None if no range in the table does).
    resolution : the 1 mm resolution summary (JSON-ready, counts per mm).
    torque_summary : pivot torques for a 3 N force along x, y, z (JSON-ready, N.m).
    home : the pose at encoder zero (position [m], theta1 [deg], inside the workspace).
    workspace_points_m : the volume sample's points inside the workspace (k, 3) [m].
    """

    params_name: str
    limits: WorkspaceLimits
    seed: int
    volume_default: VolumeEstimate
    volume_geometric: VolumeEstimate
    volume_geometric_front: VolumeEstimate
    range_table: list[dict[str, Any]]
    paper_range_half_width_deg: float | None
    resolution: dict[str, Any]
    torque_summary: dict[str, Any]
    home: dict[str, Any]
    map_points_m: np.ndarray = field(repr=False)
    counts_per_mm: np.ndarray = field(repr=False)
    torques_Nm: dict[str, np.ndarray] = field(repr=False)
    rms_torque_Nm: dict[str, np.ndarray] = field(repr=False)
    workspace_points_m: np.ndarray = field(repr=False)

    def volume_explanation(self) -> str:
        """Why the paper, the maker and this model give different volumes."""
        ours = self.volume_default.volume_m3
        geo = self.volume_geometric_front.volume_m3
        half = self.paper_range_half_width_deg
        home = self.home["theta1_deg"]
        paper_part = (f"The paper's {PAPER_VOLUME_M3:.2e} m^3 is what a leg-angle range of about "
                      f"{home:.0f} +- {half:.0f} deg gives (table), so the paper's realisability test most "
                      "likely kept the legs within a narrow stroke about home (it does not state "
                      "its limits)" if half is not None else
                      f"No range in the table reproduces the paper's {PAPER_VOLUME_M3:.2e} m^3")
        lim = self.limits.to_dict()
        span = lim["theta1_max_deg"] - lim["theta1_min_deg"]
        return (f"Volume depends almost entirely on the leg-angle range allowed. Under the project's "
                f"limits (theta1 {lim['theta1_min_deg']:.0f}..{lim['theta1_max_deg']:.0f} deg, plus "
                f"knee/parallelogram/forward-singularity margins) we get {ours:.2e} m^3, "
                f"{ours / MAKER_VOLUME_M3:.2f}x the maker's 4-inch cube ({MAKER_VOLUME_M3:.2e} m^3): "
                f"the maker's figure matches the usable travel with the legs free over about "
                f"{span:.0f} deg. Pure geometric reachability in front of the base gives {geo:.2e} "
                f"m^3, an upper bound with no leg-angle limits that includes poses at and beyond "
                f"the singularities. {paper_part}; its "
f"'limit theory' estimate is {PAPER_VOLUME_M3 / ours:.3f}x ours.")

    def to_dict(self) -> dict[str, Any]:
        """The JSON summary (no per-point maps)."""
        return {
            "params": self.params_name,
            "limits": self.limits.to_dict(),
            "seed": self.seed,
            "workspace_volume": {
                "default_limits": self.volume_default.to_dict(),
                "geometric_reachability": self.volume_geometric.to_dict(),
                "geometric_reachability_front_of_base": self.volume_geometric_front.to_dict(),
                "paper_m3": PAPER_VOLUME_M3,
                "maker_4in_cube_m3": MAKER_VOLUME_M3,
                "ratio_default_to_paper": self.volume_default.volume_m3 / PAPER_VOLUME_M3,
                "ratio_default_to_maker": self.volume_default.volume_m3 / MAKER_VOLUME_M3,
                "leg_range_table": self.range_table,
                "paper_range_half_width_deg": self.paper_range_half_width_deg,
                "explanation": self.volume_explanation(),
            },
            "resolution": self.resolution,
            "torque_for_3N": self.torque_summary,
            "encoder_zero_pose": self.home,
        }


def _leg_range_table(params: FalconParams, limits: WorkspaceLimits, samples: int,
                     rng: np.random.Generator) -> tuple[list[dict[str, Any]], float | None, np.ndarray]:
    """Volume against the leg-angle range (other margins as ``limits``); the half-width [deg]
    about home whose volume equals the paper's (log-linear interpolation, or None); and the
    sampled points [m] inside that range (empty if None)."""
    pts = _uniform(rng, TABLE_BOX_M, samples)
    check = check_workspace(pts, params, limits)
    base = check.reachable & check.away_from_singularities
    th1 = check.angles.theta1
    home = math.degrees(params.theta_home_rad)
    ranges = [(home - h, home + h) for h in TABLE_HALF_RANGES_DEG]
    ranges += [(math.degrees(limits.theta1_min_rad), math.degrees(limits.theta1_max_rad)), (0.0, 90.0)]
    rows = []
    with np.errstate(invalid="ignore"):
        for lo_deg, hi_deg in ranges:
            hits = base & ((th1 >= math.radians(lo_deg)) & (th1 <= math.radians(hi_deg))).all(axis=-1)
            est = volume_from_hits(f"theta1 in [{lo_deg:g}, {hi_deg:g}] deg", pts, hits, TABLE_BOX_M)
            rows.append({"theta1_min_deg": lo_deg, "theta1_max_deg": hi_deg,
                         "volume_m3": est.volume_m3, "ci95_m3": list(est.ci95_m3),
                         "box_encloses": est.box_encloses})
    half = np.asarray(TABLE_HALF_RANGES_DEG)
    vols = np.array([r["volume_m3"] for r in rows[:len(half)]])
    if not ((vols > 0).all() and vols[0] <= PAPER_VOLUME_M3 <= vols[-1]):
        return rows, None, np.empty((0, 3))
    match = float(np.interp(math.log(PAPER_VOLUME_M3), np.log(vols), half))
    lo_rad, hi_rad = math.radians(home - match), math.radians(home + match)
    with np.errstate(invalid="ignore"):
        inside = base & ((th1 >= lo_rad) & (th1 <= hi_rad)).all(axis=-1)
    return rows, match, pts[inside]


def _resolution_statistics(params: FalconParams, points: np.ndarray,
                           step_m: float = 1e-3) -> tuple[dict[str, float], np.ndarray, np.ndarray]:
    """Mean counts per mm over ``points`` [m] for each reading of the statistic, the per-point
    map of the chosen one (norm), and the (n, 6, 3) |count changes| of the neighbours."""
    counts0 = angles_to_counts(inverse_kinematics(points, params).theta1, params)
    changes = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            moved = points.copy()
            moved[:, axis] += sign * step_m
            angles = inverse_kinematics(moved, params, strict=False)
            changes.append(np.abs(angles_to_counts(angles.theta1, params) - counts0))
    delta = np.stack(changes, axis=1)  # (n, 6 neighbours, 3 legs); NaN where unreachable
    per_step = 1e-3 / step_m
    stats = {
        "norm": np.linalg.norm(delta, axis=-1),
        "mean_per_leg": delta.mean(axis=-1),
        "sum_over_legs": delta.sum(axis=-1),
        "max_leg": delta.max(axis=-1),
    }
    with np.errstate(invalid="ignore"):
        per_point = {k: np.nanmean(v, axis=1) * per_step for k, v in stats.items()}
    means = {k: float(np.nanmean(v)) for k, v in per_point.items()}
    return means, per_point["norm"], delta


def _resolution(params: FalconParams, points: np.ndarray, paper_range_points: np.ndarray,
                paper_half_width_deg: float | None) -> tuple[dict[str, Any], np.ndarray]:
    """The 1 mm resolution summary and the per-point map (chosen statistic, counts/mm)."""
    means, norm_map, delta = _resolution_statistics(params, points)
    chosen = means["norm"]
    rel = chosen / PAPER_COUNTS_PER_MM - 1.0
    within = abs(rel) <= RESOLUTION_TOLERANCE
    summary = {
        "statistic": "norm",
        "mean_counts_per_mm": chosen,
        "paper_counts_per_mm": PAPER_COUNTS_PER_MM,
        "relative_difference": rel,
        "within_15_percent": within,
        "alternatives_counts_per_mm": means,
        "min_counts_per_mm": float(np.nanmin(norm_map)),
        "max_counts_per_mm": float(np.nanmax(norm_map)),
        "points": int(len(points)),
        "neighbours_unreachable": int(np.isnan(delta).any(axis=-1).sum()),
        "explanation": (
            "For each random point the 6 neighbours 1 mm away along +-x, +-y, +-z are mapped to "
            "encoder counts by inverse kinematics; a neighbour's 'change in encoder values' is "
            "taken as the Euclidean norm of its 3-leg count change (the size of the move in "
            "encoder space), averaged over the 6 neighbours and over the points. The other "
            "readings bracket it: mean per leg "
            f"{means['mean_per_leg']:.1f}, largest leg {means['max_leg']:.1f}, sum over legs "
            f"{means['sum_over_legs']:.1f} counts/mm. The norm gives {chosen:.1f} counts/mm, "
            f"{100 * rel:+.1f} % from the paper's 30"
            + (" (within 15 %)." if within else
               "; outside 15 %: the average depends on the region sampled (the leg-angle range; "
               "see in_paper_volume_range).")),
        "distribution": (
            f"Counts per mm are lowest, {float(np.nanmin(norm_map)):.1f}, near the home pose "
            "(all legs mid-stroke at 40 deg) and grow toward the workspace boundary, up to "
            f"{float(np.nanmax(norm_map)):.1f}, where the knee and parallelogram singularities make "
            "dtheta1/dp large. The paper describes the centre as having the higher resolution; "
            "under this model it has the coarsest (fewest counts per mm)."),
    }
    if paper_half_width_deg is not None and len(paper_range_points) >= 10:
        narrow, _, _ = _resolution_statistics(params, paper_range_points)
        summary["in_paper_volume_range"] = {
            "theta1_half_width_deg": paper_half_width_deg, "points": int(len(paper_range_points)),
            "alternatives_counts_per_mm": narrow,
            "note": "the same statistics over the leg-angle range whose volume equals the paper's"}
    return summary, norm_map


def _torques(params: FalconParams, points: np.ndarray) -> tuple[dict[str, Any], dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Pivot torques tau = J^-T F [N.m] for F = 3 N along each axis, and their RMS over legs."""
    per_command = abs(float(torque_per_command(0.0, NOMINAL, params)[0]))  # |d tau / d Tc| at rest [N.m]
    torques, rms, summary = {}, {}, {}
    for axis, name in enumerate("xyz"):
        force = np.zeros(3)
        force[axis] = FORCE_N
        tau = leg_torques_for_force(points, force, params)
        torques[name] = tau
        rms[name] = np.sqrt(np.mean(tau ** 2, axis=-1))
        summary[name] = {"rms_torque_mean_Nm": float(rms[name].mean()),
                         "rms_torque_min_Nm": float(rms[name].min()),
                         "rms_torque_max_Nm": float(rms[name].max()),
                         "max_leg_torque_Nm": float(np.abs(tau).max()),
                         "max_leg_command": float(np.abs(tau).max() / per_command)}
    summary["force_N"] = FORCE_N
    summary["definition"] = ("tau = J^-T F at the leg pivots (theta1 sense), J = dtheta1/dp; "
                             "RMS over the three legs per point, then mean/min/max over points. "
                             "Commands at rest: |Tc| = |tau| / (N Ks).")
    return summary, torques, rms


def _home_pose(params: FalconParams, limits: WorkspaceLimits) -> dict[str, Any]:
    pose = counts_to_position(np.zeros(3), params)
    return {"position_m": pose.tolist(),
            "theta1_deg": math.degrees(params.theta_home_rad),
            "angle_line_a_to_z_axis_deg": 90.0 - math.degrees(params.theta_home_rad),
            "inside_workspace": bool(in_workspace(pose, params, limits))}


def characterise(params: FalconParams = ACRA2009, limits: WorkspaceLimits = DEFAULT_LIMITS, *,
                 samples: int = 1_000_000, map_points: int = 20_000, seed: int = 0,
                 progress: Progress | None = None) -> Characterisation:
    """Run the Section 5 characterisation of the parameter set ``params`` within the workspace
    ``limits``.

    ``samples`` uniform points per Monte Carlo volume estimate; ``map_points`` workspace
    points for the resolution and torque maps; ``seed`` seeds everything. ``progress`` is
    called with a short message before each step (the library itself never prints).
    """
    if samples < 100 or map_points < 10:
        raise InvalidParameterError(f"need samples >= 100 and map_points >= 10, got {samples} and {map_points}")
    say = progress or (lambda _msg: None)
    rng = np.random.default_rng(seed)

    say(f"workspace volume under the default limits ({samples} samples)")
    pts = _uniform(rng, DEFAULT_BOX_M, samples)
    hits = in_workspace(pts, params, limits)
    vol_default = volume_from_hits("default limits", pts, hits, DEFAULT_BOX_M)
    workspace_points = pts[hits]

    say(f"workspace volume by geometric reachability ({samples} samples)")
    box = reach_box_m(params)
    pts = _uniform(rng, box, samples)
    reach = inverse_kinematics(pts, params, strict=False).reachable.all(axis=-1)
    vol_geo = volume_from_hits("geometric reachability", pts, reach, box)
    vol_front = volume_from_hits("geometric reachability, z > 0", pts, reach & (pts[:, 2] > 0), box)

    say(f"volume against leg-angle range ({samples} samples)")
    table, half, paper_range_pts = _leg_range_table(params, limits, samples, rng)

    say(f"1 mm resolution map ({map_points} points x 6 neighbours)")
    map_pts = sample_workspace(map_points, rng, params, limits)
    resolution, counts_per_mm = _resolution(params, map_pts, paper_range_pts, half)

    say(f"pivot torques for 3 N along x, y, z ({map_points} points)")
    torque_summary, torques, rms = _torques(params, map_pts)

    return Characterisation(
        params_name=params.name, limits=limits, seed=seed, volume_default=vol_default,
        volume_geometric=vol_geo, volume_geometric_front=vol_front, range_table=table,
        paper_range_half_width_deg=half, resolution=resolution, torque_summary=torque_summary,
        home=_home_pose(params, limits), map_points_m=map_pts, counts_per_mm=counts_per_mm,
        torques_Nm=torques, rms_torque_Nm=rms, workspace_points_m=workspace_points)


__all__ = ["Characterisation", "VolumeEstimate", "characterise", "binomial_ci95", "volume_from_hits",
           "reach_box_m", "PAPER_VOLUME_M3", "MAKER_VOLUME_M3", "PAPER_COUNTS_PER_MM"]
