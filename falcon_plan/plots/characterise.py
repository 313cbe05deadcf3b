"""The figures of ``falcon-plan characterise``, after the paper's Figures 4-8.

Each figure shows one quantity three ways, all in mm: the sampled points in an isometric
view (as the paper), and two slice maps through the middle of the workspace, the x-z plane at
y = 0 (side) and the x-y plane at the middle height (back), evaluated on a 2 mm grid. A slice
shows the value at every point of its plane, where a flat projection of a 3-D cloud mixes
points at every depth. The workspace figure colours its slices by the margin to the nearest
limit [deg].
"""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from falcon_plan.plots.common import save

if TYPE_CHECKING:
    from falcon_plan.model.characterise import Characterisation
    from falcon_plan.model.dynamics import FalconModel

SLICE_STEP_M = 0.002
"""Grid spacing of the slice maps [m]."""

PLOT_POINTS = 6_000
"""At most this many points are drawn in the isometric view (the statistics use all)."""

FIGURES = (
    # (file name, title, which map, colour-bar labels of the points and of the slices)
    ("fig4_workspace.png", "Workspace (default limits): points coloured by z; slices by the margin to the "
                           "nearest limit", "workspace", ("z [mm]", "margin to the nearest limit [deg]")),
    ("fig5_resolution.png", "Encoder counts per 1 mm move", "counts_per_mm", ("counts / mm",) * 2),
    ("fig6_torque_z.png", "RMS pivot torque for 3 N along z", "z", ("torque [N.m]",) * 2),
    ("fig7_torque_x.png", "RMS pivot torque for 3 N along x", "x", ("torque [N.m]",) * 2),
    ("fig8_torque_y.png", "RMS pivot torque for 3 N along y", "y", ("torque [N.m]",) * 2),
)


def _value_function(key: str, model: FalconModel) -> Callable[[np.ndarray], np.ndarray]:
    """Points inside the workspace (n, 3) [m] -> the figure's value (n,)."""
    from falcon_plan.model.characterise import FORCE_N, _resolution_statistics
    from falcon_plan.model.kinematics import leg_torques_for_force
    from falcon_plan.plots.plan import workspace_margins_deg

    if key == "workspace":
        def margin(points: np.ndarray) -> np.ndarray:
            values = workspace_margins_deg(points, model)
            values.pop("forward singularity")
            return np.min(np.stack(list(values.values())), axis=0)
        return margin
    if key == "counts_per_mm":
        return lambda points: _resolution_statistics(model.params, points)[1]
    force = np.zeros(3)
    force["xyz".index(key)] = FORCE_N
    return lambda points: np.sqrt(np.mean(leg_torques_for_force(points, force, model.params) ** 2, axis=-1))


