"""The calibration loop: record, identify, correct the model, plan and execute with it.

:func:`calibrate` on an open device:

1. **Record** a training excitation (``mixed`` by default) and a held-out one (``fourier``,
   another seed) with the executor (:func:`falcon_plan.approach.run_from_here`:
   home if needed, approach move, excitation), each into a falcon log whose metadata
   describes the controller exactly (:mod:`falcon_plan.control`).
2. **Identify** with :func:`falcon_plan.discrepancy.workflow.find_discrepancy` and write the
   corrected model file (:func:`corrected_model_file`, :mod:`falcon_plan.model.modelfile`).
3. **Verify**: a chain of point-to-point moves (:data:`VERIFICATION_POINTS_M`) planned by the
   minimum-time planner and executed on the device with the nominal model and with the
   corrected one (plan constraints and feed-forward), :data:`VERIFY_ROUNDS` times each,
   alternating; the tracking error of each model's best run compared
   (:func:`verification_run`).

Outputs in the folder: ``train.csv``, ``heldout.csv``, ``discrepancy/`` (the workflow's
report), ``model.json``, ``verify_nominal.csv``, ``verify_corrected.csv`` (the first round;
``verify_nominal_2.csv``, ... the later ones),
``calibration.json`` and ``calibration.png``; with ``log_format="mcap"`` the four runs are
MCAP recordings (``train.mcap``, ...) instead of CSV falcon logs, read back the same way.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from falcon_plan.errors import InvalidParameterError
from falcon_plan.fileio import write_text
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.modelfile import ModelFile, save_model, unplannable_effect_notes

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device
    from falcon_plan.execution.executor import ExecutionStatus

LOG = logging.getLogger(__name__)

VERIFICATION_POINTS_M = ((0.0, 0.0, 0.125), (0.03, 0.02, 0.11), (-0.03, 0.02, 0.14),
                         (-0.025, -0.025, 0.115), (0.03, -0.02, 0.14), (0.0, 0.0, 0.125))
"""The verification moves go from each point to the next, rest to rest [m, base frame]:
diagonals across the excitation's region (+-30 mm around the centre), against and with
gravity."""
CONTROLLER_KIND = "pd"
"""The loop of the calibration's recordings and verification moves: the PD + feed-forward, whose
modest gains let a model error show in the motion (the LQR's integral action hides it in the
commands), as ``experiment run`` records."""
PREROLL_S = 0.5
"""The executor's hold at the start of each verification run [s]."""
VERIFY_HOLD_S = 0.25
"""Hold between verification moves [s] (the tracking error includes it: settling counts)."""
VERIFY_ROUNDS = 2
"""Each model's verification chain runs this many times, nominal and corrected alternating,
and the models are compared by each move's best run (:func:`best_of_runs`): on a busy host one
move of a run now and then tracks ten times worse than the same move of the same model's other
runs (a host stall: 5.3 against 0.4 counts RMS), by more than the models differ. Every run's
figure is reported."""
RUN_ATTEMPTS = 3
"""A recording or verification run that does not complete (on a busy host a stall can end a
run with a safety stop) is run again at once, up to this many times in all."""
RUN_ENDINGS_SAID_BY_THE_RETRY = {"falcon_plan.execution.safety": "watchdog: ",
                                 "falcon_plan.devices.base": "watchdog: ",
                                 "falcon_plan.execution.holding": "hold ended: "}
"""Logger -> start of the records that say why a run ended (a watchdog's trip, the hold
before the run ending): during calibrate's runs the run's reason says it, in the retry line
or the final error, so these records are not logged as errors of their own."""


class _SaidByTheRetry(logging.Filter):
    """Drops a record starting with ``prefix`` (a watchdog that could not zero the force still
    shows)."""

    def __init__(self, prefix: str) -> None:
        super().__init__()
        self.prefix = prefix

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith(self.prefix)


@contextlib.contextmanager
def _endings_said_by_the_retry() -> Any:
    """While a calibrate run goes, what ends it (:data:`RUN_ENDINGS_SAID_BY_THE_RETRY`) is not
    logged on its own: :func:`_attempts` says it once, as the reason of the retry."""
    filters = [(logging.getLogger(name), _SaidByTheRetry(prefix))
               for name, prefix in RUN_ENDINGS_SAID_BY_THE_RETRY.items()]
    for logger, quiet in filters:
        logger.addFilter(quiet)
    try:
        yield
    finally:
        for logger, quiet in filters:
            logger.removeFilter(quiet)


