"""The picture of a plan: what the motion is and how close it runs to every limit."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from falcon_plan.plots.common import AXIS_COLOURS, LEG_COLOURS, limit_lines, new_figure, save

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.trajectory import Trajectory

PLOT_RATE_HZ = 2000.0
"""The plan is drawn from samples at this rate [Hz] (exact between the planner's nodes)."""


def workspace_margins_deg(position_m: np.ndarray, model: FalconModel) -> dict[str, np.ndarray]:
    """Distance to each workspace limit of ``model`` along a path ``position_m`` (n, 3) [m],
    base frame, the worst leg at each point: leg angle, knee and parallelogram angles [deg],
    and the forward-singularity measure above its floor (unitless). Negative = outside."""
    from falcon_plan.model.kinematics import inverse_kinematics
    from falcon_plan.model.workspace import forward_singularity_measure

    limits = model.limits
    angles = inverse_kinematics(position_m, model.params, strict=False)
    th1, knee, th3 = (np.degrees(a) for a in (angles.theta1, angles.theta2 - angles.theta1, angles.theta3))
    lo1, hi1 = np.degrees([limits.theta1_min_rad, limits.theta1_max_rad])
    knee_min, th3_min = np.degrees([limits.knee_min_rad, limits.theta3_min_rad])
    worst = lambda m: np.nanmin(m, axis=-1)  # noqa: E731 - the worst of the three legs
    return {
        "leg angle [deg]": worst(np.minimum(th1 - lo1, hi1 - th1)),
        "knee [deg]": worst(np.minimum(knee - knee_min, 180 - knee_min - knee)),
        "parallelogram [deg]": worst(np.minimum(th3 - th3_min, 180 - th3_min - th3)),
        "forward singularity": forward_singularity_measure(angles, model.params) - limits.min_forward_det,
    }


def plot_plan(trajectory: Trajectory, path: str | Path, *, model: FalconModel | None = None, tc_max: float | None = None,
              title: str | None = None) -> Path:
    """Write a PNG of ``trajectory`` (a :class:`~falcon_plan.trajectory.Trajectory`):
    position [mm] and velocity [m/s] of the end effector, leg angles [deg] in their allowed
    range, leg speeds [rad/s], feed-forward commands with +-``tc_max`` (default: the plan's)
    and the device's static saturation (a plan made with ``limit="device"`` shows the
    device's speed-dependent limit L(w) of each leg instead), and the workspace margins.
    ``model`` gives the limits and the dense resampling (default: the nominal model of the
    trajectory's parameter set); ``title`` replaces the default (method, duration, end
    points). Returns the path."""
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import get_params

    model = model or FalconModel(get_params(trajectory.params_name))
    tc_max = float(tc_max if tc_max is not None else trajectory.meta.get("tc_max", model.params.command_saturation))
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
    if trajectory.meta.get("limit") == "device":
        from falcon_plan.model.saturation import SaturationModel

        device_limit = SaturationModel.of(model.params).limit(np.abs(leg_speed))  # (n, 3)
        for leg in range(3):
            label = "device limit L(w) per leg" if leg == 0 else None
            ax_cmd.plot(t_ms, device_limit[:, leg], color=LEG_COLOURS[leg], ls="--", lw=0.8, label=label)
            ax_cmd.plot(t_ms, -device_limit[:, leg], color=LEG_COLOURS[leg], ls="--", lw=0.8)
        used = float((np.abs(dense.commands) / device_limit).max())
        top = float(device_limit.max())
        ax_cmd.set_title(f"Commands: peak |Tc| {worst:.0f}, at most {100 * used:.0f} % of the device limit")
    else:
        limit_lines(ax_cmd, tc_max, f"limit tc_max = +-{tc_max:g}", "tab:red")
        saturation = model.params.command_saturation
        if saturation < tc_max:
            limit_lines(ax_cmd, saturation, f"static saturation +-{saturation}", "0.5", ":")
        top = tc_max
        ax_cmd.set_title(f"Commands: peak |Tc| {worst:.0f} = {100 * worst / tc_max:.0f} % of the limit")
    ax_cmd.set_ylabel("feed-forward command Tc [command units]")
    ax_cmd.set_ylim(-1.15 * max(top, worst), 1.15 * max(top, worst))

    margins = workspace_margins_deg(dense.position_m, model)
    det = margins.pop("forward singularity")
    for (name, values), style in zip(margins.items(), ("-", "--", "-.")):
        ax_margin.plot(t_ms, values, ls=style, label=name)
    ax_margin.axhline(0.0, color="tab:red", lw=1.0, label="limit (0)")
    ax_margin.set_ylabel("margin to the limit [deg]")
    ax_margin.set_ylim(bottom=min(-2.0, float(np.nanmin(list(margins.values())))))
    ax_margin.set_title("Workspace margins (worst leg)")
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
    fig.suptitle(title or f"Plan ({method}): {1e3 * trajectory.duration_s:.1f} ms from "
                 f"({', '.join(f'{v:.0f}' for v in p0)}) to ({', '.join(f'{v:.0f}' for v in p1)}) mm")
    return save(fig, path)
