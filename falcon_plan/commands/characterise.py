"""``falcon-plan characterise``: reproduce the paper's Section 5 (workspace, resolution, forces).

Writes to ``--out DIR``: ``summary.json`` (see :meth:`Characterisation.to_dict`), ``maps.npz``
(the per-point maps: points [m], counts per mm, pivot torques [N.m] for 3 N along x, y, z),
and PNG figures in the manner of the paper's Figures 4-8:
``fig4_workspace.png``, ``fig5_resolution.png``, ``fig6_torque_z.png``,
``fig7_torque_x.png``, ``fig8_torque_y.png``. Progress goes to stderr.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from falcon_plan.commands import common

DEFAULT_SAMPLES = 1_000_000
MAX_MAP_POINTS = 20_000


def register(subparsers: Any) -> None:
    """Add the ``characterise`` subcommand to ``subparsers`` (the ``falcon-plan`` parser's
    subcommands)."""
    parser = subparsers.add_parser(
        "characterise", help="reproduce the paper's Section 5 (workspace, resolution, force maps)",
        description=__doc__)
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder (created if missing)")
    parser.add_argument("--samples", type=common.positive_int, default=DEFAULT_SAMPLES,
                        help=f"Monte Carlo samples per volume estimate (default {DEFAULT_SAMPLES}; >= 100)")
    parser.add_argument("--map-points", type=common.positive_int, default=None,
                        help=f"workspace points for the resolution and torque maps "
                             f"(default min({MAX_MAP_POINTS}, samples / 10))")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--params", default="acra2009",
                        help="parameter set: acra2009, libnifalcon or a .json file (default acra2009)")
    common.add_json_option(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the characterisation and write the outputs; returns the exit code."""
    start = time.perf_counter()
    progress = common.step_printer("characterise")

    import numpy as np

    from falcon_plan.fileio import make_folder
    from falcon_plan.model.characterise import characterise
    from falcon_plan.model.params import get_params
    from falcon_plan.plots.characterise import write_figures

    out = make_folder(args.out)
    map_points = args.map_points or max(10, min(MAX_MAP_POINTS, args.samples // 10))
    result = characterise(get_params(args.params), samples=args.samples, map_points=map_points,
                          seed=args.seed, progress=progress)
    progress("writing summary.json and maps.npz")
    summary = result.to_dict()
    summary["runtime_s"] = time.perf_counter() - start
    common.write_json(out / "summary.json", summary, "summary")
    np.savez_compressed(out / "maps.npz", points_m=result.map_points_m, counts_per_mm=result.counts_per_mm,
                        **{f"torque_{k}_Nm": v for k, v in result.torques_Nm.items()},
                        **{f"rms_torque_{k}_Nm": v for k, v in result.rms_torque_Nm.items()})
    progress("plotting figures 4-8 (isometric views and slice maps)")
    write_figures(result, out, np.random.default_rng(args.seed))
    progress(f"done: {out}")
    if args.json:
        common.print_json(summary)
        return 0
    volume = result.volume_default
    print(f"workspace volume {volume.volume_m3:.3e} m^3 (95 % CI {volume.ci95_m3[0]:.3e}..{volume.ci95_m3[1]:.3e}); "
          f"resolution {result.resolution['mean_counts_per_mm']:.1f} counts/mm (paper 30); "
          f"RMS torque for 3 N x/y/z "
          + "/".join(f"{result.torque_summary[k]['rms_torque_mean_Nm']:.3f}" for k in "xyz") + " N.m")
    return 0