def _attempts(run: Callable[[], Any], what: str, say: Callable[[str], None],
              reopen: Callable[[], None] | None = None) -> Any:
    """``run()`` (a recording or verification; returns something with ``status`` and
    ``reason``) until it completes, at most :data:`RUN_ATTEMPTS` times, each retry at once;
    InvalidParameterError naming ``what`` and the last reason if none completes. At once: the
    retry's approach brakes the device from where it is (a watchdog zeroed the force: it is
    falling), while left to rest at zero force it lies on its stops, outside the workspace,
    where no run may start. A run that could not start (the device moving too fast to brake)
    counts as one that did not complete. A device error (the driver stopped its I/O: on a busy
    host a USB thread starved past the silence bound) is retried only on a device opened again
    (``reopen()``, e.g. close and open: only that clears the driver's failure); without
    ``reopen`` it ends the command."""
    from falcon_plan.errors import DeviceError, FalconPlanError
    from falcon_plan.execution.executor import ExecutionStatus

    for attempt in range(1, RUN_ATTEMPTS + 1):
        try:
            with _endings_said_by_the_retry():
                result = run()
            if result.status == ExecutionStatus.COMPLETED:
                return result
            status, reason = str(ExecutionStatus(result.status)), result.reason
            device_failed = status == ExecutionStatus.DEVICE_ERROR
        except FalconPlanError as exc:
            status, reason = "not started", str(exc)
            device_failed = isinstance(exc, DeviceError)
        if device_failed and reopen is None:
            break
        if attempt < RUN_ATTEMPTS:
            ended = f"ended {status}" if status != "not started" else "did not start"
            where = "on the device opened again" if device_failed else "from where the device is"
            say(f"retrying {what} (attempt {attempt + 1} of {RUN_ATTEMPTS}) {where}: "
                f"attempt {attempt} {ended} ({reason})")
            if device_failed:
                reopen()
    raise InvalidParameterError(f"{what} ended {status} in {attempt} attempt{'s' if attempt > 1 else ''}: {reason}")


def _reopen(device: Device) -> None:
    """Close ``device`` (zero force by a path that does not depend on a failed I/O thread) and
    open it again: fresh I/O threads on the firmware that runs (a Falcon keeps its firmware,
    and its homing, until it is unplugged: the image is not loaded again)."""
    device.close()
    if getattr(device, "firmware_path", None) is not None:
        device.firmware_path = None
    device.open()


