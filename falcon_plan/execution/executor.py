"""The executor: streams a Trajectory to a device at the device's rate and measures tracking.

Per tick k (slot time t_k = k / rate, from 0):

1. the reading of the previous exchange gives the counts n_k (read at t_k);
2. the workspace guard takes n_k to the measured position (warm-started forward kinematics)
   and stops if it left the workspace;
3. the command is the controller's (:class:`falcon_plan.control.Controller`, one value shared
   with the simulated experiments, the discrepancy replay and the planner's plant check),
   through its per-tick law (:meth:`Controller.tracker`) built from the whole reference before
   the run. By default the time-varying LQR of :mod:`falcon_plan.lqr`: the model's
   feed-forward (inverse dynamics of the reference over the period the command will act on,
   the command delay ahead) plus gains designed along the reference, on an observer's
   estimate of the deviation (position, count rate, an input disturbance) that knows the
   commands in flight. ``controller_kind="pd"`` gives the PD::

       Tc_k = round(kp (n_k - ref_k) + kd v_k + u_k)     clamped to +-limit

   ref_k are the plan's counts at t_k; v_k the measured count rate, first difference through
   the conventions' 50 Hz first-order low-pass; u_k the open-loop offset (:meth:`Controller.offsets`):
   the feed-forward minus kd v_ref, so that the D term damps the velocity error. Both depend
   only on the reference (logged) and the model (named in the log's metadata), so a replay
   reproduces the commands exactly;
4. at the tick's absolute deadline (see :mod:`falcon_plan.timing`) the command is
   sent and the next reading returned (I/O right at the deadline, computation after it);
5. the row (t_k, n_k, Tc_k, ref_k) goes to the falcon log as soon as Tc_k was sent, so the
   log is complete up to the last command even when the run is cut short. A paced run also
   logs what really happened (:class:`~falcon_plan.falconlog.TickTiming`): when Tc_k was
   handed to the driver, when the reading of n_k arrived (host monotonic clock, us) and the
   slots skipped before the row, so that a replay can hold each command as long as it acted.

Before the trajectory the start is held for ``preroll_s``, after it the goal for
``settle_s`` (gravity feed-forward). A cancel brakes to rest within the command limit and
holds there (:mod:`falcon_plan.execution.braking`; ``release=True``: zero force at once),
from the first deadline after it arrives (a paced loop's wait for a deadline wakes at the
cancel, so that the tick's command is the brake's): the loop follows the stop's first commands
made with the plan and takes the rest from a worker (it never computes a brake itself); a
new plan made while the run goes can take over at a tick (:meth:`Executor.prepare_splice`).
On every exit the device gets zero force (:mod:`falcon_plan.execution.safety`).

A tick that starts more than one period late skips to the current slot (the reference keeps
wall-clock time; the log shows a gap). On real hardware that is right; the emulated Falcon
steps its plant once per packet, so there a skipped slot is time the plant never lives
through and its tracking suffers (compare runs paced on a quiet machine only).

Tracking error is measured on every logged row from the start of the motion: per leg in counts (n_k - ref_k) and in
Cartesian space, forward kinematics of n_k against the planned position at t_k [mm].
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from falcon_plan.errors import DeviceError, InvalidParameterError, SafetyStop
from falcon_plan.falconlog import DEVICE_CLOCK_KEY, INTERRUPTED, LINK_DELAY_KEY, ZERO_FORCE_KEY, TickTiming
from falcon_plan.control import DEFAULT_VELOCITY_CUTOFF_HZ
from falcon_plan.control import Controller, link_delay_samples
from falcon_plan.execution.braking import Brake, FirstCommands, StopStart, stop_commands
from falcon_plan.execution.force_loop import ForceLoop
from falcon_plan.execution.schedule import RunSchedule, SpliceOffer, SpliceSlot, held
from falcon_plan.execution.splice import (BRAKE_BUDGET_S, STOP_BUDGET_S, JobThread, LatencyBudget, finish_stop,
                                          refine_brake, stop_offer, warm_stop)
from falcon_plan.execution.safety import MAX_LEG_SPEED_RAD_S, SafetyConfig, require_homed, require_near_start
from falcon_plan.timing import (ARRIVAL_LEAD_S, ARRIVAL_LOCK_READINGS, DEFAULT_SPIN_S, DeadlineTimer,
                                TimingSummary, gc_paused, realtime_section)
from falcon_plan.model.kinematics import angles_to_counts, inverse_kinematics
from falcon_plan.model.workspace import require_in_workspace
from falcon_plan.trajectory import Trajectory

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device, DeviceReading
    from falcon_plan.execution.holding import HoldLoop
    from falcon_plan.falconlog import LogWriter
    from falcon_plan.model.dynamics import FalconModel

log = logging.getLogger(__name__)

class ExecutionStatus(StrEnum):
    """How a run ended (equal to its string value, which is what JSON and logs carry)."""

    COMPLETED = "completed"
    CANCELLED = "cancelled"
    SAFETY_STOP = "safety_stop"
    DEVICE_ERROR = "device_error"


STATUSES = tuple(s.value for s in ExecutionStatus)
"""Possible :attr:`ExecutionReport.status` values."""


class RowSink(Protocol):
    """Something that follows a run row by row as the falcon log does (an MCAP recorder, a
    live view: :class:`falcon_plan.recording.RunRecorder`)."""

    def start(self, meta: dict[str, str], model: FalconModel) -> None:
        """Called once before the first row with the log's metadata ``meta`` and the executor's
        ``model``."""

    def row(self, t_s: float, enc: np.ndarray, tc: np.ndarray, ref: np.ndarray, measured_m: np.ndarray,
            planned_m: np.ndarray, timing: TickTiming | None) -> None:
        """Called once per logged row, from the control loop, with what the falcon log gets
        (``t_s`` [s], counts ``enc``, commands ``tc``, planned counts ``ref``, the tick's
        ``timing`` on paced runs, else None) and the measured and planned end-effector
        positions ``measured_m``, ``planned_m`` [m, base frame]. It must be cheap and must not
        block (hand the row to another thread); the arrays are not changed afterwards."""

    def finish(self, report: ExecutionReport | None) -> None:
        """Called once at the end, on every exit path, with the ``report`` (None when an
        exception ends the run)."""


@dataclass(frozen=True)
class TrackingError:
    """Tracking error over the logged rows from the start of the motion (the pre-roll
    excluded; the settle included): measured minus planned, each row's reading against the
    plan at the tick it was read for (after a host stall, a reading from before it is not
    compared with the plan of the later tick that used it).

    Attributes
    ----------
    counts_rms, counts_max : per leg 0, 1, 2 [counts] (max of the absolute value).
    axis_rms_mm, axis_max_mm : per axis x, y, z of FK(measured counts) - planned position [mm].
    norm_rms_mm, norm_max_mm : of the Cartesian error's Euclidean norm [mm].
    final_mm : Cartesian error norm at the last logged row [mm].
    """

    counts_rms: tuple[float, float, float]
    counts_max: tuple[float, float, float]
    axis_rms_mm: tuple[float, float, float]
    axis_max_mm: tuple[float, float, float]
    norm_rms_mm: float
    norm_max_mm: float
    final_mm: float

    @classmethod
    def from_errors(cls, counts_err: np.ndarray, cart_err_m: np.ndarray) -> "TrackingError | None":
        """From per-row errors, measured minus planned: ``counts_err`` (n, 3) [counts] per leg
        and ``cart_err_m`` (n, 3) [m, base frame]; None when n = 0."""
        if counts_err.shape[0] == 0:
            return None
        mm = cart_err_m * 1e3
        norm = np.linalg.norm(mm, axis=1)
        rms = lambda a: tuple(float(x) for x in np.sqrt(np.mean(a * a, axis=0)))  # noqa: E731
        peak = lambda a: tuple(float(x) for x in np.abs(a).max(axis=0))  # noqa: E731
        return cls(rms(counts_err), peak(counts_err), rms(mm), peak(mm),
                   float(np.sqrt(np.mean(norm * norm))), float(norm.max()), float(norm[-1]))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {"counts_rms": list(self.counts_rms), "counts_max": list(self.counts_max),
                "axis_rms_mm": list(self.axis_rms_mm), "axis_max_mm": list(self.axis_max_mm),
                "norm_rms_mm": self.norm_rms_mm, "norm_max_mm": self.norm_max_mm,
                "final_mm": self.final_mm}


@dataclass(frozen=True)
class RowErrors:
    """Every logged row's tracking error: ``t_s`` (rows,) its slot's time [s, trajectory time,
    as the log's t column]; ``error_counts`` (rows, 3) its counts minus the reference of the
    slot they were read for [counts] (:meth:`_Run._row_errors`)."""

    t_s: np.ndarray
    error_counts: np.ndarray


@dataclass(frozen=True)
class ExecutionReport:
    """What a run did.

    Attributes
    ----------
    status : an :class:`ExecutionStatus` (a plain string is converted).
    reason : why it ended ("" when completed), naming the cause (error type and message).
    samples : commands sent (= rows logged); planned_samples : ticks the run would have had.
    duration_s : loop time covered, last logged slot + 1 period [s] (pre-roll and settle
        included); wall_time_s : wall clock [s].
    rate_hz : loop rate [Hz]; paced : whether the loop slept to wall-clock deadlines.
    tracking : tracking errors (None when no sample was sent).
    timing : missed deadlines and start-error jitter (None when not paced).
    saturated_samples : samples where a command was clamped to the limit.
    log_path : the falcon log written (None if none).
    trajectory_source : the trajectory's ``source``.
    error : the exception that ended the run, if any (not serialised).
    brake : the safe stop spliced in when the run was cancelled (None: none; see
        :mod:`falcon_plan.execution.braking`): its tick, deceleration, the splice's
        discontinuity in position, rate and command, and how long it took to compute.
    splices : every new plan offered while the run went (:meth:`Executor.prepare_splice`):
        its tick, source, whether it was taken (or arrived after its tick: kept the running
        plan), the splice's jumps in position [counts], leg rate [counts/s] and feed-forward
        [command units], and how long preparing it took [ms].
    stop_work_us : after a cancel, the loop's own work on the stop per tick, as (tick, CPU time
        of the loop's thread [us]) for every tick that did any (the look-up of the first
        commands, handing the rest to a worker, taking it over, starting the refinement): the
        loop never computes a brake itself unless the worker missed every tick its first
        commands cover (then that tick shows it).
    rows : every logged row's tracking error (:class:`RowErrors`; not serialised).
    """

    status: ExecutionStatus
    reason: str
    samples: int
    planned_samples: int
    duration_s: float
    wall_time_s: float
    rate_hz: float
    paced: bool
    tracking: TrackingError | None
    timing: TimingSummary | None
    saturated_samples: int
    log_path: str | None
    trajectory_source: str
    error: BaseException | None = field(default=None, compare=False, repr=False)
    brake: Brake | None = field(default=None, compare=False)
    splices: tuple[dict[str, Any], ...] = field(default=(), compare=False)
    stop_work_us: tuple[tuple[int, float], ...] = field(default=(), compare=False)
    rows: RowErrors | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise InvalidParameterError(f"status must be one of {STATUSES}, got {self.status!r}")
        object.__setattr__(self, "status", ExecutionStatus(self.status))

    @property
    def missed_deadlines(self) -> int:
        """Ticks that started more than one period late (0 when not paced)."""
        return self.timing.missed_deadlines if self.timing else 0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (timing flattened: missed_deadlines, jitter_p50/p99/max_us)."""
        timing = self.timing.to_dict() if self.timing else {
            "ticks": self.samples, "missed_deadlines": 0, "skipped_slots": 0, "missed_share": 0.0,
            "jitter_p50_us": None, "jitter_p99_us": None, "jitter_max_us": None,
            "busy_p50_us": None, "busy_p99_us": None, "work_p50_us": None, "work_p99_us": None}
        return {"status": self.status.value, "reason": self.reason, "samples": self.samples,
                "planned_samples": self.planned_samples, "duration_s": self.duration_s,
                "wall_time_s": self.wall_time_s, "rate_hz": self.rate_hz, "paced": self.paced,
                "tracking": self.tracking.to_dict() if self.tracking else None,
                **timing, "saturated_samples": self.saturated_samples,
                "log_path": self.log_path, "trajectory_source": self.trajectory_source,
                "brake": None if self.brake is None else self.brake.to_dict(), "splices": list(self.splices),
                "stop_work_max_us": max((us for _, us in self.stop_work_us), default=None)}

    def summary(self) -> str:
        """A few human-readable lines."""
        lines = [f"status: {self.status}" + (f" ({self.reason})" if self.reason else ""),
                 f"samples: {self.samples}/{self.planned_samples} at {self.rate_hz:g} Hz "
                 f"({self.duration_s:.3f} s, wall {self.wall_time_s:.3f} s)"]
        if self.tracking:
            tr = self.tracking
            lines.append("tracking counts rms/max per leg: "
                         + ", ".join(f"{r:.2f}/{m:.0f}" for r, m in zip(tr.counts_rms, tr.counts_max)))
            lines.append(f"tracking Cartesian |e| rms {tr.norm_rms_mm:.3f} mm, max {tr.norm_max_mm:.3f} mm, "
                         f"final {tr.final_mm:.3f} mm")
        if self.timing:
            tm = self.timing
            jit = ("n/a" if tm.p99_us is None else
                   f"p50 {tm.p50_us:.0f} us, p99 {tm.p99_us:.0f} us, max {tm.max_us:.0f} us")
            stall = "" if not tm.missed_deadlines or tm.longest_late_us is None else \
                f" (the longest {1e-3 * tm.longest_late_us:.1f} ms late: a host stall, not in the jitter)"
            lines.append(f"missed deadlines: {tm.missed_deadlines}/{tm.ticks}{stall}; jitter {jit}")
            if tm.aligned_shift_us is not None:
                lines.append(f"deadlines moved {tm.aligned_shift_us:.0f} us during the hold, onto the phase at which "
                             f"the device's readings arrive (+{ARRIVAL_LEAD_S * 1e6:.0f} us)")
            if tm.busy_p99_us is not None:
                work = ("" if tm.work_p99_us is None else
                        f"; after the device I/O p50 {tm.work_p50_us:.0f} us, p99 {tm.work_p99_us:.0f} us "
                        f"(the loop's own CPU time p50 {tm.work_cpu_p50_us:.0f} us, p99 {tm.work_cpu_p99_us:.0f} us)")
                lines.append(f"loop work per tick: p50 {tm.busy_p50_us:.0f} us, p99 {tm.busy_p99_us:.0f} us{work}")
        if self.saturated_samples:
            lines.append(f"saturated samples: {self.saturated_samples}")
        if self.brake is not None:
            b = self.brake
            lines.append(f"safe stop: braked at {b.deceleration_m_s2:.1f} m/s^2 for {1e3 * b.stop_s:.1f} ms from "
                         f"tick {b.tick} (peak feed-forward {b.peak_feedforward:.0f}, its first command computed in "
                         f"{1e3 * b.compute_s:.2f} ms), then held with gravity compensation")
        if self.log_path:
            lines.append(f"log: {self.log_path}")
        return "\n".join(lines)


