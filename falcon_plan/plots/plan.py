"""The picture of a plan: what the motion is and how close it runs to every limit."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from falcon_plan.model.workspace import workspace_margins_deg
from falcon_plan.plots.common import AXIS_COLOURS, LEG_COLOURS, limit_lines, new_figure, save

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.planning.bound import CommandBound
    from falcon_plan.trajectory import Trajectory

PLOT_RATE_HZ = 2000.0
"""The plan is drawn from samples at this rate [Hz] (exact between the planner's nodes)."""


def plan_bound(trajectory: Trajectory, model: FalconModel, tc_max: float | None = None) -> CommandBound:
    """The command bound ``trajectory`` was planned under, from its metadata (limit kind,
    tc_max, feedback reserve) for ``model``'s device; ``tc_max`` [command units] overrides the
    recorded one. What the plan's report measures "max |Tc|/bound" against."""
    from falcon_plan.planning.bound import CommandBound
    from falcon_plan.model.saturation import SaturationModel

    meta = trajectory.meta
    limit = float(tc_max if tc_max is not None else meta.get("tc_max", model.params.command_saturation))
    return CommandBound(str(meta.get("limit", "constant")), limit, float(meta.get("feedback_reserve", 0.0)),
                        SaturationModel.of(model.params))


def plot_plan(trajectory: Trajectory, path: str | Path, *, model: FalconModel | None = None, tc_max: float | None = None,
              title: str | None = None) -> Path:
    """Write a PNG of ``trajectory`` (a :class:`~falcon_plan.trajectory.Trajectory`):
    position [mm] and velocity [m/s] of the end effector, leg angles [deg] in their allowed
    range, leg speeds [rad/s], feed-forward commands against the bound the plan was made
    under (:func:`plan_bound`: ``tc_max``, default the plan's, minus its feedback reserve, or
    for ``limit="device"`` the device's speed-dependent limit L(w) of each leg minus the
    reserve; the title's percentage is the report's max |Tc|/bound), and the workspace
    margins [deg].
    ``model`` gives the limits and the dense resampling (default: the nominal model of the
    trajectory's parameter set); ``title`` replaces the default (method, duration, end
    points). Returns the path."""
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import get_params

    model = model or FalconModel(get_params(trajectory.params_name))
    dense = trajectory.sample(PLOT_RATE_HZ, model)
    t_ms = 1e3 * dense.t_s
    theta1 = dense.theta1_rad
    leg_speed = np.gradient(theta1, dense.t_s, axis=0)

    fig, axes = new_figure(3, 2, (12, 9.5), sharex=True)
    (ax_pos, ax_vel), (ax_ang, ax_speed), (ax_cmd, ax_margin) = axes
    for i, axis in enumerate("xyz"):
        ax_pos.plot(t_ms, 1e3 * dense.position_m[:, i], color=AXIS_COLOURS[i], label=axis)
        ax_vel.plot(t_ms, dense.velocity_m_s[:, i], color=AXIS_COLOURS[i], label=axis)
    ax_vel.plot(t_ms, np.linalg.norm(dense.velocity_m_s, axis=1), color="0.3", ls=":", label="|v|")
    ax_pos.set_ylabel("position [mm]")
    ax_pos.set_title("End effector position (base frame)")
    ax_vel.set_ylabel("velocity [m/s]")
    ax_vel.set_title("End effector velocity")

    lo, hi = np.degrees([model.limits.theta1_min_rad, model.limits.theta1_max_rad])
    ax_ang.axhspan(lo, hi, color="0.92", label=f"allowed [{lo:g}, {hi:g}] deg")
    for leg in range(3):
        ax_ang.plot(t_ms, np.degrees(theta1[:, leg]), color=LEG_COLOURS[leg], label=f"leg {leg}")
        ax_speed.plot(t_ms, leg_speed[:, leg], color=LEG_COLOURS[leg], label=f"leg {leg}")
        ax_cmd.plot(t_ms, dense.commands[:, leg], color=LEG_COLOURS[leg], label=f"leg {leg}")
    ax_ang.set_ylim(min(lo, np.degrees(theta1).min()) - 10, max(hi, np.degrees(theta1).max()) + 10)
    ax_ang.set_ylabel("leg angle theta1 [deg]")
    ax_ang.set_title("Leg angles in their allowed range")
    ax_speed.set_ylabel("leg speed [rad/s]")
    ax_speed.set_title("Leg speeds")

    worst = np.abs(dense.commands).max()
    bound = plan_bound(trajectory, model, tc_max)
    allowed = bound.allowed(model, dense.position_m, dense.velocity_m_s, dense.acceleration_m_s2)  # (n, 3)
    used = float((np.abs(dense.commands) / allowed).max())
    if bound.kind == "device":
        for leg in range(3):
            label = f"plan's bound: device limit L(w) - {bound.reserve:g} reserve, per leg" if leg == 0 else None
            ax_cmd.plot(t_ms, allowed[:, leg], color=LEG_COLOURS[leg], ls="--", lw=0.8, label=label)
            ax_cmd.plot(t_ms, -allowed[:, leg], color=LEG_COLOURS[leg], ls="--", lw=0.8)
        top = float(allowed.max())
        ax_cmd.set_title(f"Commands: peak |Tc| {worst:.0f}, at most {100 * used:.1f} % of the plan's bound")
    else:
        reserve = f" ({bound.tc_max:g} - {bound.reserve:g} feedback reserve)" if bound.reserve else ""
        limit_lines(ax_cmd, bound.at_rest, f"plan's bound +-{bound.at_rest:g}{reserve}", "tab:red")
        saturation = model.params.command_saturation
        if bound.reserve:
            same = " = static saturation" if saturation == bound.tc_max else ""
            limit_lines(ax_cmd, bound.tc_max, f"tc_max +-{bound.tc_max:g}{same}", "0.4", ":")
        if saturation < bound.tc_max:
            limit_lines(ax_cmd, saturation, f"static saturation +-{saturation}", "0.5", ":")
        top = bound.tc_max
        ax_cmd.set_title(f"Commands: peak |Tc| {worst:.0f} = {100 * used:.1f} % of the plan's bound {bound.at_rest:g}")
    ax_cmd.set_ylabel("feed-forward command Tc [command units]")
    ax_cmd.set_ylim(-1.15 * max(top, worst), 1.15 * max(top, worst))

    margins = workspace_margins_deg(dense.position_m, model)
    det = margins.pop("forward singularity")
    for (name, values), style in zip(margins.items(), ("-", "--", "-.")):
        ax_margin.plot(t_ms, values, ls=style, label=name)
    ax_margin.axhline(0.0, color="tab:red", lw=1.0, label="limit (0)")
    ax_margin.set_ylabel("margin to the limit [deg]")
    ax_margin.set_ylim(bottom=min(-2.0, float(np.nanmin(list(margins.values())))))
    nearest = np.nanmin(np.stack(list(margins.values())))
    ax_margin.set_title(f"Workspace margins (worst leg): nearest limit {nearest:.1f} deg away")
    ax_margin.text(0.98, 0.04, f"forward-singularity measure: min {np.nanmin(det) + model.limits.min_forward_det:.2f} "
                   f"(floor {model.limits.min_forward_det:g})", transform=ax_margin.transAxes, ha="right",
                   fontsize=8, bbox={"facecolor": "white", "alpha": 0.8, "lw": 0})
    for ax in axes.flat:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    for ax in axes[-1]:
        ax.set_xlabel("time [ms]")
    p0, p1 = (np.round(1e3 * trajectory.position_m[i]) + 0.0 for i in (0, -1))  # + 0.0: no "-0"
    method = trajectory.meta.get("method", trajectory.source)
    payload = model.effects.payload_kg
    fig.suptitle(title or f"Plan ({method}): {1e3 * trajectory.duration_s:.1f} ms from "
                 f"({', '.join(f'{v:.0f}' for v in p0)}) to ({', '.join(f'{v:.0f}' for v in p1)}) mm"
                 + (f", payload {payload:g} kg" if payload else ""))
    return save(fig, path)
