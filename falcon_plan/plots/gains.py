"""The picture of a tracking LQR's gain schedule along a plan (:mod:`falcon_plan.lqr`)."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from falcon_plan.plots.common import LEG_COLOURS, new_figure, save

if TYPE_CHECKING:
    from falcon_plan.lqr import GainSchedule


def plot_gains(schedule: GainSchedule, path: str | Path, *, title: str | None = None) -> Path:
    """Write a PNG of ``schedule`` along its reference: the reference counts; the position
    gains (each leg's own, and the largest coupling to the other legs) [command units per
    count]; the count-rate gains [command units per count/s]; the feed-forward with the
    device's speed-dependent limit the commands are clamped to. Time from the schedule's first
    sample [s]; ``title`` overrides the default. Returns the path."""
    gains = schedule.gains_at()                 # (K, 3, nz); u = -K z, z = (dn, dn/dt, line)
    t = np.arange(schedule.samples) / schedule.rate_hz
    fig, axes = new_figure(4, 1, (11, 10), sharex=True)
    ax_ref, ax_kp, ax_kd, ax_ff = axes
    legs = np.arange(3)
    for leg in range(3):
        colour = LEG_COLOURS[leg]
        ax_ref.plot(t, schedule.ref_counts[:, leg], color=colour, lw=1.2, label=f"leg {leg}")
        # the sign convention: a positive command lowers the counts, so the gains are negative
        ax_kp.plot(t, -gains[:, leg, leg], color=colour, lw=1.2, label=f"leg {leg}: own")
        others = np.abs(gains[:, leg, :3][:, legs != leg]).max(axis=1)
        ax_kp.plot(t, others, color=colour, lw=0.9, ls=":", label=f"leg {leg}: largest coupling")
        ax_kd.plot(t, -gains[:, leg, 3 + leg], color=colour, lw=1.2, label=f"leg {leg}")
        ax_ff.plot(t, schedule.feedforward[:, leg], color=colour, lw=1.0, label=f"leg {leg}")
        ax_ff.plot(t, schedule.command_limits[:, leg], color=colour, lw=0.7, ls="--")
        ax_ff.plot(t, -schedule.command_limits[:, leg], color=colour, lw=0.7, ls="--")
    ax_ref.set_ylabel("reference [counts]")
    ax_ref.set_title("Reference")
    ax_kp.set_ylabel("[command units / count]")
    ax_kp.set_title("Position gains (feedback per count of error)")
    ax_kd.set_ylabel("[command units / (count/s)]")
    ax_kd.set_title("Count-rate gains")
    ax_ff.set_ylabel("[command units]")
    ax_ff.set_title("Feed-forward, and the device's limit the commands are clamped to (dashed)")
    ax_ff.set_xlabel("time [s]")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.suptitle(title or f"Time-varying LQR along the plan: {schedule.delay_samples:g}-sample command delay, "
                          f"{schedule.rate_hz:g} Hz, {schedule.gains.shape[0]} distinct gains")
    return save(fig, path)


__all__ = ["plot_gains"]
