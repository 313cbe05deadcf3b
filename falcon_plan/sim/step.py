"""The paper's Section 6 validation experiment, in simulation.

The device starts at rest under the encoder-space PD (kp 10, kd 0.1) with the reference at
``start_m``'s counts, already sagged to where the PD's steady-state error holds it against
gravity (:func:`pd_equilibrium`; a real run starts settled too). At ``step_at_s`` the
reference steps to the goal's counts, and the run goes on to ``duration_s``. The result is a falcon log (with ref columns and the metadata ``rate_hz``,
``controller``, ``params``), a summary (settling time, steady-state error in counts, peak
command) and, on request, a plot of encoder counts and commands over time like the paper's
Figure 9.

Being integral-free, the PD settles with an error n - ref = Tc_hold / kp, where Tc_hold are
the commands that hold the device against gravity there; the summary reports that
prediction (from the model's inverse dynamics) next to the simulated error.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidParameterError
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import counts_to_position, position_to_counts
from falcon_plan.model.workspace import require_in_workspace
from falcon_plan.control import DEFAULT_KD, DEFAULT_KP, EncoderPD
from falcon_plan.sim.plant import SimPlant

SETTLING_BAND_COUNTS = 3
"""Settled: every later sample within this many counts of the final value."""
STEADY_WINDOW_S = 0.1
"""The steady-state error is averaged over the last this many seconds."""


@dataclass(frozen=True)
class StepResult:
    """Outcome of one simulated step experiment. Per-leg arrays have shape (3,).

    Attributes
    ----------
    log : the run's falcon log, with ref columns and the metadata ``rate_hz``,
        ``controller``, ``params`` (and ``effects`` when not nominal).
    start_m, goal_m : the start and goal points [m], base frame.
    step_at_s : time of the reference step [s], rounded to a whole tick.
    goal_counts : the reference after the step [counts] (fractional).
    settling_time_s : time from the step until the counts stay within
        SETTLING_BAND_COUNTS of their final value [s]; NaN if they never do before the end.
    steady_state_error_counts : mean of n - ref over the last STEADY_WINDOW_S [counts].
    predicted_error_counts : Tc_hold / kp at the final position: the integral-free PD's
        expected error [counts].
    peak_command : largest |Tc| issued after the step [command units].
    final_position_m : the end effector's position at the end of the run [m], base frame.
    """

    log: FalconLog
    start_m: np.ndarray
    goal_m: np.ndarray
    step_at_s: float
    goal_counts: np.ndarray
    settling_time_s: np.ndarray
    steady_state_error_counts: np.ndarray
    predicted_error_counts: np.ndarray
    peak_command: np.ndarray
    final_position_m: np.ndarray

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no log rows)."""
        def listed(a: np.ndarray) -> list[float | None]:
            return [None if not np.isfinite(x) else round(float(x), 6) for x in a]
        return {
            "start_m": listed(self.start_m), "goal_m": listed(self.goal_m),
            "rate_hz": float(self.log.meta["rate_hz"]), "step_at_s": self.step_at_s,
            "duration_s": float(self.log.t_s[-1] + (self.log.t_s[1] - self.log.t_s[0])),
            "goal_counts": listed(self.goal_counts),
            "settling_time_s": listed(self.settling_time_s),
            "settling_band_counts": SETTLING_BAND_COUNTS,
            "steady_state_error_counts": listed(self.steady_state_error_counts),
            "predicted_error_counts": listed(self.predicted_error_counts),
            "peak_command": [int(x) for x in self.peak_command],
            "final_position_m": listed(self.final_position_m),
            "controller": self.log.meta["controller"], "params": self.log.meta["params"],
            "effects": json.loads(self.log.meta.get("effects", "{}")),
        }

    def summary(self) -> str:
        """A few human-readable lines."""
        def fmt(a: np.ndarray, spec: str) -> str:
            return ", ".join("never" if not np.isfinite(x) else format(float(x), spec) for x in a)
        return "\n".join([
            f"step {np.round(self.start_m * 1e3, 1).tolist()} mm -> "
            f"{np.round(self.goal_m * 1e3, 1).tolist()} mm at {self.log.meta['rate_hz']} Hz",
            f"settling (+-{SETTLING_BAND_COUNTS} counts) [s]: {fmt(self.settling_time_s, '.3f')}",
            f"steady-state error [counts]: {fmt(self.steady_state_error_counts, '.1f')} "
            f"(predicted Tc_hold/kp: {fmt(self.predicted_error_counts, '.1f')})",
            f"peak command: {', '.join(str(int(x)) for x in self.peak_command)}",
        ])


def pd_equilibrium(model: FalconModel, ref_counts: Any, kp: float = DEFAULT_KP,
                   effects: Effects | None = None, iterations: int = 20) -> np.ndarray:
    """Point [m] where the PD with gain ``kp`` [command units per count] at ``ref_counts`` (3,)
    holds the device of ``model`` (with ``effects`` instead of its own when given) at rest:
    kp (n(p) - ref) = Tc_hold(p), solved by fixed-point iteration on the counts (the holding
    command changes little per count, so it contracts fast; stops once converged to 1e-6
    counts or after ``iterations`` steps)."""
    holder = model if effects is None else model.with_effects(effects)
    ref = np.asarray(ref_counts, float)
    counts = ref.copy()
    for _ in range(iterations):
        p = counts_to_position(counts, model.params)
        new = ref + holder.holding_commands(p) / kp
        if np.abs(new - counts).max() < 1e-6:
            break
        counts = new
    return counts_to_position(counts, model.params)