class Executor:
    """Streams trajectories to a device under a controller (see the module docstring).

    Parameters
    ----------
    device : an open, homed :class:`~falcon_plan.devices.base.Device`.
    model : FalconModel (parameters for kinematics, workspace limits, feed-forward).
    rate_hz : loop rate [Hz]; default and only allowed value: ``device.rate_hz``.
    log_path : falcon log to write as the run goes (None: no log).
    controller_kind : the controller when ``controller`` is None: "lqr" (default,
        ``Controller.executor_default``) or "pd" (with the fields below).
    kp, kd, velocity_cutoff_hz, derivative_on, feedforward : the PD's fields (see
        :class:`~falcon_plan.control.Controller`), used when ``controller`` is None and
        ``controller_kind`` is "pd"; the command limit is ``safety.command_limit``, the feed-forward
        (and the LQR's design) uses ``model``'s effects.
    feedforward_lead_samples : the command delay the controller assumes [samples, may be
        fractional] (None: the model's, 2 plus a fitted extra delay, plus the link delay
        ``doctor`` measured or else the device's known ``link_delay_s``); used when
        ``controller`` is None.
    controller : the whole controller (its rate must be the device's; its command limit is
        capped by ``safety.command_limit``).
    zero_force_periods_before : zero-force ticks the caller sent just before the run (e.g. a
        position read); the log's ``zero_force_periods_before`` is this plus the executor's own
        first read, so that a replay starts as the run did.
    preroll_s : time to hold the start before the trajectory [s] (default 0.5 s): the loop,
        the velocity filter and the device's command pipeline settle before the motion, whose
        time 0 is at t = preroll_s in the log. (A device that had zero force falls freely for
        the first 2-3 samples; the PD loop, lightly damped, rings from that for ~0.5 s.)
    settle_s : time to hold the goal after the trajectory [s].
    safety : :class:`SafetyConfig` (bounds; the checks always run).
    pace : sleep to wall-clock deadlines. Default True, except for a simulated device (one
        with a ``plant``) that runs as fast as possible (``realtime`` False). A device that
        paces itself (``BaseDevice`` with ``realtime=True``) sleeps inside ``exchange`` too:
        open devices with ``realtime=False`` and let the executor pace (as
        :mod:`~falcon_plan.execution.device_factory` does). A paced run's loop runs at
        real-time priority where the system allows it (:func:`falcon_plan.timing.realtime_priority`).
    spin_s : busy-wait window before each deadline [s].
    progress_period_s : how often ``progress`` is called, in loop time [s].
    sink : a :class:`RowSink` that gets every logged row too (None: none).
    release : what a cancel does: False (default) brakes to rest within the command limit and
        holds there with gravity compensation for max(``settle_s``, :data:`~falcon_plan.execution.braking.STOP_HOLD_S`)
        before the run ends (:mod:`falcon_plan.execution.braking`); True ends the run at once
        with zero force (drops the grip under gravity).
    """

    def __init__(self, device: Device, model: FalconModel, rate_hz: float | None = None,
                 log_path: str | Path | None = None, kp: float = 10.0, kd: float = 0.1, *,
                 velocity_cutoff_hz: float = DEFAULT_VELOCITY_CUTOFF_HZ, derivative_on: str = "error",
                 feedforward: str = "model", feedforward_lead_samples: int | None = None,
                 preroll_s: float = 0.5, settle_s: float = 0.0, safety: SafetyConfig | None = None,
                 pace: bool | None = None, spin_s: float = DEFAULT_SPIN_S,
                 progress_period_s: float = 0.05, controller: Controller | None = None,
                 zero_force_periods_before: int = 0, controller_kind: str = "lqr",
                 sink: RowSink | None = None, release: bool = False) -> None:
        device_rate = float(device.rate_hz)
        rate = device_rate if rate_hz is None else float(rate_hz)
        if not (math.isfinite(rate) and rate > 0):
            raise InvalidParameterError(f"rate_hz must be a positive number, got {rate_hz!r}")
        if abs(rate - device_rate) > 1e-9 * device_rate:
            raise InvalidParameterError(
                f"rate_hz {rate:g} differs from the device's {device_rate:g} Hz: open the device "
                "at the rate you want to run")
        for name, value in (("preroll_s", preroll_s), ("settle_s", settle_s)):
            if not (math.isfinite(value) and value >= 0):
                raise InvalidParameterError(f"{name} must be a finite number >= 0, got {value!r}")
        safety = safety or SafetyConfig()
        if controller is None:
            kind = controller_kind
            if kind == "lqr" and feedforward != "model":
                raise InvalidParameterError(f"the LQR always uses the model's feed-forward, got feedforward={feedforward!r} "
                                            "(controller_kind='pd' runs the PD without it)")
            default = Controller.executor_default(rate, model, kind=kind, delay_samples=feedforward_lead_samples,
                                                  link_delay_s=getattr(device, "link_delay_s", 0.0))
            if kind == "pd":
                controller = Controller(rate, kp, kd, derivative_on, velocity_cutoff_hz, feedforward,
                                        default.feedforward_lead_samples, safety.command_limit, model.effects)
            else:
                controller = default
        elif abs(controller.rate_hz - rate) > 1e-9 * rate:
            raise InvalidParameterError(f"the controller runs at {controller.rate_hz:g} Hz but the "
                                        f"device at {rate:g} Hz")
        self.controller = controller.replace(
            command_limit=min(controller.command_limit, safety.command_limit))
        self.device = device
        self.model = model
        self.rate_hz = rate
        self.log_path = None if log_path is None else Path(log_path)
        self.preroll_s = float(preroll_s)
        self.approach_s = 0.0
        """The approach move at the head of the trajectory run [s] (set by
        :func:`~falcon_plan.approach.run_from_here`, which then carries the pre-roll's hold in
        the trajectory after it and sets ``preroll_s`` to 0): the log's ``approach_s``, and its
        ``preroll_s`` is that hold."""
        self.settle_s = float(settle_s)
        self.safety = safety
        self.pace = _default_pace(device) if pace is None else bool(pace)
        self.spin_s = float(spin_s)
        self.progress_period_s = float(progress_period_s)
        if isinstance(zero_force_periods_before, bool) or int(zero_force_periods_before) != zero_force_periods_before \
                or zero_force_periods_before < 0:
            raise InvalidParameterError(f"zero_force_periods_before must be a whole number >= 0, got "
                                        f"{zero_force_periods_before!r}")
        self.zero_force_periods_before = int(zero_force_periods_before)
        self._prepared: tuple[tuple[int, float], RunSchedule] | None = None
        self._running: _Run | None = None
        self.sink = sink
        self.release = bool(release)
        self.brake_budget = LatencyBudget(BRAKE_BUDGET_S)
        """The minimum-time brake's measured latency (it takes over from the quick brake after it)."""
        self.stop_budget = LatencyBudget(STOP_BUDGET_S)
        """The measured latency of the rest of the quick brake after a cancel (a worker's, taken
        over from the first commands, :func:`~falcon_plan.execution.splice.finish_stop`)."""

    # --- public -------------------------------------------------------------------------------
    def run(self, trajectory: Trajectory, cancel: threading.Event | None = None,
            progress: Callable[[int, int], None] | None = None, *, motion_start_s: float = 0.0,
            splices: SpliceSlot | None = None, hold: HoldLoop | None = None) -> ExecutionReport:
        """Execute ``trajectory`` (starting at t = 0) and return the report.

        ``cancel`` set mid-run ends it with status "cancelled": from the next command on it
        brakes to rest and holds (or, with ``release``, stops at once); ``progress(done, total)`` is
        called about every ``progress_period_s`` of loop time with sample counts;
        ``motion_start_s`` [s, >= 0] is when, in the trajectory, the motion that the tracking
        error measures starts (e.g. after an approach and a hold; the log's metadata says
        when, ``motion_start_s`` from its first row); ``splices``: where new plans made while
        the run goes arrive (:meth:`prepare_splice`), each taken at its tick; ``hold``: a
        :class:`~falcon_plan.execution.holding.HoldLoop` of this executor holding the device at
        the trajectory's start, which the run takes over at its first tick (its first command
        is the hold's last one, not zero force).

        Raises (before any force is applied)
        ------
        SafetyStop : device not homed, or not at the trajectory's start.
        WorkspaceError : the trajectory leaves the workspace.
        InvalidParameterError : trajectory planned with other parameters than the model.

        A safety stop or device error mid-run returns a report with that status; a
        KeyboardInterrupt or an unexpected error is re-raised, after zero force and closing
        the log.
        """
        if not (math.isfinite(motion_start_s) and 0.0 <= motion_start_s <= trajectory.duration_s):
            raise InvalidParameterError(f"motion_start_s must be in [0, {trajectory.duration_s:g}] s, got {motion_start_s!r}")
        schedule = self.prepare(trajectory, motion_start_s)
        self._prepared = None
        require_homed(self.device)
        paced = self.pace   # a real-time run: high priority, and the GIL handed back to it often
        with realtime_section() if paced else gc_paused():
            self._running = _Run(self, schedule, trajectory.source, cancel, progress, splices, hold)
            try:
                return self._running.execute()
            finally:
                self._running = None

    def running_run(self) -> "_Run | None":
        """The run going now (None between runs): its current tick ``k_now``, its schedule ``s``
        and its controller law ``law`` (for :mod:`falcon_plan.execution.splice`)."""
        return self._running

    def command_lead(self) -> int:
        """The command delay in whole ticks (a new reference takes effect this much after the
        command tick that starts it)."""
        return int(math.ceil(self.controller.feedforward_lead_samples - 1e-9))

    def plan_start_tick(self) -> int:
        """The tick of the run's trajectory's t = 0 (after the pre-roll)."""
        return int(round(self.preroll_s * self.rate_hz))

    def offer_and_wait(self, slot: SpliceSlot, offer: SpliceOffer) -> bool:
        """Hand ``offer`` to the running run through ``slot`` and wait for the loop's answer:
        True when taken at its tick, False when refused or when the run ended before it."""
        run = self._running
        ticks_left = 0 if run is None else max(offer.tick - run.k_now, 0)
        return slot.offer_and_wait(offer, timeout_s=1.0 + 4.0 * ticks_left / self.rate_hz)

    def splice_time_after(self, budget_s: float) -> float:
        """The earliest splice time [s, in the running trajectory's time, on the loop's grid]
        that leaves ``budget_s`` [s] (the measured time to replan and :meth:`prepare_splice`)
        before its commands change: the run's current tick plus the budget in ticks, plus the
        command delay. InvalidParameterError when no run is going or the budget reaches past
        the running plan (then brake or keep the plan)."""
        run = self._running
        if run is None:
            raise InvalidParameterError("no run is going")
        rate = self.rate_hz
        lead = int(math.ceil(self.controller.feedforward_lead_samples - 1e-9))
        k_s = run.k_now + int(math.ceil(max(budget_s, 0.0) * rate)) + 1 + lead
        n_pre = int(round(self.preroll_s * rate))
        if k_s >= run.s.t_s.shape[0] - 1:
            raise InvalidParameterError(f"a splice {budget_s * 1e3:.1f} ms from now is past the running plan")
        return (max(k_s, n_pre + 1) - n_pre) / rate

    def prepare_splice(self, trajectory: Trajectory, splice_s: float, *, full_design: bool = True) -> SpliceOffer:
        """Prepare, off the loop (e.g. in a replanning thread), the switch of the running run to
        ``trajectory``, a plan that starts from the running plan's state at ``splice_s`` [s in
        the running trajectory's time, on the loop's grid] (:func:`falcon_plan.planning.replan.replan`
        makes one): its reference on the loop's grid, then its goal held for ``settle_s``; the
        commands change one command delay earlier, so that the new plan's motion starts at
        ``splice_s``; the controller's gains along it (``full_design``: the LQR's whole design,
        else the goal's stationary gains). Hand it to the run through its :class:`SpliceSlot`."""
        rate = self.rate_hz
        n_pre = self.plan_start_tick()
        k_s = n_pre + int(round(splice_s * rate))
        if abs((k_s - n_pre) / rate - splice_s) > 1e-9:
            raise InvalidParameterError(f"splice_s must be a tick of the running plan (k / {rate:g} s inside it), "
                                        f"got {splice_s!r}")
        return self.prepare_splice_at(trajectory, k_s, full_design=full_design)

    def prepare_splice_at(self, trajectory: Trajectory, k_s: int, *, full_design: bool = True) -> SpliceOffer:
        """:meth:`prepare_splice` with the splice given as the run's tick ``k_s`` where the new
        plan's t = 0 falls (its commands change :meth:`command_lead` ticks earlier);
        ``trajectory`` and ``full_design`` as there."""
        t0 = time.perf_counter()
        run = self._running
        if run is None:
            raise InvalidParameterError("no run is going: a splice is prepared for a running run")
        c, rate = self.controller, self.rate_hz
        lead = self.command_lead()
        s = held(run.s, k_s + lead + 5)   # a tick past the end: the run holds its last point for the splice
        if not 0 < k_s:
            raise InvalidParameterError(f"the splice tick must be inside the running run (k > 0), got {k_s!r}")
        k_c = max(k_s - lead, 0)
        n_new = int(math.ceil(trajectory.duration_s * rate - 1e-9)) + 1 + int(round(self.settle_s * rate))
        pos, vel, _ = self._motion(trajectory, np.arange(n_new) / rate)
        encoder = self.model.effects.encoder_params(self.model.params)
        new_ref = angles_to_counts(inverse_kinematics(pos, self.model.params).theta1, encoder)
        ref_tail = np.concatenate([s.ref_counts[k_c:k_s], new_ref])
        pos_tail = np.concatenate([s.position_m[k_c:k_s], pos])
        from falcon_plan.lqr import model_feedforward
        from falcon_plan.model.kinematics import jacobian

        ff_tail = model_feedforward(ref_tail, self.model, c.feedforward_effects, rate, c.feedforward_lead_samples,
                                    positions_m=pos_tail)
        tail = c.splice_tail(run.law, k_c, ref_tail, ff_tail, self.model, full_design=full_design)
        lo = max(0, k_c - 2)
        old_ff = model_feedforward(s.ref_counts[lo:k_c + lead + 4], self.model, c.feedforward_effects, rate,
                                   c.feedforward_lead_samples, positions_m=s.position_m[lo:k_c + lead + 4])[k_c - lo]
        # the leg rates of the two plans at the splice, each from its own trajectory's velocity
        plan_rate = jacobian(s.position_m[k_s], self.model.params) @ s.velocity_m_s[k_s] * encoder.counts_per_rad
        new_rate = jacobian(pos[0], self.model.params) @ vel[0] * encoder.counts_per_rad
        jumps = (float(np.abs(new_ref[0] - s.ref_counts[k_s]).max()), float(np.abs(new_rate - plan_rate).max()),
                 float(np.abs(ff_tail[0] - old_ff).max()))
        vel_tail = np.concatenate([s.velocity_m_s[k_c:k_s], vel])
        return SpliceOffer(k_c, ref_tail, pos_tail, vel_tail, tail, jumps, trajectory.source, time.perf_counter() - t0)

    def stop_commands(self, offer: SpliceOffer) -> FirstCommands:
        """The stop's first commands along the plan of ``offer`` from its tick on
        (:func:`~falcon_plan.execution.braking.stop_commands`; tens of milliseconds for a plan of
        a second: made off the loop once the run took it)."""
        c = self.controller
        return stop_commands(offer.ref_counts, offer.position_m, offer.velocity_m_s, offer.tick, self.model,
                             c.feedforward_effects, self.rate_hz, c.feedforward_lead_samples)

    def prepare(self, trajectory: Trajectory, motion_start_s: float = 0.0) -> RunSchedule:
        """Compute everything the run of ``trajectory`` needs before its first tick (the
        reference, the controller's offsets or gain schedule) and keep it for :meth:`run` of the
        same trajectory object and ``motion_start_s`` [s]; a caller that must start the run
        soon after measuring the device (an approach from a moving state) prepares first."""
        key = (id(trajectory), float(motion_start_s))
        if self._prepared is not None and self._prepared[0] == key:
            return self._prepared[1]
        schedule = self._schedule(trajectory, motion_start_s)
        self._prepared = (key, schedule)
        return schedule

    def rehearse(self, trajectory: Trajectory, motion_start_s: float = 0.0) -> None:
        """Prepare the run of ``trajectory`` (its motion from ``motion_start_s`` [s], as for
        :meth:`prepare`) and discard it: the first preparation in a
        process loads the compiled kernels its batches use, builds the forward kinematics and
        serialises kernels for their cache keys, calls that hold the interpreter lock for up to
        15-30 ms each; done before any force (:func:`~falcon_plan.approach.run_from_here`), a
        hold that runs while the real run is prepared then never waits for them."""
        self._schedule(trajectory, motion_start_s)

    # --- helpers ------------------------------------------------------------------------------
    def _schedule(self, trajectory: Trajectory, motion_start_s: float = 0.0) -> RunSchedule:
        params = self.model.params
        if trajectory.params_name != params.name:
            raise InvalidParameterError(
                f"trajectory was planned with parameters {trajectory.params_name!r} but the executor's "
                f"model uses {params.name!r}")
        require_in_workspace(trajectory.position_m, params, self.model.limits, what="trajectory point")
        period = 1.0 / self.rate_hz
        n_pre = int(round(self.preroll_s * self.rate_hz))
        n_traj = int(math.ceil(trajectory.duration_s * self.rate_hz - 1e-9)) + 1
        n_settle = int(round(self.settle_s * self.rate_hz))
        t = np.arange(n_pre + n_traj + n_settle) * period
        pos, vel, _ = self._motion(trajectory, t - n_pre * period)
        theta1 = inverse_kinematics(pos, params).theta1
        # counts from the model's home angle (a fitted encoder offset moves it)
        ref_counts = angles_to_counts(theta1, self.model.effects.encoder_params(params))
        n_motion = n_pre + int(round(motion_start_s * self.rate_hz))
        tracker = self.controller.tracker(ref_counts, self.model, n_motion)
        c = self.controller
        first_brake = stop_commands(ref_counts, pos, vel, 0, self.model, c.feedforward_effects, self.rate_hz,
                                    c.feedforward_lead_samples)
        return RunSchedule(t, pos, ref_counts, tracker, n_motion, vel, first_brake)

    @staticmethod
    def _motion(trajectory: Trajectory, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Planned position, velocity, acceleration at trajectory times t [s] (from 0); before
        the start and after the end: at rest at the first / last point."""
        pos, vel, acc = trajectory.at_time(t + trajectory.t_s[0])
        moving = ((t >= 0.0) & (t <= trajectory.duration_s + 1e-12))[:, None]
        return pos, np.where(moving, vel, 0.0), np.where(moving, acc, 0.0)

    def _meta(self, source: str, held: bool = False) -> dict[str, str]:
        """The falcon log's metadata of a run of ``source``; ``held``: it takes the device over
        from a hold (no zero force before it)."""
        zero_before = 0 if held else 1 + self.zero_force_periods_before
        return {**self.controller.to_meta(), ZERO_FORCE_KEY: str(zero_before), "params": self.model.params.name,
                "trajectory_source": source, "device": type(self.device).__name__,
                "preroll_s": f"{self.preroll_s:g}", "settle_s": f"{self.settle_s:g}", "paced": str(self.pace).lower(),
                DEVICE_CLOCK_KEY: getattr(self.device, "device_clock", "wall"),
                LINK_DELAY_KEY: f"{link_delay_samples(self.model, getattr(self.device, 'link_delay_s', 0.0), self.rate_hz):.4g}",
                "started_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")}


LOG_FLUSH_S = 0.05
"""A run's falcon log goes to the OS every this long of rows [s] (:class:`LogWriter`
``flush_rows``), not every row: each write call let the driver's and an emulated device's
threads take the interpreter lock, and the loop waited for it back (one CPU-stress process
beside a run on the emulated Falcon: the tick's log row took 32 / 108 us p50 / p90 wall time
written per row, 19 / 32 us with the rows kept). A process killed mid-run loses at most this
much of its log, and never leaves half a row."""
ALIGN_SETTLE_TICKS = 100
"""Ticks of the hold that must remain after the grid moved (its one longer tick is a
disturbance the hold settles): with a shorter hold, the grid stays where it started."""
SPLICE_HOLD_S = 2.0
"""A run whose end comes while a new plan for it is under way (its :class:`SpliceSlot` expects
one) holds its last point, up to this long past its own end or past the latest tick a plan was
announced for, whichever is later [s] (:meth:`_Run.hold_end`: new goals that keep coming keep
it going), so the plan can still be spliced in (from rest there)."""
SPLICE_GRACE_S = 0.25
"""A paced run also holds its end while a new plan was under way this recently [s] (goals
streamed at a few hertz: the next one is likely coming)."""


def _at_rest(ref_counts: np.ndarray) -> np.ndarray:
    """Per sample of a reference (K, 3) [counts], whether it is at rest there: equal to both
    neighbours (the ends never count)."""
    step_still = np.all(np.abs(np.diff(ref_counts, axis=0)) <= 1e-9, axis=1)
    rest = np.zeros(ref_counts.shape[0], dtype=bool)
    rest[1:-1] = step_still[:-1] & step_still[1:]
    return rest


def _arrival_s(reading: DeviceReading) -> float:
    """When ``reading`` arrived at the host [s, monotonic]: the driver's own record, else now."""
    return reading.arrived_s if reading.arrived_s is not None else time.monotonic()