def _slice(plane: str, level_m: float, lo: np.ndarray, hi: np.ndarray, model: FalconModel,
           value: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grid axes [m] and values (NaN outside the workspace) of the plane ``"xz"`` or ``"xy"``
    at the other coordinate = level_m."""
    from falcon_plan.model.workspace import in_workspace

    i, j = "xyz".index(plane[0]), "xyz".index(plane[1])
    a = np.arange(lo[i], hi[i] + SLICE_STEP_M, SLICE_STEP_M)
    b = np.arange(lo[j], hi[j] + SLICE_STEP_M, SLICE_STEP_M)
    grid = np.full((len(b), len(a), 3), level_m)
    grid[..., i], grid[..., j] = np.meshgrid(a, b)
    points = grid.reshape(-1, 3)
    inside = in_workspace(points, model.params, model.limits)
    values = np.full(len(points), np.nan)
    if inside.any():
        values[inside] = value(points[inside])
    return a, b, values.reshape(len(b), len(a))


def write_figures(result: Characterisation, out_dir: Path, rng: np.random.Generator, model: FalconModel | None = None) -> list[Path]:
    """Write the five PNG figures of ``result``, a
    :class:`~falcon_plan.model.characterise.Characterisation`, into ``out_dir``; returns their
    paths. ``rng`` picks the points drawn when there are more than :data:`PLOT_POINTS`;
    ``model`` gives the slice maps' workspace and values (default: the nominal model of the
    result's parameter set and limits)."""
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import get_params
    from falcon_plan.model.workspace import workspace_extent_m

    model = model or FalconModel(get_params(result.params_name), limits=result.limits)
    lo, hi = workspace_extent_m(model.params, model.limits)
    lo, hi = lo - SLICE_STEP_M, hi + SLICE_STEP_M
    middle_z = float(np.round((lo[2] + hi[2]) / 2, 3))
    maps = {"workspace": (result.workspace_points_m, 1e3 * result.workspace_points_m[:, 2]),
            "counts_per_mm": (result.map_points_m, result.counts_per_mm)}
    maps.update({k: (result.map_points_m, v) for k, v in result.rms_torque_Nm.items()})
    paths = []
    for name, title, key, label in FIGURES:
        points, values = maps[key]
        if len(points) > PLOT_POINTS:
            keep = rng.choice(len(points), PLOT_POINTS, replace=False)
            points, values = points[keep], values[keep]
        value = _value_function(key, model)
        slices = [("xz", 0.0, "side: x-z slice at y = 0"),
                  ("xy", middle_z, f"back: x-y slice at z = {1e3 * middle_z:.0f} mm")]
        fig = _figure(points, values, [(p, lvl, t, *_slice(p, lvl, lo, hi, model, value)) for p, lvl, t in slices],
                      title, label, separate_scale=key == "workspace")
        paths.append(save(fig, out_dir / name))
    return paths


def _figure(points: np.ndarray, values: np.ndarray, slices: list[tuple[Any, ...]], title: str,
            labels: tuple[str, str], separate_scale: bool) -> Any:
    """Isometric scatter [mm] and the slice maps, each with its colour bar: one range over
    points and slices when they show the same quantity (``separate_scale`` False: nothing is
    clipped), else one each."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=(16, 5.2), layout="constrained")
    fig.suptitle(title)
    iso = fig.add_subplot(1, 3, 1, projection="3d")
    pts = 1e3 * points
    slice_values = np.concatenate([s[5].ravel() for s in slices])
    if separate_scale:  # the workspace's slices show the margin, the points their z: two scales
        iso_range = (float(np.nanmin(values)), float(np.nanmax(values)))
        slice_range = (0.0, float(np.nanmax(slice_values)))
    else:  # one quantity: one scale over the points and the slices (neither is clipped)
        both = np.concatenate([np.ravel(values), slice_values])
        iso_range = slice_range = (float(np.nanmin(both)), float(np.nanmax(both)))
    art = iso.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=values, s=2, cmap="viridis", vmin=iso_range[0],
                      vmax=iso_range[1])
    for setter, axis in ((iso.set_xlabel, "x"), (iso.set_ylabel, "y"), (iso.set_zlabel, "z")):
        setter(f"{axis} [mm]")
    for axis in (iso.xaxis, iso.yaxis, iso.zaxis):
        axis.set_major_locator(MaxNLocator(5))
    iso.view_init(elev=20, azim=-60)
    iso.set_title("isometric (sampled points)")
    fig.colorbar(art, ax=iso, shrink=0.7, pad=0.12, label=f"{labels[0]} (isometric view)")
    for index, (plane, _level, subtitle, a, b, grid) in enumerate(slices, start=2):
        ax = fig.add_subplot(1, 3, index)
        mesh = ax.pcolormesh(1e3 * a, 1e3 * b, grid, cmap="viridis", vmin=slice_range[0], vmax=slice_range[1],
                             shading="nearest")
        ax.set_xlabel(f"{plane[0]} [mm]")
        ax.set_ylabel(f"{plane[1]} [mm]")
        ax.set_aspect("equal")
        ax.set_title(subtitle)
        ax.grid(True, alpha=0.25)
    fig.colorbar(mesh, ax=fig.axes[-1], shrink=0.85, label=f"{labels[1]} (slices)")
    return fig