@dataclass(frozen=True)
class VerificationRun:
    """Tracking of the verification chain with one model on the device.

    counts_rms : RMS over legs and samples of measured minus planned counts (each reading
        against the plan at the tick it was read for), from the first move's start to the end
        [counts]; counts_max : its largest absolute value.
    norm_rms_mm, norm_max_mm : of the Cartesian error norm [mm].
    per_move_counts_rms : the same RMS per move (its motion and the hold after it).
    duration_s : total planned motion time [s]; status : the executor's :class:`ExecutionStatus`.
    model : which model planned and ran it ("nominal" or "corrected").
    log_path : the run's falcon log (None if not written); notes : what the run reported
        (e.g. the approach move's length); reason : why a run that did not complete ended.
    rows : every row's error (:class:`~falcon_plan.execution.executor.RowErrors`; None when the
        run sent nothing; not serialised).
    """

    model: str
    counts_rms: float
    counts_max: float
    norm_rms_mm: float
    norm_max_mm: float
    per_move_counts_rms: list[float]
    duration_s: float
    status: ExecutionStatus
    log_path: str | None
    notes: list[str]
    reason: str = ""
    rows: Any = field(default=None, repr=False, compare=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {k: v for k, v in self.__dict__.items() if k != "rows"}


def verification_trajectory(model: FalconModel,
                            points_m: Any = VERIFICATION_POINTS_M) -> tuple[Any, list[float]]:
    """The verification moves through ``points_m`` ((P, 3) points [m], default
    :data:`VERIFICATION_POINTS_M`) planned with ``model`` (minimum time, the planner's fast
    options), joined with :data:`VERIFY_HOLD_S` holds into one trajectory; returns it and the
    start times of the moves [s] (plus its end)."""
    from falcon_plan.approach import concatenate
    from falcon_plan.planning.api import plan
    from falcon_plan.planning.problem import PlanOptions
    from falcon_plan.trajectory import Trajectory

    points = np.asarray(points_m, dtype=float)
    chain, starts = None, []
    for a, b in zip(points[:-1], points[1:]):
        move = plan(a, b, PlanOptions.fast(), model).trajectory
        hold_t = np.array([0.0, VERIFY_HOLD_S])
        rest = np.zeros((2, 3))
        hold = Trajectory(hold_t, np.vstack([b, b]), rest, rest, np.tile(move.commands[-1], (2, 1)),
                          move.params_name, move.source)
        starts.append(0.0 if chain is None else chain.duration_s)
        piece = concatenate(move, hold)
        chain = piece if chain is None else concatenate(chain, piece)
    starts.append(chain.duration_s)
    return chain, starts


def verification_run(device: Device, kind: str, model: FalconModel, label: str, *,
                     log_path: str | Path | None = None, pace: bool = False) -> VerificationRun:
    """Plan the verification chain with ``model`` and execute it on ``device`` (of ``kind``:
    sim, emulated, usb) with ``model``'s feed-forward (approach move first if needed);
    tracking from the first move's start, each row's counts against the reference of the slot
    they were read for (:class:`~falcon_plan.execution.executor.RowErrors`). ``label`` names
    the run in the result, ``log_path`` is where its falcon log goes (None: no log), ``pace``
    runs it against the wall clock."""
    from falcon_plan.approach import run_from_here

    rate = float(device.rate_hz)
    trajectory, starts = verification_trajectory(model)
    report, approach_s = run_from_here(device, kind, trajectory, model, rate_hz=rate, log_path=log_path,
                                       pace=pace, preroll_s=PREROLL_S, settle_s=0.0, controller_kind=CONTROLLER_KIND)
    per_move: list[float] = []
    err_all = np.zeros((0, 3))
    if report.samples and report.rows is not None:
        # each row's counts against the reference of the slot they were read for (a reading
        # from before a host stall is not compared with the reference after it)
        t_motion = report.rows.t_s - PREROLL_S - approach_s  # pre-roll then approach before the chain
        err = report.rows.error_counts
        for a, b in zip(starts[:-1], starts[1:]):
            seg = (t_motion >= a) & (t_motion < b)
            per_move.append(float(np.sqrt(np.mean(err[seg] ** 2))) if seg.any() else math.nan)
        err_all = err[t_motion >= 0.0]
    tr = report.tracking
    counts_rms = float(np.sqrt(np.mean(err_all ** 2))) if err_all.size else \
        (float(np.sqrt(np.mean(np.square(tr.counts_rms)))) if tr else math.nan)
    counts_max = float(np.abs(err_all).max()) if err_all.size else (max(tr.counts_max) if tr else math.nan)
    return VerificationRun(label, counts_rms, counts_max, tr.norm_rms_mm if tr else math.nan,
                           tr.norm_max_mm if tr else math.nan, per_move, starts[-1], report.status,
                           None if log_path is None else str(log_path),
                           unplannable_effect_notes(model.effects, model.params), report.reason, report.rows)


def best_of_runs(runs: list[VerificationRun]) -> VerificationRun:
    """One model's verification over several runs of its chain (:data:`VERIFY_ROUNDS`): per
    move the lowest RMS of the runs, ``counts_rms`` the RMS over the moves of those [counts]
    (equal weight per move); the rest (maximum, Cartesian figures, log, status) of the run
    with the lowest whole-run RMS. Runs without per-move figures (no log): that best run."""
    best = min(runs, key=lambda r: r.counts_rms)
    per_move = [r.per_move_counts_rms for r in runs]
    if not all(per_move) or len({len(m) for m in per_move}) != 1:
        return best
    moves = np.fmin.reduce(np.array(per_move, float), axis=0)
    return dataclasses.replace(best, counts_rms=float(np.sqrt(np.mean(moves ** 2))),
                               per_move_counts_rms=[float(x) for x in moves])


def corrected_model_file(report: Any, model: FalconModel, logs: dict[str, str],
                         source: str = "falcon-plan discrepancy") -> ModelFile:
    """The model file of ``report`` (a :class:`~falcon_plan.discrepancy.workflow.DiscrepancyReport`):
    ``model``'s parameters with the corrected effects, and the provenance (``logs``: their
    roles and paths, the date, named effects, fitted parameters with standard deviations,
    held-out errors, and ``source``: the command that made it). A transport delay the
    workflow fitted and kept (the logs' link, :func:`~falcon_plan.discrepancy.checks.fit_transport_delay`)
    becomes the parameters' ``link_delay_samples`` (the part beyond the device's command
    delay), so that the corrected model's controller leads its feed-forward by the delay the
    logs showed, as ``doctor``'s model file does with the delay it measures."""
    data = report.to_dict()
    params = model.params
    delay_fit = report.settings.get("transport_delay_fit")
    if delay_fit is not None and delay_fit.get("kept"):
        link = max(0.0, float(delay_fit["value"]) - params.command_delay_samples)
        params = params.replace(link_delay_samples=round(link, 3))
    provenance = {
        "source": source, "logs": dict(logs), "effects_named": list(report.effects),
        "parameters": {f: p.to_dict() for f, p in report.parameters.items()},
        "indistinguishable": data.get("indistinguishable", []),
        "heldout_rms_counts": {"nominal": report.heldout_before.rms_counts_all,
                               "corrected": report.heldout_after.rms_counts_all},
        "train_rms_counts": {"nominal": report.train_before.rms_counts_all,
                             "corrected": report.train_after.rms_counts_all},
        "settings": data.get("settings", {}),
        "link_delay_samples": {"before": model.params.link_delay_samples, "after": params.link_delay_samples},
    }
    return ModelFile(FalconModel(params, report.corrected, model.limits), provenance)


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`calibrate` found and measured (see the module docstring).

    ``effects_named`` the names the workflow gave; ``corrected`` the corrected effects
    (``Effects.to_dict()``); ``heldout_rms_counts`` the held-out replay RMS [counts] under the
    nominal and corrected models; ``nominal`` / ``corrected_run`` the verification runs with
    each model; ``timings_s`` the time of each step [s]; ``files`` the paths written, by role;
    ``link_delay_samples`` the link delay of the nominal and the corrected model [periods];
    ``runs_counts_rms`` every verification run's RMS [counts] by model.
    """

    effects_named: list[str]
    corrected: dict[str, Any]
    heldout_rms_counts: dict[str, float]
    nominal: VerificationRun
    corrected_run: VerificationRun
    timings_s: dict[str, float]
    files: dict[str, str]
    link_delay_samples: tuple[float, float] = (0.0, 0.0)
    """The parameters' link delay [periods] of the nominal and of the corrected model (the
    corrected one carries a transport delay fitted on the logs, :func:`corrected_model_file`)."""
    runs_counts_rms: dict[str, list[float]] = field(default_factory=dict)
    """Every verification run's RMS [counts] by model ("nominal", "corrected"), in order
    (``nominal`` and ``corrected_run`` combine each model's runs, :func:`best_of_runs`)."""

    @property
    def improvement(self) -> float:
        """Verification RMS tracking error, nominal over corrected (> 1: the correction helps)."""
        return self.nominal.counts_rms / self.corrected_run.counts_rms

    @property
    def unchanged(self) -> bool:
        """True when the corrected model is the nominal one (no effect, the same link delay)."""
        return not self.corrected and self.link_delay_samples[0] == self.link_delay_samples[1]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {"effects_named": self.effects_named, "corrected_effects": self.corrected,
                "heldout_rms_counts": self.heldout_rms_counts,
                "verification": {"nominal": self.nominal.to_dict(), "corrected": self.corrected_run.to_dict(),
                                 "nominal_over_corrected": self.improvement,
                                 "runs_counts_rms": self.runs_counts_rms},
                "link_delay_samples": {"nominal": self.link_delay_samples[0],
                                       "corrected": self.link_delay_samples[1]},
                "timings_s": self.timings_s, "files": self.files}

    def summary(self) -> str:
        """A few human-readable lines."""
        n, c = self.nominal, self.corrected_run
        # corrected holds the effects that differ from nominal (Effects.to_dict)
        changed = ", ".join(f"{k} {v if isinstance(v, str) else format(v, '.4g')}" for k, v in self.corrected.items())
        return "\n".join([
            f"effects named: {', '.join(self.effects_named)}; corrected model: {changed or 'the nominal one'}",
            f"held-out replay RMS [counts]: {self.heldout_rms_counts['nominal']:.3g} (nominal) -> "
            f"{self.heldout_rms_counts['corrected']:.3g} (corrected)",
            f"verification tracking RMS [counts] under the {CONTROLLER_KIND.upper()} + feed-forward (whose modest "
            f"gains let a model error show; the default LQR hides much of it): {n.counts_rms:.3g} nominal -> "
            f"{c.counts_rms:.3g} corrected "
            f"(max {n.counts_max:.0f} -> {c.counts_max:.0f}; Cartesian RMS {n.norm_rms_mm:.3f} -> "
            f"{c.norm_rms_mm:.3f} mm)" + (
                f"; each move's best of {len(self.runs_counts_rms['nominal'])} runs (whole runs: nominal "
                f"{', '.join(f'{x:.3g}' for x in self.runs_counts_rms['nominal'])}; corrected "
                f"{', '.join(f'{x:.3g}' for x in self.runs_counts_rms['corrected'])})"
                if len(self.runs_counts_rms.get("nominal", ())) > 1 else ""),
            *([f"link delay: {self.link_delay_samples[0]:.2f} -> {self.link_delay_samples[1]:.2f} periods "
               "(fitted on the logs; the corrected model's feed-forward leads by it)"]
              if self.link_delay_samples[1] != self.link_delay_samples[0] else []),
            *[f"note: {x}" for x in c.notes],
            *([f"note: the corrected model is the nominal one: the two verification runs differ by "
               f"the run-to-run spread on this machine ({n.counts_rms:.3g} vs {c.counts_rms:.3g} counts)"]
              if self.unchanged else
              [f"warning: the corrected model tracks worse than the nominal one in the verification "
               f"(RMS {c.counts_rms:.3g} vs {n.counts_rms:.3g} counts): keep the nominal model"]
              if self.improvement < 1.0 else []),
            f"model: {self.files['model']}  plot: {self.files['plot']}"])


def calibrate(device: Device, kind: str, out_dir: str | Path, *, model: FalconModel | None = None,
              duration_s: float = 8.0, seed: int = 0, train_kind: str = "mixed",
              heldout_kind: str = "fourier", pace: bool = False,
              candidates: list[str] | None = None, log_format: str = "csv",
              progress: Callable[[str], None] | None = None) -> CalibrationResult:
    """Run the whole loop (module docstring) on the open ``device`` (of ``kind``: sim,
    emulated, usb), writing into ``out_dir``. ``model`` is the starting (nominal) model.

    ``duration_s`` [s] is the length of each excitation, ``train_kind`` / ``heldout_kind``
    their designs (see :func:`~falcon_plan.discrepancy.excitation.design_trajectory`) and
    ``seed`` their random seed (the held-out one uses seed + 1); ``pace`` runs against the
    wall clock; ``candidates`` restricts the effects considered (default all); ``log_format``
    is "csv" (falcon logs) or "mcap" (MCAP recordings) for the four runs' records;
    ``progress``, if given, is told each step as it starts (one line of text).
    """
    from falcon_plan.discrepancy.excitation import design_trajectory
    from falcon_plan.discrepancy.report import write_report
    from falcon_plan.discrepancy.workflow import find_discrepancy
    from falcon_plan.approach import run_from_here
    from falcon_plan.falconlog import read_log

    if log_format not in ("csv", "mcap"):
        raise InvalidParameterError(f"log_format must be 'csv' or 'mcap', got {log_format!r}")
    say = progress or (lambda _text: None)
    model = model or FalconModel()
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InvalidParameterError(f"cannot create the output folder {out}: {exc.strerror}") from None
    rate = float(device.rate_hz)
    timings: dict[str, float] = {}
    files = {name: str(out / f"{name}.{log_format}") for name in ("train", "heldout", "verify_nominal", "verify_corrected")}

    t0 = time.perf_counter()
    for name, exc_kind, exc_seed in (("train", train_kind, seed), ("heldout", heldout_kind, seed + 1)):
        say(f"recording the {'training' if name == 'train' else 'held-out'} excitation ({exc_kind}, "
            f"{duration_s:g} s) -> {files[name]}")
        excitation = design_trajectory(exc_kind, duration_s, exc_seed, rate)
        _attempts(lambda: run_from_here(device, kind, excitation, model, rate_hz=rate, log_path=files[name],
                                        pace=pace, controller_kind=CONTROLLER_KIND)[0],
                  f"recording the {name} excitation", say, lambda: _reopen(device))
    timings["record_s"] = time.perf_counter() - t0

    say("identifying what the model misses (replays and fits of every candidate effect; 5-45 s)")
    t0 = time.perf_counter()
    report = find_discrepancy(read_log(files["train"]), read_log(files["heldout"]), model=model,
                              candidates=candidates)
    timings["identify_s"] = time.perf_counter() - t0
    write_report(report, out / "discrepancy", plots=True)
    model_file = corrected_model_file(report, model, {"train": files["train"], "heldout": files["heldout"]},
                                      source="falcon-plan calibrate")
    files["model"] = str(save_model(out / "model.json", model_file.model, model_file.provenance))

    say(f"effects named: {', '.join(report.effects)}; verifying moves with the nominal and the corrected "
        f"model, {VERIFY_ROUNDS} runs each")
    t0 = time.perf_counter()
    runs: dict[str, list[VerificationRun]] = {"nominal": [], "corrected": []}
    for round_ in range(1, VERIFY_ROUNDS + 1):
        for label, run_model in (("nominal", model), ("corrected", model_file.model)):
            key = f"verify_{label}" if round_ == 1 else f"verify_{label}_{round_}"
            files[key] = str(out / f"{key}.{log_format}")
            say(f"verifying with the {label} model (run {round_} of {VERIFY_ROUNDS}) -> {files[key]}")
            runs[label].append(_attempts(
                lambda: verification_run(device, kind, run_model, label, log_path=files[key], pace=pace),
                f"verifying with the {label} model", say, lambda: _reopen(device)))
    nominal, corrected = (best_of_runs(runs[label]) for label in ("nominal", "corrected"))
    timings["verify_s"] = time.perf_counter() - t0
    files["plot"] = str(out / "calibration.png")
    result = CalibrationResult(list(report.effects), report.corrected.to_dict(),
                               {"nominal": report.heldout_before.rms_counts_all,
                                "corrected": report.heldout_after.rms_counts_all},
                               nominal, corrected, timings, files,
                               (model.params.link_delay_samples, model_file.model.params.link_delay_samples),
                               {label: [r.counts_rms for r in rs] for label, rs in runs.items()})
    plot_calibration(result, files["plot"])
    write_text(out / "calibration.json", json.dumps(result.to_dict(), indent=2) + "\n", "calibration summary")
    files["summary"] = str(out / "calibration.json")
    return result


def plot_calibration(result: CalibrationResult, path: str | Path) -> None:
    """Plot ``result``: the tracking error (measured minus planned counts, per leg) of the
    verification chain with the nominal and the corrected model, and the RMS per move; a PNG
    written to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(11, 8.5))
    runs = (result.nominal, result.corrected_run)
    for ax, run in zip(axes[:2], runs):
        if run.rows is None:
            continue
        for leg in range(3):
            ax.plot(run.rows.t_s, run.rows.error_counts[:, leg], lw=0.7, label=f"leg {leg}")
        ax.set_ylabel("counts - plan")
        ax.set_title(f"{run.model} model: tracking RMS {run.counts_rms:.2f} counts, max {run.counts_max:.0f}"
                     f" (Cartesian RMS {run.norm_rms_mm:.3f} mm)")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    axes[1].set_xlabel("log time [s] (pre-roll, approach, then the moves)")
    lim = max(abs(np.array(axes[0].get_ylim())).max(), abs(np.array(axes[1].get_ylim())).max())
    for ax in axes[:2]:
        ax.set_ylim(-lim, lim)
    moves = np.arange(len(runs[0].per_move_counts_rms))
    axes[2].bar(moves - 0.2, runs[0].per_move_counts_rms, 0.4, label="nominal model")
    axes[2].bar(moves + 0.2, runs[1].per_move_counts_rms, 0.4, label="corrected model")
    axes[2].set_xticks(moves, [f"move {i + 1}" for i in moves])
    axes[2].set_ylabel("RMS [counts]")
    axes[2].set_title(f"per verification move; effects named: {', '.join(result.effects_named)}")
    axes[2].legend(fontsize=8)
    axes[2].grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


__all__ = ["calibrate", "CalibrationResult", "VerificationRun", "verification_run",
           "verification_trajectory", "corrected_model_file", "plot_calibration", "VERIFICATION_POINTS_M"]
