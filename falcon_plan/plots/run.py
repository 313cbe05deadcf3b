"""The picture of a run: how well the device followed its reference, from a falcon log."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from falcon_plan.errors import LogFormatError
from falcon_plan.plots.common import AXIS_COLOURS, LEG_COLOURS, limit_lines, new_figure, save

if TYPE_CHECKING:
    from falcon_plan.falconlog import FalconLog


def run_errors(log: FalconLog) -> tuple[np.ndarray, np.ndarray]:
    """Tracking errors of a log with reference columns, per row: measured minus reference
    counts (n, 3), and the end effector's error [mm] (n, 3), forward kinematics of the
    measured counts minus that of the reference counts (base frame)."""
    from falcon_plan.model.kinematics import counts_to_position
    from falcon_plan.model.params import get_params

    if log.ref is None:
        raise LogFormatError("tracking errors need a log with reference columns (ref0..ref2), as the executor writes")
    params = get_params(log.meta.get("params", "acra2009"))
    return log.enc - log.ref, 1e3 * (counts_to_position(log.enc, params) - counts_to_position(log.ref, params))


def plot_run(log: FalconLog, path: str | Path, *, title: str | None = None) -> Path:
    """Write a PNG of a falcon log that has reference columns (the executor's): measured and
    reference counts per leg, the tracking error per leg [counts], the end-effector error in
    the base frame [mm] (forward kinematics of both), and the commands with the command
    limit and the static saturation, under ``title`` (default: samples, rate and controller). Returns the
    path."""
    from falcon_plan.model.params import get_params

    params = get_params(log.meta.get("params", "acra2009"))
    t = log.t_s - log.t_s[0]
    err_counts, err_mm = run_errors(log)
    preroll = float(log.meta.get("preroll_s", 0.0))
    moving = t >= preroll - 1e-9  # statistics from the move's start, as the executor's report
    if not moving.any():  # a run stopped during its pre-roll: statistics over all of it
        moving = np.ones_like(moving)
    limit = float(log.meta.get("command_limit", params.command_limit))

    fig, axes = new_figure(4, 1, (11, 11), sharex=True)
    ax_counts, ax_err, ax_mm, ax_cmd = axes
    for leg in range(3):
        colour = LEG_COLOURS[leg]
        ax_counts.plot(t, log.enc[:, leg], color=colour, lw=1.2, label=f"leg {leg} measured")
        ax_counts.plot(t, log.ref[:, leg], color=colour, lw=0.9, ls="--", label=f"leg {leg} reference")
        err = err_counts[moving, leg]
        ax_err.plot(t, err_counts[:, leg], color=colour, lw=0.9,
                    label=f"leg {leg}: rms {np.sqrt(np.mean(err ** 2)):.1f}, max {np.abs(err).max():.0f} counts")
        ax_cmd.plot(t, log.tc[:, leg], color=colour, lw=0.9, label=f"leg {leg}")
    ax_counts.set_ylabel("encoder [counts]")
    ax_counts.set_title("Reference (dashed) and measured encoder counts")
    ax_err.axhline(0.0, color="0.4", lw=0.8)
    ax_err.set_ylabel("measured - reference [counts]")
    ax_err.set_title("Tracking error per leg (statistics from the move's start)")
    for i, axis in enumerate("xyz"):
        ax_mm.plot(t, err_mm[:, i], color=AXIS_COLOURS[i], lw=0.9, label=axis)
    norm = np.linalg.norm(err_mm, axis=1)
    ax_mm.plot(t, norm, color="k", lw=1.2, label=f"|e|: rms {np.sqrt(np.mean(norm[moving] ** 2)):.2f}, "
                                                 f"max {norm[moving].max():.2f} mm")
    ax_mm.set_ylabel("position error [mm]")
    ax_mm.set_title("Tracking error of the end effector (forward kinematics, base frame)")
    limit_lines(ax_cmd, limit, f"command limit +-{limit:g}", "tab:red")
    if params.command_saturation < limit:
        limit_lines(ax_cmd, params.command_saturation, f"static saturation +-{params.command_saturation}", "0.5", ":")
    ax_cmd.set_ylim(-1.12 * limit, 1.12 * limit)
    ax_cmd.set_ylabel("command Tc [command units]")
    saturated = int(np.any(np.abs(log.tc) >= limit, axis=1).sum())
    ax_cmd.set_title(f"Commands sent ({saturated} samples at the limit)")
    ax_cmd.set_xlabel("time [s]")
    for ax in axes:
        if preroll > 0:
            ax.axvline(preroll, color="0.5", lw=0.8, ls="-.", label="move starts" if ax is ax_cmd else None)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="best", ncol=2 if ax is ax_counts else 1)
    rate = log.meta.get("rate_hz", "?")
    fig.suptitle(title or f"Run: {len(log)} samples at {rate} Hz, controller {log.meta.get('controller', '?')}, "
                          f"device {log.meta.get('device', '?')}")
    return save(fig, path)
