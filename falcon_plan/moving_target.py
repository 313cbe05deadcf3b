"""Following a moving target plan by plan (issue 24 item 5).

A target point moves (e.g. on a circle, :func:`circle_target`) and is sampled at ``update_hz``;
each sample is a new goal for the running run: the :class:`~falcon_plan.execution.splice.SpliceCoordinator`
plans from the running reference's state a little ahead (:func:`falcon_plan.planning.replan.moving_planner`)
and splices the plan in, continuous in position and velocity. A newer sample replaces one not
yet planned, so the device always heads for the latest target it could plan for.

The run is on the simulated device stepped as fast as it goes: its time is the loop's ticks,
the loop waits while a replan is made, and a replan counts as late when its measured latency
(in ticks; or a simulated one, the same on any host: ``simulated_latency_s``) reaches past its
splice tick (then it is refused and made again with the latency it measured as budget). So
the figures are the ones a real-time run on this machine would have, without its missed
deadlines on a loaded machine. The target moves in that time too.

The lag behind the target: at each logged row, the distance from the measured point to where
the target is at that instant [mm], and the time shift [s] that best aligns the executed path
with the target's (least squares over the run after its first second).
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.execution.executor import ExecutionReport, Executor
from falcon_plan.execution.splice import LatencyBudget, SpliceCoordinator
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import counts_to_position
from falcon_plan.planning.api import plan_problem
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.replan import Replan, moving_planner

PREDICT_MOTION_S = 0.05
"""How long a new plan takes to reach a nearby moving goal, roughly [s] (the prediction's
horizon beyond the replan's latency budget; :func:`follow_target`)."""
Target = Callable[[float], np.ndarray]
"""``target(t_s) -> (3,)``: where the target is at time t [s from the start of the motion, m]."""


def circle_target(center_m: Any, radius_m: float = 0.02, period_s: float = 2.0) -> Target:
    """A target going round a circle of ``radius_m`` [m] about ``center_m`` (3,) [m] in the
    x-y plane (facing the user), once per ``period_s`` [s], starting at its rightmost point."""
    c = np.asarray(center_m, dtype=float).reshape(3)

    def at(t_s: float) -> np.ndarray:
        a = 2.0 * math.pi * t_s / period_s
        return c + radius_m * np.array([math.cos(a), math.sin(a), 0.0])

    return at


class _Rows:
    """A row sink keeping each row's time [s], measured and planned points [m]."""

    def __init__(self) -> None:
        self.t, self.measured, self.planned = [], [], []

    def start(self, meta: dict[str, str], model: Any) -> None:
        """Nothing to do before the first row (``meta``, ``model`` unused)."""

    def row(self, t_s: float, enc: Any, tc: Any, ref: Any, measured_m: Any, planned_m: Any, timing: Any) -> None:
        """Keep ``t_s``, ``measured_m`` and ``planned_m`` (``enc``, ``tc``, ``ref``, ``timing`` unused)."""
        self.t.append(float(t_s))
        self.measured.append(np.array(measured_m, dtype=float))
        self.planned.append(np.array(planned_m, dtype=float))

    def finish(self, report: Any) -> None:
        """Nothing to do at the end (``report`` unused)."""


@dataclass
class MovingTargetRun:
    """A run that followed a moving target.

    Attributes
    ----------
    report : the executor's report (its ``splices``: every splice, with its jumps).
    rate_hz : the loop rate [Hz]; motion_start_tick : the loop's tick of the motion's start.
    target : the target followed.
    target_t_s, target_m : (u,) when each target sample was taken [s from the motion's start]
        and (u, 3) where it was [m].
    plans : (start time [s from the motion's start], (m, 3) points [m]) of the first plan and
        of every plan spliced in, each the part the run followed (up to the next splice).
    t_s, measured_m, planned_m : the logged rows: time [s from the motion's start], measured and
        planned points [m].
    outcomes : the coordinator's record of every replan (taken or not, budget, latency).
    """

    report: ExecutionReport
    rate_hz: float
    motion_start_tick: int
    target: Target
    target_t_s: np.ndarray
    target_m: np.ndarray
    plans: list[tuple[float, np.ndarray]]
    t_s: np.ndarray
    measured_m: np.ndarray
    planned_m: np.ndarray
    outcomes: list[dict[str, Any]] = field(default_factory=list)

    def lag(self, settle_s: float = 1.0) -> dict[str, float]:
        """How far behind the target the device stays after the first ``settle_s`` [s] of the
        motion, while the target moves: the distance measured point - target at the same instant
        (mean, max [mm]) and the time shift [s] that best aligns the executed path with the
        target's (least squares over shifts of 0 to 1 s, to a millisecond)."""
        last_update = float(self.target_t_s[-1]) if self.target_t_s.size else 0.0
        keep = (self.t_s >= settle_s) & (self.t_s <= last_update)
        t, p = self.t_s[keep], self.measured_m[keep]
        if t.size == 0:
            return {"distance_mean_mm": math.nan, "distance_max_mm": math.nan, "time_lag_s": math.nan}
        now = np.array([self.target(x) for x in t])
        dist = 1e3 * np.linalg.norm(p - now, axis=1)
        shifts = np.arange(0.0, 1.0, 1e-3)
        ts, ps = t[::8], p[::8]
        cost = [float(np.mean(np.sum((ps - np.array([self.target(x - s) for x in ts])) ** 2, axis=1))) for s in shifts]
        return {"distance_mean_mm": float(dist.mean()), "distance_max_mm": float(dist.max()),
                "time_lag_s": float(shifts[int(np.argmin(cost))])}

    def taken(self) -> list[dict[str, Any]]:
        """The splices taken (the loop's records)."""
        return [s for s in self.report.splices if s["taken"]]


FOLLOW_OPTIONS: dict[str, Any] = {"replan_search": "first", "time_budget_s": 0.1}
"""Planner options (by name) of a moving target's goals
(:class:`~falcon_plan.planning.problem.SolverSettings`): the first warm guess that makes a plan
within the bound, not the shortest of all (a goal replaced 50 ms later gains nothing from a
plan 0.2 % shorter, and the device follows only as closely as the replan's latency budget lets
it: the splice comes that much later); and an optimiser budget of two goal periods at 20 Hz,
after which the pipeline returns its ruckig fallback: one replan is made at a time, and in the
service demo a 3 mm step from rest whose switching-time solve stalled took 1.2 s beside the
running loop, while the device held still and the target went on (a 35 mm lag)."""


def follow_target(target: Target, duration_s: float = 4.0, *, update_hz: float = 20.0,
                  model: FalconModel | None = None, rate_hz: float = 800.0,
                  options: PlanOptions | None = None, hold_s: float = 1.5, predict: bool = True,
                  simulated_latency_s: float | None = None) -> MovingTargetRun:
    """Run the simulated device after ``target`` for ``duration_s`` [s] of target time, a new
    goal every 1 / ``update_hz`` [s] (module docstring), under ``model`` (default nominal; the
    simulated world is the same) at ``rate_hz`` [Hz], plans made with ``options`` (default
    ``PlanOptions.fast(**FOLLOW_OPTIONS)``); every plan's goal is held ``hold_s`` [s] after it (longer than a
    replan's budget, so that the run goes on until the next splice; after the last update the
    device holds the last goal that long). The device starts at rest at its home point; the first plan goes from
    there to the target at time 0.

    ``predict``: each goal is where the target will be when the new plan could reach it (the
    replan's latency budget plus :data:`PREDICT_MOTION_S` ahead of the sample); False: the
    sampled point itself. Goals are at rest: the executor holds a plan's end still, so a plan
    that ended moving would leave the reference's velocity to jump there.

    ``simulated_latency_s``: every replan is judged as if it took that long [s] (a machine of
    known speed, the same on any host; :class:`~falcon_plan.execution.splice.SpliceCoordinator`);
    None: by the latency measured on this machine."""
    from falcon_plan.devices.sim_device import SimDevice

    model = model or FalconModel()
    options = options or PlanOptions.fast(**FOLLOW_OPTIONS)
    home = counts_to_position(np.zeros(3))
    first = Replan.of_plan(plan_problem(PlanProblem(tuple(home), tuple(target(0.0))), options, model))
    rows = _Rows()
    samples: list[tuple[float, np.ndarray]] = []
    with SimDevice(model=FalconModel(model.params), rate_hz=rate_hz) as device:
        device.home()
        executor = Executor(device, model, preroll_s=0.05, settle_s=hold_s, sink=rows,
                            progress_period_s=1.0 / update_hz)
        coordinator = SpliceCoordinator(executor, moving_planner(options, model), first, budget=LatencyBudget(0.05),
                                        simulated_latency_s=simulated_latency_s)
        n_pre = executor.plan_start_tick()

        def progress(done: int, total: int) -> None:  # in the loop, every 1 / update_hz of its time
            t = (done - n_pre) / rate_hz
            if 0.0 < t <= duration_s:
                samples.append((t, target(t)))
                ahead = coordinator.budget.budget_s() + PREDICT_MOTION_S if predict else 0.0
                coordinator.request(target(t + ahead))

        try:
            report = executor.run(first.trajectory, progress=progress, splices=coordinator.slot)
        finally:
            coordinator.close()
    t_rows = np.array(rows.t) - n_pre / rate_hz
    planned = np.array(rows.planned)
    taken = sorted(s["tick"] + executor.command_lead() for s in report.splices if s["taken"])
    starts = [(k - n_pre) / rate_hz for k in [n_pre] + taken] + [math.inf]
    plans = [(a, planned[(t_rows >= a - 1e-9) & (t_rows < b - 1e-9)]) for a, b in zip(starts[:-1], starts[1:])]
    return MovingTargetRun(report, rate_hz, n_pre, target, np.array([s[0] for s in samples]),
                           np.array([s[1] for s in samples]).reshape(-1, 3), plans, t_rows,
                           np.array(rows.measured), planned, list(coordinator.outcomes))


def plot_moving_target(run: MovingTargetRun, path: str | Path) -> Path:
    """Draw ``run`` to the PNG ``path``: in the x-y plane the target's path and its samples, each
    spliced plan (the part the run followed, alternating colours) and the executed path; next to
    it the distance to the target over time [mm]."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [1.1, 1]})
    t_dense = np.linspace(0.0, float(run.target_t_s[-1]) if run.target_t_s.size else 1.0, 400)
    dense = np.array([run.target(x) for x in t_dense]) * 1e3
    ax.plot(dense[:, 0], dense[:, 1], color="0.75", lw=6, label="target path", zorder=1)
    ax.plot(run.target_m[:, 0] * 1e3, run.target_m[:, 1] * 1e3, "o", color="tab:orange", ms=4,
            label=f"target samples ({len(run.target_m)})", zorder=3)
    colours = ("tab:green", "tab:purple")
    for i, (_, pts) in enumerate(run.plans):
        if pts.size:
            ax.plot(pts[:, 0] * 1e3, pts[:, 1] * 1e3, color="tab:blue" if i == 0 else colours[i % 2], lw=2.0, zorder=2,
                    label="spliced plans (alternating colours)" if i == 1 else ("first plan" if i == 0 else None))
    ax.plot(run.measured_m[:, 0] * 1e3, run.measured_m[:, 1] * 1e3, color="k", lw=0.8, ls="--", zorder=4,
            label="executed (measured)")
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=3, fontsize=8)   # below: never on the data
    ax.set_title(f"moving target: {len(run.taken())} plans spliced in")
    now = np.array([run.target(x) for x in run.t_s])
    moving = (run.t_s >= 0.0) & (run.t_s <= (run.target_t_s[-1] if run.target_t_s.size else 0.0))
    ax2.plot(run.t_s[moving], 1e3 * np.linalg.norm(run.measured_m[moving] - now[moving], axis=1), color="k", lw=1,
             label="|measured - target now|")
    for i, s in enumerate(run.taken()):
        ax2.axvline((s["tick"] - run.motion_start_tick) / run.rate_hz, color="tab:blue", lw=0.4, alpha=0.5,
                    label="splices" if i == 0 else None)
    lag = run.lag()
    ax2.set_title(f"lag after 1 s: mean {lag['distance_mean_mm']:.1f} mm, max {lag['distance_max_mm']:.1f} mm, "
                  f"about {1e3 * lag['time_lag_s']:.0f} ms behind", fontsize=10)
    ax2.set_xlabel("time from the motion's start [s]")
    ax2.set_ylabel("distance to the target [mm]")
    ax2.grid(alpha=0.3)
    ax2.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=2, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["MovingTargetRun", "Target", "circle_target", "follow_target", "plot_moving_target", "FOLLOW_OPTIONS"]
