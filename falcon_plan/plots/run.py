"""The picture of a run: how well the device followed its reference, from a falcon log."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from falcon_plan.errors import LogFormatError
from falcon_plan.falconlog import motion_start_s
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


def run_title(log: FalconLog) -> str:
    """The run in words: what was followed, on which device, under which controller (the
    controller's :attr:`~falcon_plan.control.Controller.label`, read from the log's metadata)."""
    from falcon_plan.control import Controller
    from falcon_plan.errors import FalconPlanError

    try:
        controller = Controller.from_meta(log.meta or {}).label
    except (FalconPlanError, ValueError):
        controller = "an unrecorded controller"
    device = {"SimDevice": "the simulated device", "UsbFalcon": "the USB driver (a Falcon or its emulation)"}.get(
        log.meta.get("device", ""), "the device")
    source = log.meta.get("trajectory_source", "a trajectory")
    return f"Executing the {source} plan on {device} under {controller} ({len(log)} samples)"


def plot_run(log: FalconLog, path: str | Path, *, title: str | None = None) -> Path:
    """Write a PNG of a falcon log that has reference columns (the executor's): measured and
    reference counts per leg, the tracking error per leg [counts], the end-effector error in
    the base frame [mm] (forward kinematics of both), and the commands with the command
    limit and the static saturation, under ``title`` (default: :func:`run_title`). What comes
    before the move (the approach and the hold at the start: the log's ``motion_start_s``, or
    its pre-roll) has its own narrow column, so the move fills the wide one; legends sit
    outside the axes. Returns the path."""
    from falcon_plan.model.params import get_params

    params = get_params(log.meta.get("params", "acra2009"))
    t = log.t_s - log.t_s[0]
    err_counts, err_mm = run_errors(log)
    start = motion_start_s(log.meta or {})
    moving = t >= start - 1e-9  # statistics from the move's start, as the executor's report
    if not moving.any():  # a run stopped before the move: statistics of what ran
        moving = np.ones_like(moving)
    before = ~moving
    limit = float(log.meta.get("command_limit", params.command_limit))
    norm = np.linalg.norm(err_mm, axis=1)

    split = bool(before.any()) and bool(moving.any())
    fig, grid = new_figure(4, 2 if split else 1, (13, 11), sharex="col", sharey="row", squeeze=False,
                           gridspec_kw={"width_ratios": [1, 3]} if split else {})
    columns = [(grid[:, 0], before, "before the move: approach and hold"), (grid[:, 1], moving, "the move")] \
        if split else [(grid[:, 0], np.ones_like(moving), "")]
    for axes, rows, heading in columns:
        ax_counts, ax_err, ax_mm, ax_cmd = axes
        tt = t[rows]
        for leg in range(3):
            colour = LEG_COLOURS[leg]
            ax_counts.plot(tt, log.enc[rows, leg], color=colour, lw=1.2, label=f"leg {leg} measured")
            ax_counts.plot(tt, log.ref[rows, leg], color=colour, lw=0.9, ls="--", label=f"leg {leg} reference")
            err = err_counts[rows, leg]
            ax_err.plot(tt, err, color=colour, lw=0.9,
                        label=f"leg {leg}: rms {np.sqrt(np.mean(err ** 2)):.1f}, max {np.abs(err).max():.0f} counts")
            ax_cmd.plot(tt, log.tc[rows, leg], color=colour, lw=0.9, label=f"leg {leg}")
        ax_err.axhline(0.0, color="0.4", lw=0.8)
        for i, axis in enumerate("xyz"):
            ax_mm.plot(tt, err_mm[rows, i], color=AXIS_COLOURS[i], lw=0.9, label=axis)
        ax_mm.plot(tt, norm[rows], color="k", lw=1.2, label=f"|e|: rms {np.sqrt(np.mean(norm[rows] ** 2)):.2f}, "
                                                            f"max {norm[rows].max():.2f} mm")
        limit_lines(ax_cmd, limit, f"command limit +-{limit:g}", "tab:red")
        if params.command_saturation < limit:
            limit_lines(ax_cmd, params.command_saturation, f"static saturation +-{params.command_saturation}", "0.5", ":")
        ax_cmd.set_ylim(-1.12 * limit, 1.12 * limit)
        ax_cmd.set_xlabel("time [s]")
        if heading and rows is before:
            ax_counts.set_title(heading, fontsize=10)
        for ax in axes:
            ax.grid(True, alpha=0.3)
    last = columns[-1][0]
    saturated = int(np.any(np.abs(log.tc) >= limit, axis=1).sum())
    move = "the move: " if split else ""
    for ax, what in zip(last, (f"{move}encoder counts, measured and reference (dashed)",
                               "tracking error per leg (statistics from the move's start)",
                               "end-effector error (forward kinematics, base frame)",
                               f"commands sent ({saturated} samples at the limit)")):
        ax.set_title(what, fontsize=10)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.07, 1.0), borderaxespad=0.0)
    first = columns[0][0]
    first[0].set_ylabel("encoder [counts]")
    first[1].set_ylabel("measured - reference [counts]")
    first[2].set_ylabel("position error [mm]")
    first[3].set_ylabel("command Tc [command units]")
    fig.suptitle(title or run_title(log))
    return save(fig, path)
