"""``falcon-plan characterise``: reproduce the paper's Section 5 (workspace, resolution, forces).

Writes to ``--out DIR``: ``summary.json`` (see :meth:`Characterisation.to_dict`), ``maps.npz``
(the per-point maps: points [m], counts per mm, pivot torques [N.m] for 3 N along x, y, z),
and PNG figures in the manner of the paper's Figures 4-8:
``fig4_workspace.png``, ``fig5_resolution.png``, ``fig6_torque_z.png``,
``fig7_torque_x.png``, ``fig8_torque_y.png``. Progress goes to stderr.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.model.characterise import Characterisation, characterise
from falcon_plan.model.params import get_params

DEFAULT_SAMPLES = 1_000_000
MAX_MAP_POINTS = 20_000
PLOT_POINTS = 6_000
"""At most this many points are drawn per scatter plot (the statistics use all of them)."""

FIGURES = (
    # (file name, title, which map, colour-bar label)
    ("fig4_workspace.png", "Workspace (default limits), coloured by z", "workspace", "z [m]"),
    ("fig5_resolution.png", "Encoder counts per 1 mm move", "counts_per_mm", "counts / mm"),
    ("fig6_torque_z.png", "RMS pivot torque for 3 N along z", "z", "torque [N.m]"),
    ("fig7_torque_x.png", "RMS pivot torque for 3 N along x", "x", "torque [N.m]"),
    ("fig8_torque_y.png", "RMS pivot torque for 3 N along y", "y", "torque [N.m]"),
)


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def register(subparsers: Any) -> None:
    """Add the ``characterise`` subcommand."""
    parser = subparsers.add_parser(
        "characterise", help="reproduce the paper's Section 5 (workspace, resolution, force maps)",
        description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, type=Path, help="output directory (created if missing)")
    parser.add_argument("--samples", type=_positive_int, default=DEFAULT_SAMPLES,
                        help=f"Monte Carlo samples per volume estimate (default {DEFAULT_SAMPLES}; >= 100)")
    parser.add_argument("--map-points", type=_positive_int, default=None,
                        help=f"workspace points for the resolution and torque maps "
                             f"(default min({MAX_MAP_POINTS}, samples / 10))")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--params", default="acra2009",
                        help="parameter set: acra2009, libnifalcon or a .json file (default acra2009)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the characterisation and write the outputs; returns the exit code."""
    start = time.perf_counter()

    def progress(message: str) -> None:
        print(f"characterise [{time.perf_counter() - start:5.1f} s] {message}", file=sys.stderr, flush=True)

    map_points = args.map_points or max(10, min(MAX_MAP_POINTS, args.samples // 10))
    result = characterise(get_params(args.params), samples=args.samples, map_points=map_points,
                          seed=args.seed, progress=progress)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    progress("writing summary.json and maps.npz")
    summary = result.to_dict()
    summary["runtime_s"] = time.perf_counter() - start
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    np.savez_compressed(out / "maps.npz", points_m=result.map_points_m, counts_per_mm=result.counts_per_mm,
                        **{f"torque_{k}_Nm": v for k, v in result.torques_Nm.items()},
                        **{f"rms_torque_{k}_Nm": v for k, v in result.rms_torque_Nm.items()})
    progress("plotting figures 4-8")
    write_figures(result, out, np.random.default_rng(args.seed))
    progress(f"done: {out}")
    volume = result.volume_default
    print(f"workspace volume {volume.volume_m3:.3e} m^3 (95 % CI {volume.ci95_m3[0]:.3e}..{volume.ci95_m3[1]:.3e}); "
          f"resolution {result.resolution['mean_counts_per_mm']:.1f} counts/mm (paper 30); "
          f"RMS torque for 3 N x/y/z "
          + "/".join(f"{result.torque_summary[k]['rms_torque_mean_Nm']:.3f}" for k in "xyz") + " N.m")
    return 0


def write_figures(result: Characterisation, out_dir: Path, rng: np.random.Generator) -> list[Path]:
    """Write the five PNG figures (Agg backend) and return their paths."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = {"workspace": (result.workspace_points_m, result.workspace_points_m[:, 2]),
            "counts_per_mm": (result.map_points_m, result.counts_per_mm)}
    maps.update({k: (result.map_points_m, v) for k, v in result.rms_torque_Nm.items()})
    paths = []
    for name, title, key, label in FIGURES:
        points, values = maps[key]
        if len(points) > PLOT_POINTS:
            keep = rng.choice(len(points), PLOT_POINTS, replace=False)
            points, values = points[keep], values[keep]
        fig = _scatter_views(plt, points, values, title, label)
        path = out_dir / name
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def _scatter_views(plt: Any, points: np.ndarray, values: np.ndarray, title: str, label: str) -> Any:
    """Isometric, side (x-z) and back (x-y) views of coloured points [m], as in Figure 4."""
    fig = plt.figure(figsize=(15, 5))
    fig.subplots_adjust(left=0.03, right=0.88, bottom=0.12, wspace=0.35)
    fig.suptitle(title)
    iso = fig.add_subplot(1, 3, 1, projection="3d")
    art = iso.scatter(points[:, 0], points[:, 1], points[:, 2], c=values, s=2, cmap="viridis")
    iso.set_xlabel("x [m]")
    iso.set_ylabel("y [m]")
    iso.set_zlabel("z [m]", labelpad=8)
    iso.view_init(elev=20, azim=-60)
    iso.set_title("isometric")
    for index, (i, j, view) in enumerate([(0, 2, "side (x-z)"), (0, 1, "back (x-y)")], start=2):
        ax = fig.add_subplot(1, 3, index)
        order = np.argsort(points[:, 3 - i - j])  # draw far points first
        ax.scatter(points[order, i], points[order, j], c=values[order], s=2, cmap="viridis",
                   vmin=values.min(), vmax=values.max())
        ax.set_xlabel(f"{'xyz'[i]} [m]")
        ax.set_ylabel(f"{'xyz'[j]} [m]")
        ax.set_aspect("equal")
        ax.set_title(view)
    fig.colorbar(art, cax=fig.add_axes((0.91, 0.15, 0.015, 0.7)), label=label)
    return fig