def run_step_experiment(start_m: Any, goal_m: Any, *, rate_hz: float = 800.0,
                        duration_s: float = 1.5, step_at_s: float = 0.25,
                        effects: Effects | None = None, model: FalconModel | None = None,
                        kp: float = DEFAULT_KP, kd: float = DEFAULT_KD) -> StepResult:
    """Simulate the step experiment (module docstring) and return its log and summary.

    ``start_m``, ``goal_m``: points [m] inside the workspace (WorkspaceError otherwise);
    ``rate_hz``: loop rate [Hz]; ``duration_s``: length of the run [s]; ``step_at_s``: time
    of the reference step [s], 0 < step_at_s < duration_s; ``effects``: the simulated
    device's effects (default nominal); ``model``: the simulated device's parameters and
    limits (default nominal); ``kp`` [command units per count], ``kd`` [command units per
    count/s]: the PD's gains (default the paper's).
    """
    model = model or FalconModel()
    start, goal = np.asarray(start_m, float), np.asarray(goal_m, float)
    if start.shape != (3,) or goal.shape != (3,):
        raise InvalidParameterError("start_m and goal_m must be 3 coordinates [m]")
    require_in_workspace(np.stack([start, goal]), model.params, model.limits)
    if not 0.0 < step_at_s < duration_s:
        raise InvalidParameterError(f"need 0 < step_at_s ({step_at_s}) < duration_s ({duration_s})")
    plant = SimPlant(model, rate_hz=rate_hz, effects=effects)
    pd = EncoderPD(rate_hz, kp=kp, kd=kd)
    start_ref = position_to_counts(start, model.params)
    rest = pd_equilibrium(model, start_ref, kp, plant.effects)
    plant.reset(rest)
    plant.reset(rest, commands=pd.update(plant.counts, start_ref))
    pd.reset()
    k_total = int(round(duration_s * rate_hz))
    k_step = int(round(step_at_s * rate_hz))
    ref = np.empty((k_total, 3))
    ref[:k_step] = start_ref
    ref[k_step:] = position_to_counts(goal, model.params)
    run = plant.run_pd(pd, ref)

    final = run.counts[-1]
    after = run.counts[k_step:]
    outside = np.abs(after - final) > SETTLING_BAND_COUNTS
    settling = np.full(3, np.nan)
    for leg in range(3):
        idx = np.flatnonzero(outside[:, leg])
        last = idx[-1] + 1 if idx.size else 0
        if last < after.shape[0]:
            settling[leg] = last / rate_hz
    window = max(1, int(round(STEADY_WINDOW_S * rate_hz)))
    steady = (run.counts[-window:] - ref[-window:]).mean(axis=0)
    predicted = model.with_effects(plant.effects).holding_commands(plant.position_m) / kp
    meta = {"rate_hz": f"{rate_hz:g}", "controller": pd.metadata, "params": model.params.name,
            "source": "falcon-plan simulate step",
            "start_m": ",".join(f"{x:g}" for x in start), "goal_m": ",".join(f"{x:g}" for x in goal)}
    if not plant.effects.is_nominal:
        meta["effects"] = json.dumps(plant.effects.to_dict(), sort_keys=True)
    log = FalconLog(run.t_s, run.counts, run.commands, ref, meta)
    return StepResult(log=log, start_m=start, goal_m=goal, step_at_s=k_step / rate_hz,
                      goal_counts=ref[-1].copy(), settling_time_s=settling,
                      steady_state_error_counts=steady, predicted_error_counts=predicted,
                      peak_command=np.abs(run.commands[k_step:]).max(axis=0),
                      final_position_m=plant.position_m)


def plot_step(result: StepResult, path: str | Path) -> None:
    """Encoder counts (with the reference dashed) and commands over time, per leg, of
    ``result`` in the manner of the paper's Figure 9; written as a PNG at ``path``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = result.log
    fig, (ax_enc, ax_tc) = plt.subplots(2, 1, sharex=True, figsize=(8.0, 6.5))
    colours = ("tab:blue", "tab:orange", "tab:green")
    for leg, colour in enumerate(colours):
        ax_enc.plot(log.t_s, log.enc[:, leg], color=colour, label=f"leg {leg}")
        if log.ref is not None:
            ax_enc.plot(log.t_s, log.ref[:, leg], color=colour, ls="--", lw=0.8)
        ax_tc.plot(log.t_s, log.tc[:, leg], color=colour, label=f"leg {leg}")
    ax_tc.axvline(result.step_at_s, color="0.6", lw=0.8)
    for ax in (ax_enc, ax_tc):
        ax.grid(True, alpha=0.3)
    from falcon_plan.model.params import get_params
    from falcon_plan.plots.common import limit_lines

    saturation = get_params(log.meta.get("params", "acra2009")).command_saturation
    limit_lines(ax_tc, saturation, f"static saturation +-{saturation}", "0.4", ":")
    ax_enc.axvline(result.step_at_s, color="0.6", lw=0.8, label="reference step")
    ax_enc.set_ylabel("encoder [counts]")
    ax_enc.set_title(f"Simulated step, PD {log.meta['controller'][3:]} at {log.meta['rate_hz']} Hz "
                     "(dashed: reference)")
    ax_enc.legend(loc="best", fontsize=8)
    ax_tc.legend(loc="best", fontsize=8)
    ax_tc.set_ylabel("command Tc [command units]")
    ax_tc.set_xlabel("time [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


__all__ = ["StepResult", "run_step_experiment", "plot_step", "pd_equilibrium", "SETTLING_BAND_COUNTS"]