def _default_pace(device: Device) -> bool:
    """Pace unless the device is a simulation stepped as fast as possible (real hardware,
    and anything that does not say, is always paced)."""
    return not (hasattr(device, "plant") and getattr(device, "realtime", True) is False)


class _Run:
    """One execution: the loop and its state (built fresh by :meth:`Executor.run`)."""

    def __init__(self, ex: Executor, schedule: RunSchedule, source: str,
                 cancel: threading.Event | None, progress: Callable[[int, int], None] | None,
                 splices: SpliceSlot | None = None, hold: HoldLoop | None = None) -> None:
        self.ex, self.s, self.source, self.hold = ex, schedule, source, hold
        self.cancel, self.progress, self.slot = cancel, progress, splices
        self.splices: list[dict[str, Any]] = []
        self.k_now = 0                 # the tick the loop is at (for splice_time_after)
        self.period_s = 1.0 / ex.rate_hz
        self.law = schedule.tracker
        self._read_for: int | None = None   # the tick the latest reading was read for
        n = schedule.t_s.shape[0]
        # what each logged row measured and sent; errors and saturation are computed at the end
        self.row_slot = np.zeros(n, dtype=np.int64)
        self.row_read_slot = np.zeros(n, dtype=np.int64)   # the slot each row's counts were read for
        self.row_counts = np.zeros((n, 3))
        self.row_position = np.zeros((n, 3))
        self.row_commands = np.zeros((n, 3))
        self.rows = 0
        self.covered_s = 0.0
        # the hold's new readings move the deadline grid onto their arrivals, once
        long_hold = schedule.preroll_samples >= ARRIVAL_LOCK_READINGS + ALIGN_SETTLE_TICKS
        self.loop = ForceLoop(ex.device, ex.model, ex.safety, ex.rate_hz,
                              timer=DeadlineTimer(ex.rate_hz, ex.spin_s, capacity=n) if ex.pace else None,
                              lock_arrivals=long_hold)
        """The device's force, the guards, the deadlines."""
        self.at_rest = _at_rest(schedule.ref_counts)   # where the arrival lock may move the grid
        # A simulated device run as fast as possible has no wall-clock deadline to miss (its
        # firmware hold counts simulated periods), so the watchdog watches real-time runs only.
        self.watch = ex.pace or _default_pace(ex.device)
        self.brake: Brake | None = None
        self.brake_slot: SpliceSlot | None = None   # where the minimum-time brake arrives
        # the stop's first command sent at a cancel: (tick, the table's row or None, compute time [s])
        self._brake_started: tuple[int, StopStart | None, float] | None = None
        # ... then until the rest is taken, with the schedule it was cancelled on
        self._stop_start: tuple[int, StopStart | None, float, RunSchedule] | None = None
        self._stop_due: int | None = None          # the last tick of the first commands followed
        self.stop_work: dict[int, float] = {}      # the loop's CPU time on the stop per tick [s]
        self._refine_due: int | None = None        # the rest of the stop was taken: refine it from this tick
        # the stop's off-loop jobs after a cancel, on a thread started now (not at the cancel),
        # its first job a stop computed once (first calls in a process are slow)
        self.jobs = JobThread("falcon-plan stop") if cancel is not None and not ex.release else None
        if self.jobs is not None:
            self.jobs.submit("warm-up", lambda: warm_stop(ex, schedule))
        # the stop's first commands made with each plan followed, latest start first (each for its ticks)
        self.first_brakes: list[FirstCommands] = [] if schedule.first_brake is None else [schedule.first_brake]
        self._tables = threading.Lock()            # first_brakes: the loop's splices, a worker's new table
        self._table_done: threading.Event | None = None   # set when the last spliced plan's table is in
        self.n_planned = n                           # ticks of the plan followed now (holds for a splice not counted)
        self._before = (self.loop.guard.state(), self.law.state())

    def _command(self, k: int, counts: np.ndarray, t_s: float, slots: int) -> tuple[np.ndarray, np.ndarray]:
        """Measured position [m] and clamped command for slot k from the latest counts, read
        at device time ``t_s`` [s]; ``slots`` periods separate the exchanges that read them
        and the previous counts. The controller state before the update is kept, so that a
        missed deadline can recompute the command for a later slot from the same counts
        (:meth:`_redo`)."""
        self._before = (self.loop.guard.state(), self.law.state())
        fresh = self.loop.guard.fresh(t_s)
        ref = self.s.ref_counts[min(k, self.s.ref_counts.shape[0] - 1)]
        position = self.loop.guard.check(counts, t_s, slots, ref)
        return position, self.law.update(k, counts, slots, fresh, self._read_for)

    def _redo(self, k: int, counts: np.ndarray, t_s: float, slots: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_command` again for slot k, from the state before the last one."""
        guard, state = self._before
        self.loop.guard.restore(guard)
        self.law.restore(state)
        return self._command(k, counts, t_s, slots)

    def execute(self) -> ExecutionReport:
        ex, s = self.ex, self.s
        n = s.t_s.shape[0]
        status, reason, error = ExecutionStatus.COMPLETED, "", None
        wall0 = time.perf_counter()
        writer: LogWriter | None = None
        meta = {**ex._meta(self.source, held=self.hold is not None), "motion_start_s": f"{s.motion_start_s:g}"}
        if ex.approach_s > 0.0:   # the hold before the motion is inside the trajectory, after the approach
            meta.update(approach_s=f"{ex.approach_s:g}", preroll_s=f"{max(s.motion_start_s - ex.approach_s, 0.0):g}")
        if ex.log_path is not None:
            from falcon_plan.falconlog import LogWriter

            writer = LogWriter(ex.log_path, meta, with_ref=True, with_timing=self.loop.timer is not None,
                               flush_rows=max(1, int(round(LOG_FLUSH_S * ex.rate_hz))))
        if ex.sink is not None:
            ex.sink.start(meta, ex.model)
        try:  # before any force of the run's own: a failure here is raised, not reported
            # zero force, or the command a hold applies now (it stops after its current tick)
            first = np.zeros(3) if self.hold is None else self.hold.release()
            t_init = time.perf_counter()
            reading, start = self.loop.first(first)
            read_s = _arrival_s(reading)
            counts, t_read = np.asarray(reading.counts, dtype=float), reading.t_s
            self.law.start(counts, first)
            require_near_start(start, s.position_m[0], ex.safety.max_start_error_m)
            position, tc = self._command(0, counts, t_read, 1)
        except BaseException:
            self._finish()
            self._close_log(writer, INTERRUPTED)
            self._end_sink(None)
            raise
        interrupted = False
        try:
            # the first deadline one period after the initial read (a self-pacing device's own grid), plus 0.1 ms
            self.loop.begin(max(time.perf_counter(), t_init + self.period_s) + 1e-4, watch=self.watch)
            progress_every = max(1, int(round(ex.progress_period_s * ex.rate_hz)))
            k, gap = 0, 1   # the initial read counts as slot -1 (the loop's last_slot)
            hold_step = max(1, int(0.02 * ex.rate_hz))  # ticks a hold for a splice grows by (more than a skip)
            while k < n:
                self.k_now = k
                if k >= n - hold_step and status != ExecutionStatus.CANCELLED and self._awaits_plan(n):
                    n = self._hold_on(n + hold_step)  # a new plan is on its way: hold the end until it arrives
                if self.cancel is not None and self.cancel.is_set() and status != ExecutionStatus.CANCELLED:
                    reason = f"cancelled after {self.rows} of the {n} planned samples" + (
                        "" if ex.release else "; then braked to rest and held")
                    status = ExecutionStatus.CANCELLED
                    if ex.release:
                        break
                    with self._stop_work(k):
                        self._brake(k)   # command k brakes; the rest off the loop once it is sent
                    position, tc = self._redo(k, counts, t_read, gap)
                elif (slot := self.brake_slot if status == ExecutionStatus.CANCELLED else self.slot) is not None:
                    if not ex.pace:
                        slot.wait_for(k)
                    due, missed = slot.take(k)
                    if missed is not None and missed.brake is None:
                        self.splices.append(self._splice_record(missed, taken=False))
                    if due is None and self._stop_due is not None and k >= self._stop_due:
                        due = self._stop_late(k)      # the worker missed every first command: here
                    if due is not None:
                        with self._stop_work(k) if status == ExecutionStatus.CANCELLED else contextlib.nullcontext():
                            n = self._splice(due)
                        slot.applied()
                        position, tc = self._redo(k, counts, t_read, gap)
                # a cancel wakes the wait: this tick's command brakes (the top of the loop)
                slot = self.loop.wait(k, wake=self.cancel if status != ExecutionStatus.CANCELLED else None)
                if slot is None:
                    continue
                if slot != k:  # missed deadlines: skip to the current slot
                    if slot >= n and status != ExecutionStatus.CANCELLED and self._awaits_plan(n):
                        n = self._hold_on(slot + hold_step)   # (a stall past the held end)
                    if slot >= n:
                        break
                    position, tc = self._redo(slot, counts, t_read, gap)
                    k = slot
                gap = k - self.loop.last_slot
                reading = self.loop.send(tc, k)
                self._record(writer, k, counts, self.loop.exchange.sent, position, (self.loop.sent_s, read_s, gap - 1))
                if self._brake_started is not None:  # the stop's first command is out: the rest off the loop
                    with self._stop_work(k):
                        n = self._brake_rest()
                elif self._refine_due is not None and k >= self._refine_due:   # the rest is followed: refine it
                    with self._stop_work(k):
                        self._refine()
                if self.progress is not None and self.rows % progress_every == 0:
                    self.progress(self.rows, n)
                k += 1
                fresh = self.loop.guard.fresh(reading.t_s)     # before _command makes it the previous reading
                counts, t_read = np.asarray(reading.counts, dtype=float), reading.t_s
                read_s = _arrival_s(reading)
                self._read_for = self.loop.read_for(read_s)
                if self.loop.arrival_lock is not None and fresh:
                    self.loop.arrival_lock.note(read_s, may_move=k + ALIGN_SETTLE_TICKS <= self.s.preroll_samples,
                                                still=bool(self.at_rest[min(k, self.at_rest.shape[0] - 1)]))
                if k < n:
                    position, tc = self._command(k, counts, t_read, gap)
        except SafetyStop as exc:
            status, reason, error = ExecutionStatus.SAFETY_STOP, f"{type(exc).__name__}: {exc}", exc
        except DeviceError as exc:
            status, reason, error = ExecutionStatus.DEVICE_ERROR, f"{type(exc).__name__}: {exc}", exc
        except BaseException:
            interrupted = True
            self._end_sink(None)
            raise
        finally:
            zero_problem = self._finish()
            if interrupted:   # (the log after zero force)
                self._close_log(writer, INTERRUPTED)
        if zero_problem is not None and status != ExecutionStatus.DEVICE_ERROR:  # a device error says it
            reason = f"{reason}; " if reason else ""
            reason += f"zero force at the end failed: {type(zero_problem).__name__}: {zero_problem}"
            if status in (ExecutionStatus.COMPLETED, ExecutionStatus.CANCELLED):
                status, error = ExecutionStatus.DEVICE_ERROR, zero_problem
        watchdog = self.loop.watchdog
        if watchdog.tripped and status in (ExecutionStatus.COMPLETED, ExecutionStatus.CANCELLED):
            status, reason = ExecutionStatus.SAFETY_STOP, watchdog.reason
        elif watchdog.tripped and status == ExecutionStatus.DEVICE_ERROR:
            reason = f"{reason} (before it, {watchdog.reason})"
        self._close_log(writer, status.value)
        log.info("execution %s after %d samples%s", status, self.rows, f": {reason}" if reason else "")
        errors = self._row_errors()
        report = ExecutionReport(
            status=status, reason=reason, samples=self.rows, planned_samples=n,
            duration_s=self.covered_s, wall_time_s=time.perf_counter() - wall0,
            rate_hz=ex.rate_hz, paced=ex.pace,
            tracking=self._tracking(errors),
            timing=self.loop.timer.summary() if self.loop.timer is not None else None,
            saturated_samples=int(np.any(np.abs(self.row_commands[: self.rows])
                                         >= self.ex.controller.command_limit, axis=1).sum()),
            log_path=None if ex.log_path is None else str(ex.log_path),
            trajectory_source=self.source, error=error, brake=self.brake, splices=tuple(self.splices),
            stop_work_us=tuple((k, 1e6 * t) for k, t in sorted(self.stop_work.items())),
            rows=RowErrors(self.s.t_s[self.row_slot[: self.rows]], errors))
        self._end_sink(report)
        return report

    @contextlib.contextmanager
    def _stop_work(self, k: int) -> Any:
        """Count the CPU time of the loop's thread in the block as work on the stop at tick k
        (:attr:`ExecutionReport.stop_work_us`: the loop's own, not the machine's delays)."""
        t0 = time.thread_time()
        try:
            yield
        finally:
            self.stop_work[k] = self.stop_work.get(k, 0.0) + time.thread_time() - t0

    def _brake(self, k: int) -> None:
        """The safe stop's first command, at command tick k, before it is sent
        (:mod:`falcon_plan.execution.braking`): the table's first commands from tick k
        (:func:`~falcon_plan.execution.braking.first_commands`, made with the plan followed) with
        the controller's current gain (a look-up, a few tens of microseconds); when its row is
        not within the bound, the plan goes on. Once it is sent, :meth:`_brake_rest`."""
        ex = self.ex
        c = ex.controller
        if not ex.pace and self._table_done is not None:   # a simulation: as if the last splice's table were in
            self._table_done.wait(10.0)
        t0 = time.perf_counter()
        table = next((t for t in self.first_brakes if t.ticks.start <= k), None)
        row = None if table is None else table.row(k)
        if row is not None:
            c.apply_tail(self.law, k, c.quick_tail(self.law, k, row.ref_counts[:row.exact], row.feedforward, ex.model))
        self._brake_started = (k, row, time.perf_counter() - t0)

    def _brake_rest(self) -> int:
        """After the stop's first command (tick k, :meth:`_brake`) was sent: the run follows the
        table's first commands from k, and a worker computes the rest of the stop
        (:func:`~falcon_plan.execution.splice.finish_stop`), handed over through ``brake_slot``
        at a tick after its measured latency, before the first commands run out (from the plan
        when no row was within); returns the run's new number of ticks."""
        k, row, first_s = self._brake_started
        self._brake_started, self._stop_start = None, (k, row, first_s, self.s)
        n = self.s.t_s.shape[0]
        if row is not None:
            e = row.exact
            n = self._follow(k, row.position_m[:e], row.ref_counts[:e], row.velocity_m_s[:e])
            self._stop_due = k + e - 1
        self.brake_slot = SpliceSlot()
        finish_stop(self.ex, self._stop_start[3], k, row, self.brake_slot, self.ex.stop_budget)
        return n

    def _stop_late(self, k: int) -> SpliceOffer | None:
        """The rest of the stop from tick k computed in the loop: the worker missed every tick
        of the first commands (a stalled machine; logged)."""
        tick, row, _, before = self._stop_start
        self._stop_due = None
        log.warning("cancel at tick %d: the rest of the stop computed in the loop at tick %d (the worker was late)",
                    tick, k)
        with self._stop_work(k):
            return stop_offer(self.ex, before, tick, row, k)

    def _awaits_plan(self, n: int) -> bool:
        """Whether the run, ``n`` ticks long now, holds its end on for a new plan on its way."""
        return (self.slot is not None and self.slot.expecting(SPLICE_GRACE_S if self.ex.pace else 0.0)
                and n < self.hold_end())

    def hold_end(self) -> int:
        """The tick up to which the run may hold its end for a new plan (:data:`SPLICE_HOLD_S`)."""
        latest = self.slot.latest_tick if self.slot is not None else 0
        return max(self.n_planned, latest) + int(SPLICE_HOLD_S * self.ex.rate_hz)

    def _hold_on(self, n_new: int) -> int:
        """Hold the run's last point up to ``n_new`` ticks (its end holds still already); ``n_new``."""
        self.s = held(self.s, n_new)
        self._grow(n_new)
        return n_new

    def _follow(self, k: int, position_m: np.ndarray, ref_counts: np.ndarray, velocity_m_s: np.ndarray) -> int:
        """Replace the run's reference from tick k on by ``ref_counts`` (m, 3) [counts] with its
        points ``position_m`` [m] and velocities ``velocity_m_s`` [m/s]; the new number of ticks."""
        s = self.s
        n_new = k + ref_counts.shape[0]
        self.s = RunSchedule(np.arange(n_new) / self.ex.rate_hz, np.concatenate([s.position_m[:k], position_m]),
                           np.concatenate([s.ref_counts[:k], ref_counts]), s.tracker, min(s.preroll_samples, n_new),
                           np.concatenate([s.velocity_m_s[:k], velocity_m_s]))
        self._grow(n_new)
        self.n_planned = n_new
        # the tables made for the reference before k hold for the ticks before k only
        with self._tables:
            self.first_brakes = [t for t in (t.after(k) for t in self.first_brakes) if len(t.ticks)]
        return n_new

    def _add_first_brake(self, table: FirstCommands) -> None:
        """Add the stop's first commands ``table`` made (off the loop) for a plan spliced in at
        its first tick, for its ticks before any later splice."""
        with self._tables:
            later = [t.ticks.start for t in self.first_brakes if t.ticks.start > table.ticks.start]
            table = table.after(min(later)) if later else table
            self.first_brakes = sorted([*self.first_brakes, table], key=lambda t: -t.ticks.start)

    def _splice(self, offer: SpliceOffer) -> int:
        """Follow ``offer`` from its tick on (the reference, the controller); the run's new length.
        The rest of a stop (``offer.brake``) is the report's brake, not a splice: once it is
        followed, the minimum-time brake is made off the loop
        (:func:`~falcon_plan.execution.splice.refine_brake`, taken at its tick through a new
        ``brake_slot``)."""
        self.ex.controller.apply_tail(self.law, offer.tick, offer.tail)
        n_new = self._follow(offer.tick, offer.position_m, offer.ref_counts, offer.velocity_m_s)
        if offer.brake is None:
            self.splices.append(self._splice_record(offer, taken=True))
            if self.jobs is not None:   # a cancel may come: the stop's first commands along it, off the loop
                done = self._table_done = threading.Event()

                def table() -> None:
                    try:
                        self._add_first_brake(self.ex.stop_commands(offer))
                    finally:
                        done.set()

                self.jobs.submit("the stop's first commands", table)
            return n_new
        k, _, first_s, _ = self._stop_start
        self._stop_due = None
        self.brake = dataclasses.replace(offer.brake, compute_s=first_s)
        self._refine_due = offer.tick + 1      # the next tick (the loop's work spread over two ticks)
        return n_new

    def _refine(self) -> None:
        """Start the minimum-time brake off the loop from the stop followed now, taken at its
        tick through a new ``brake_slot`` (:func:`~falcon_plan.execution.splice.refine_brake`)."""
        self._refine_due = None
        log.info("cancel at tick %d: braking at %.1f m/s^2 for %.1f ms (first command in %.3f ms)", self.brake.tick,
                 self.brake.deceleration_m_s2, 1e3 * self.brake.stop_s, 1e3 * self.brake.compute_s)
        self.brake_slot = SpliceSlot()
        refine_brake(self.ex, self.brake, self.brake_slot, self.ex.brake_budget)

    @staticmethod
    def _splice_record(offer: SpliceOffer, taken: bool) -> dict[str, Any]:
        return {"tick": offer.tick, "source": offer.source, "taken": taken,
                "position_jump_counts": offer.jumps[0], "velocity_jump_counts_s": offer.jumps[1],
                "command_jump": offer.jumps[2], "prepare_ms": 1e3 * offer.prepare_s}

    def _grow(self, n_new: int) -> None:
        """Room for ``n_new`` rows."""
        grow = n_new - self.row_slot.shape[0]
        if grow > 0:
            self.row_slot = np.concatenate([self.row_slot, np.zeros(grow, dtype=np.int64)])
            self.row_read_slot = np.concatenate([self.row_read_slot, np.zeros(grow, dtype=np.int64)])
            for name in ("row_counts", "row_position", "row_commands"):
                setattr(self, name, np.concatenate([getattr(self, name), np.zeros((grow, 3))]))

    def _end_sink(self, report: ExecutionReport | None) -> None:
        if self.ex.sink is not None:
            self.ex.sink.finish(report)

    def _record(self, writer: LogWriter | None, k: int, counts: np.ndarray, tc: np.ndarray,
                position: np.ndarray, tick: tuple[float, float, int]) -> None:
        """Log and keep row k (its command was sent); ``tick`` = (when the command was handed
        to the driver [s, monotonic], when the reading of ``counts`` arrived [s], slots
        skipped before the row)."""
        timing = None
        if self.loop.timer is not None and (writer is not None or self.ex.sink is not None):
            timing = TickTiming(int(round(tick[0] * 1e6)), int(round(tick[1] * 1e6)), int(tick[2]))
        if writer is not None:
            writer.write(self.s.t_s[k], counts, tc, self.s.ref_counts[k], timing)
        if self.ex.sink is not None:
            self.ex.sink.row(self.s.t_s[k], counts.astype(np.int64), tc, self.s.ref_counts[k], position,
                             self.s.position_m[k], timing)
        row = self.rows
        self.row_slot[row] = k
        self.row_read_slot[row] = k if self._read_for is None or self._read_for < 0 else min(self._read_for, k)
        self.row_counts[row] = counts
        self.row_position[row] = position
        self.row_commands[row] = tc
        self.rows = row + 1
        self.covered_s = self.s.t_s[k] + self.period_s

    def _row_errors(self) -> np.ndarray:
        """Each row's counts minus the reference at the slot they were read for (:attr:`row_read_slot`,
        :meth:`~falcon_plan.timing.HandOvers.reading_tick`) (rows, 3) [counts]: after a host
        stall the counts are a reading from before it, and the reference of the row's own slot,
        later by the stall, would show the motion in between as an error that never was."""
        return self.row_counts[: self.rows] - self.s.ref_counts[self.row_read_slot[: self.rows]]

    def _tracking(self, errors: np.ndarray) -> TrackingError | None:
        """Tracking error of the rows from the start of the motion (see :class:`TrackingError`),
        from ``errors``, :meth:`_row_errors`: each row's counts against the reference of the slot
        they were read for."""
        moving = self.row_slot[: self.rows] >= self.s.preroll_samples
        read = self.row_read_slot[: self.rows][moving]
        return TrackingError.from_errors(errors[moving],
                                         self.row_position[: self.rows][moving] - self.s.position_m[read])

    def _finish(self) -> Exception | None:
        """Stop the stop's worker and end the loop (zero force, :meth:`ForceLoop.end`; never
        raises over the original error); returns why zero force failed (None: it was sent)."""
        if self.jobs is not None:
            self.jobs.close()
        return self.loop.end()

    @staticmethod
    def _close_log(writer: LogWriter | None, end: str) -> None:
        """Close the run's log (if any) with its end line saying how the run ended (``end``:
        a status, or :data:`~falcon_plan.falconlog.INTERRUPTED`), so that a log of a run cut
        short says so."""
        if writer is not None:
            writer.close(end)

