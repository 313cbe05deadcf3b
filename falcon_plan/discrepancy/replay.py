"""Replaying a falcon log through a model.

Two replays:

- :func:`closed_loop_replay`: the simulated plant (:class:`~falcon_plan.sim.plant.SimPlant`,
  any effects) under the log's controller (:class:`~falcon_plan.control.Controller`, read
  from the metadata: the same value the executor or ``experiment synth`` ran, feed-forward
  included) tracking the log's reference, from the log's first pose at rest. Its counts
  against the logged counts are the tracking-replay error (the held-out measure, and the
  criterion for the plant-only effects). For a log whose controller is unknown
  (``--controller open-loop``) the plant plays the logged commands instead.

  Timing (:func:`tick_schedule`): each logged command acts for the time it really acted. Its
  reading arrived at ``read_us`` and it was handed to the driver at ``sent_us`` (the log's
  timing columns; without them, both at the row's slot ``t``); it starts acting a transport
  delay D after it was sent (:func:`transport_delay_samples`, fractional periods) and acts
  until the next command starts (zero-order hold through gaps and jitter, up to the
  firmware's command hold). The plant steps on the nominal grid of periods; the command
  acting in a period is the time average of the commands that acted in it (the motor torque
  is linear in the command), and a reading is the counts of the motor angle interpolated to
  its arrival time. A log on the nominal grid with a whole delay runs the same loop compiled
  (:meth:`~falcon_plan.control.Controller.run_on`; the two agree exactly there).
- :func:`windowed_replay`: open loop over short windows (default 80 ms): the model's forward
  dynamics driven by the logged commands (delayed as the plant delays them), re-initialised at
  every window from the measured state. Shows where and how fast the model drifts from the
  data without the PD hiding it.
"""
from __future__ import annotations

import functools
import math
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Sequence, TypeVar

import numpy as np

from falcon_plan.control import OPEN_LOOP, Controller, EncoderPD
from falcon_plan.discrepancy.motion import MotionEstimate, sample_index
from falcon_plan.errors import FalconPlanError, LogFormatError
from falcon_plan.falconlog import DEVICE_CLOCK_KEY, ZERO_FORCE_KEY, FalconLog, parse_link_delay_samples, parse_rate_hz
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import (angles_to_counts, counts_to_position,
                                           encoder_resolution_m_per_count, jacobian, position_to_counts)
from falcon_plan.sim.equations import BACKLASH_CONTACT_STIFFNESS_NM_RAD, friction_substeps
from falcon_plan.sim.batch import TIMED_LINE
from falcon_plan.sim.plant import SimPlant



def log_controller(log: FalconLog, controller: str | None = None,
                   rate_hz: float | None = None) -> Controller | None:
    """The controller that produced ``log``: from ``controller`` (a ``controller`` metadata
    value, e.g. "pd kp=10 kd=0.1") if given, else from the log's metadata
    (:meth:`Controller.from_meta`); None for ``controller="open-loop"`` (replay the logged
    commands). ``rate_hz`` overrides the log's rate; without either the controller carries
    the default 800 Hz and :func:`closed_loop_replay` sets the rate it replays at. Raises
    :class:`LogFormatError` naming what is missing and the ``--controller`` option."""
    if controller is not None and controller.strip() == OPEN_LOOP:
        return None
    rate = rate_hz if rate_hz is not None else parse_rate_hz(log.meta or {})
    return Controller.from_meta(log.meta or {}, text=controller,
                                rate_hz=rate if rate is not None else Controller.rate_hz)


MOVING_START_COUNTS = 2
"""A log starts moving when some leg's counts change by at least this much between its first
two rows (one count is quantisation)."""
START_FIT_S = 0.15
"""The start velocity of a closed-loop replay is refined on this first stretch of the log [s]."""
START_FIT_STEPS_COUNTS_S = (400.0, 130.0, 45.0)
"""Pattern-search steps of that refinement, per leg [counts/s] (a 3 x 3 x 3 grid each)."""
_START_CACHE: dict[tuple, np.ndarray] = {}
_CACHE_LOCK = threading.Lock()
"""Guards the replay's caches: replays run side by side (:func:`side_by_side`)."""


def initial_state(log: FalconLog, rate_hz: float, params: Any,
                  offset_counts: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A first guess of the replay's start: position [m] of the first row's counts (+
    ``offset_counts`` on every leg, read with the parameter set ``params``) and velocity
    [m/s]: at rest, unless the log starts moving (an unheld device falling before the loop
    caught it), then the first difference of the counts at ``rate_hz`` [Hz]."""
    n0 = np.asarray(log.enc[0], float) + offset_counts
    p0 = counts_to_position(n0, params)
    k = sample_index(log.t_s[:2], rate_hz) if len(log) > 1 else np.zeros(1, int)
    step = np.asarray(log.enc[1], float) - np.asarray(log.enc[0], float) if len(log) > 1 else np.zeros(3)
    if len(log) < 2 or k[1] != 1 or np.abs(step).max() < MOVING_START_COUNTS:
        return p0, np.zeros(3)
    leg_rate = step * rate_hz / params.counts_per_rad
    return p0, np.linalg.solve(jacobian(p0, params), leg_rate)


def zero_force_periods(log: FalconLog) -> int:
    """Periods of zero force just before the log's first row (the executor's first read
    sends zero force; its logs say ``zero_force_periods_before: 1``); 0 if not said."""
    text = (log.meta or {}).get(ZERO_FORCE_KEY, "0")
    try:
        value = int(text)
    except ValueError:
        raise LogFormatError(f"zero_force_periods_before metadata must be a whole number, got {text!r}") from None
    if not 0 <= value <= 1000:
        raise LogFormatError(f"zero_force_periods_before metadata must be in [0, 1000], got {value}")
    return value


def start_velocity(log: FalconLog, model: FalconModel, rate_hz: float, controller: Controller,
                   ref: np.ndarray) -> np.ndarray:
    """The start velocity [m/s] of a log that starts moving: :func:`initial_state`'s guess
    refined so that the nominal closed loop (``model`` without effects) matches the log's first
    :data:`START_FIT_S` best under ``controller`` at ``rate_hz`` [Hz] tracking ``ref`` (the
    reference on the sample grid, (K, 3) counts) (sum of squared count errors; a pattern
    search, the guess itself included, so never worse there). The start state is unknown, not a model parameter: the
    encoder's whole counts give the velocity only to ~1 count per sample, and the quantised
    loop remembers a wrong start for seconds. Cached per log (the workflow replays one log
    many times)."""
    n = min(len(log), max(2, int(round(START_FIT_S * rate_hz))))
    enc = np.asarray(log.enc[:n], float)
    motion_start = motion_start_slot(log, rate_hz)
    key = (enc.tobytes(), ref[:n].tobytes(), rate_hz, controller, model.params, motion_start)
    known = _START_CACHE.get(key)
    if known is not None:
        return known
    p0, v0 = initial_state(log, rate_hz, model.params)
    to_cartesian = np.linalg.inv(jacobian(p0, model.params)) / model.params.counts_per_rad
    plant = SimPlant(model.with_effects(Effects()), rate_hz=rate_hz)

    def mismatch(dv_counts: np.ndarray) -> float:
        plant.reset(p0, v0 + to_cartesian @ dv_counts)
        return float(np.sum((controller.run_on(plant, ref, model, samples=n, motion_start=motion_start).counts
                             - enc) ** 2))

    best_dv, best = np.zeros(3), mismatch(np.zeros(3))
    grid = np.array(np.meshgrid(*[(-1.0, 0.0, 1.0)] * 3, indexing="ij")).reshape(3, -1).T
    for step in START_FIT_STEPS_COUNTS_S:
        centre = best_dv
        for d in grid:
            if not d.any():
                continue
            value = mismatch(centre + step * d)
            if value < best:
                best, best_dv = value, centre + step * d
    velocity = v0 + to_cartesian @ best_dv
    with _CACHE_LOCK:
        if len(_START_CACHE) > 64:
            _START_CACHE.clear()
        _START_CACHE[key] = velocity
    return velocity


FIT_STEP_PHASE_RAD = 1.2
"""Largest phase [rad] of the drive's fastest mode per RK4 substep in the trial replays of a
fit (h omega; e.g. 3 substeps for a backlash contact at 800 Hz, 1 for a 30 N.m/rad cable)."""
CHECK_STEP_PHASE_RAD = 0.8
"""The same for the check replays (held-out error; 3 substeps for a backlash contact at 800 Hz
to 1 kHz). Measured on a 7.6 s busy-host backlash log at 1 kHz: 3 substeps replay it within
0.02 counts RMS of 6 (1.316 against 1.294, held-out 1.424 against 1.426; 2 substeps 1.282 and
1.463: the whole-count replay's chaos), in 133 ms against 580 ms (6 unrolled RK4 substeps
compile to code 4.4 times as slow as 3)."""
CABLE_SUBSTEP_CHOICES = (1, 2, 3, 6)
"""The substep counts used (each is a compiled plant layout, built once per process)."""


def cable_substeps(effects: Effects, model: FalconModel, rate_hz: float, step_phase_rad: float) -> int | None:
    """RK4 substeps per period that keep the cable model's fastest mode (the motor inertia on
    the cable spring, or on the backlash contact when the cable is rigid) at or below
    ``step_phase_rad`` radians of phase per substep, the smallest of
    :data:`CABLE_SUBSTEP_CHOICES` that does (the largest if none); None for a rigid drive.
    ``effects`` the replay's effects, ``model`` the parameter set, ``rate_hz`` the control
    rate [Hz]. (The plant's fixed default, 6, is set for the stiffest case.)"""
    if not (effects.backlash_rad > 0 or math.isfinite(effects.cable_stiffness_Nm_rad)):
        return None
    stiffness = effects.cable_stiffness_Nm_rad
    if not math.isfinite(stiffness):
        stiffness = BACKLASH_CONTACT_STIFFNESS_NM_RAD
    params = model.params
    omega = math.sqrt(stiffness / (params.motor_inertia_kgm2 * params.drive_ratio ** 2))
    needed = omega / (rate_hz * step_phase_rad)
    return next((n for n in CABLE_SUBSTEP_CHOICES if n >= needed), max(CABLE_SUBSTEP_CHOICES))


REPLAY_FAILURES = (FalconPlanError, ArithmeticError, RuntimeError)
"""What a replay raises when the simulated device leaves the workspace or the numbers blow up
under a wrong parameter (the project's errors, arithmetic, a compiled function failing): the
searches score such a replay as as bad as it gets. Anything else (an import, name or type
error) is a bug and propagates."""


TRANSPORT_DELAY_KEY = "transport_delay_samples"
"""Log metadata: the measured delay from handing a command to the driver to its acting on
the motors [control periods, may be fractional, >= 1] (e.g. fitted by the discrepancy
workflow); absent: :func:`nominal_transport_delay`."""
MIN_TRANSPORT_DELAY_SAMPLES = 1.0
"""A command cannot act before the reading it was computed from was taken and the period it
was sent in ended: the replay's delay is at least this [periods]."""


def nominal_transport_delay(log: FalconLog, model: FalconModel) -> float:
    """The delay [control periods, may be fractional] from sending a command to its acting
    that the run logged in ``log`` assumed: ``model``'s command delay plus the USB link's
    delay the log records (:data:`~falcon_plan.falconlog.LINK_DELAY_KEY`: the run's model's
    measured one or its device's known one; in a log without it, ``model``'s
    ``link_delay_samples``). A delay the run knew about is part of the nominal replay, not a
    hidden effect; raises LogFormatError for a bad metadata value."""
    link = parse_link_delay_samples(log.meta or {})
    return float(model.params.command_delay_samples) + float(model.params.link_delay_samples if link is None else link)


def transport_delay_samples(log: FalconLog, effects: Effects, model: FalconModel) -> float:
    """The delay [control periods] from sending a command to its acting in a replay of
    ``log``: the log's :data:`TRANSPORT_DELAY_KEY` metadata if present, else
    :func:`nominal_transport_delay` (from the log's link delay and ``model``'s command delay),
    plus the ``effects``' extra delay. Raises LogFormatError for a bad metadata value."""
    text = (log.meta or {}).get(TRANSPORT_DELAY_KEY)
    base = nominal_transport_delay(log, model)
    if text is not None:
        try:
            base = float(text)
        except ValueError:
            base = math.nan
        if not (math.isfinite(base) and MIN_TRANSPORT_DELAY_SAMPLES <= base <= 100):
            raise LogFormatError(f"{TRANSPORT_DELAY_KEY} metadata must be a number of periods in "
                                 f"[{MIN_TRANSPORT_DELAY_SAMPLES:g}, 100], got {text!r}")
    return base + float(effects.extra_delay_samples)


def with_transport_delay(log: FalconLog, delay_samples: float) -> FalconLog:
    """``log`` with its :data:`TRANSPORT_DELAY_KEY` metadata set to ``delay_samples``
    [control periods] (the same rows)."""
    meta = {**(log.meta or {}), TRANSPORT_DELAY_KEY: f"{float(delay_samples):.4f}"}
    return FalconLog(log.t_s, log.enc, log.tc, log.ref, meta, *log.timing_columns)


def lived_timing(log: FalconLog) -> bool:
    """Whether ``log``'s timing columns say when a device that lives in wall-clock time was
    commanded (not a simulated plant stepped by the loop's ticks or slots: ``device_clock:
    ticks`` or ``slots``)."""
    return log.has_timing and (log.meta or {}).get(DEVICE_CLOCK_KEY) not in ("ticks", "slots")


@dataclass(frozen=True)
class TickSchedule:
    """When each row of a log really ran, in control periods from its first reading.

    ``read`` (N,): when the reading whose counts the row holds arrived; ``sent`` (N,): when
    its command was handed to the driver (>= read); ``slot`` (N,) int: the row's slot on the
    nominal grid (from ``t``; the PD scales its count difference by :attr:`reading_slots`);
    ``timed``: whether the times differ from the slots (from the log's timing columns, or a
    device that stepped one period per tick through skipped slots); ``fresh`` (N,) bool:
    whether the row's reading is a new one, False when the host had no new status by its tick
    and used the previous row's reading again (the same arrival time in the log); ``held``:
    force was held up to the first row (:func:`held_before`), so the first row's command is
    taken to act from the start instead of zero force until it arrives.
    """

    read: np.ndarray
    sent: np.ndarray
    slot: np.ndarray
    timed: bool
    fresh: np.ndarray
    held: bool = False

    @property
    def reading_slots(self) -> np.ndarray:
        """(N,) the slots between the exchanges that returned the readings of each row and of
        the row before, which the executor's PD divides the count difference by: row k's
        reading came back from row k-1's exchange, so slot[k-1] - slot[k-2] (1 for the
        first two rows: the executor's first read counts as slot -1)."""
        steps = np.diff(self.slot, prepend=self.slot[0] - 1)
        return np.concatenate([[1], steps[:-1]]).astype(float)

    @property
    def regular(self) -> bool:
        """True when every row ran on its slot with none skipped (the compiled loop applies)."""
        return (not self.timed) and bool(np.all(np.diff(self.slot) == 1))


def tick_schedule(log: FalconLog, rate_hz: float) -> TickSchedule:
    """The :class:`TickSchedule` of ``log`` at ``rate_hz`` [Hz]: from its timing columns
    (:class:`~falcon_plan.falconlog.TickTiming`) when it has them, else the row slots; for a
    device that stepped one period per tick (``device_clock: ticks`` metadata, the executor's
    on an older simulated plant) the rows are consecutive periods whatever the host's timing;
    for one that lived the loop's slots (``device_clock: slots``) each row acts at its slot."""
    slot = sample_index(log.t_s, rate_hz)
    slot = slot - slot[0]
    held = held_before(log)
    clock = (log.meta or {}).get(DEVICE_CLOCK_KEY)
    gaps = bool(np.any(np.diff(slot) != 1))
    if clock == "ticks":   # the rows are consecutive periods to the device
        rows = np.arange(slot.size, dtype=float)
        return TickSchedule(rows, rows, slot, gaps, np.ones(slot.size, bool), held)
    if clock == "slots":   # each row's command at its slot; its reading from the exchange before
        read = np.concatenate([[0.0], slot[:-1] + 1.0])
        return TickSchedule(read, slot.astype(float), slot, gaps, np.ones(slot.size, bool), held)
    if not log.has_timing:
        return TickSchedule(slot.astype(float), slot.astype(float), slot, False, np.ones(slot.size, bool), held)
    # The replay starts from the first reading; a first command sent much later (the host
    # stalled before its first tick) is taken to follow a reading one period old.
    origin = max(float(log.read_us[0]), float(log.sent_us[0]) - 1e6 / rate_hz)
    sent = np.maximum.accumulate((np.asarray(log.sent_us, float) - origin) * 1e-6 * rate_hz)
    read = np.clip((np.asarray(log.read_us, float) - origin) * 1e-6 * rate_hz, 0.0, sent)
    read_us = np.asarray(log.read_us)
    fresh = np.concatenate([[True], read_us[1:] != read_us[:-1]])
    return TickSchedule(read, sent, slot, True, fresh, held)


def held_before(log: FalconLog) -> bool:
    """Whether force was held on the device up to ``log``'s first row: the executor took the
    device over from a hold (its ``zero_force_periods_before`` metadata is said, and 0), whose
    last command was still acting while the run's first commands travelled to the device.
    A log that does not say so is taken to start after zero force (:func:`zero_force_periods`)."""
    return ZERO_FORCE_KEY in (log.meta or {}) and zero_force_periods(log) == 0


_TIMED_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
"""The inputs of :func:`_timed_inputs` per schedule and delay (the workflow replays a log many times)."""


def _timed_inputs(schedule: TickSchedule, delay: float, hold: float, rate_hz: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The per-period inputs of :meth:`SimPlant.run_timed_pd` for a log's ``schedule``, a
    transport ``delay`` and a command ``hold`` [periods] at ``rate_hz`` [Hz]: (the period
    each row's tick runs in (N,), ticks (J, 4), weights (J, TIMED_LINE)).

    Row k's tick runs in period j_k = ceil(read_k) (one period later if the previous row's
    already took it), reading the counts a share read_k - (j_k - 1) into the period before
    (a row that used the previous row's reading again reads those counts again);
    its command acts from max(sent_k + delay, j_k) until the next row's starts, at most
    ``hold`` periods (then zero force); a period's weights are the shares of it each
    remembered command acted in. With ``schedule.held`` the first row's command acts from
    period 0 (it stands for the hold's last command, which the log does not record: on a
    live nominal log's held-out replay, zero force there instead made the first half second's
    error 4.4 counts RMS, and the whole replay's 1.41 counts instead of 0.79)."""
    n = schedule.read.size
    rows = np.arange(n)
    # each row one period after the previous at least: j_k - k never decreases
    j = np.maximum.accumulate(np.ceil(schedule.read - 1e-9).astype(np.int64) - rows) + rows
    share = np.clip(schedule.read - (j - 1), 0.0, 1.0)
    start = np.maximum(schedule.sent + max(delay, MIN_TRANSPORT_DELAY_SAMPLES), j)
    if schedule.held:
        start[0] = 0.0
    start = np.maximum.accumulate(start)
    end = np.minimum(np.append(start[1:], np.inf), start + hold)
    periods = int(j[-1]) + 1
    ticks = np.zeros((periods, 4))
    ticks[j, 0] = 1.0
    ticks[j, 1] = rate_hz / schedule.reading_slots
    ticks[j, 2] = share
    ticks[j, 3] = schedule.fresh
    ticks[:, 1] = np.where(ticks[:, 0] > 0, ticks[:, 1], rate_hz)
    weights = np.zeros((periods, TIMED_LINE))
    newest = np.searchsorted(j, np.arange(periods), side="right") - 1  # row of line[0] per period
    # every (row k, period p) its command acts in: p from floor(start_k) to the period of end_k
    first = np.floor(start).astype(np.int64)
    last = np.minimum(np.ceil(np.minimum(end, periods)).astype(np.int64) - 1, periods - 1)
    spans = np.maximum(last - first + 1, 0)
    k = np.repeat(rows, spans)
    p = first[k] + np.arange(k.size) - np.repeat(np.cumsum(spans) - spans, spans)
    share_p = np.minimum(end[k], p + 1) - np.maximum(start[k], p)
    m = newest[p] - k
    acts = (share_p > 0) & (m >= 0) & (m < TIMED_LINE)
    weights[p[acts], m[acts]] = share_p[acts]   # (each period and line slot is one row's)
    return j, ticks, weights


def motion_start_slot(log: FalconLog, rate_hz: float) -> int:
    """The slot (from the first row's, at ``rate_hz`` [Hz]) where the motion of the run logged
    in ``log`` started (its ``motion_start_s`` metadata [s]; 0 without it): before it, in the approach
    and the hold, the executor's LQR kept within the device's static limit, and so does a
    replay (:meth:`~falcon_plan.control.Controller.run_on`)."""
    try:
        start_s = float(log.meta.get("motion_start_s", 0.0))
    except (TypeError, ValueError):
        raise LogFormatError(f"motion_start_s metadata must be a number [s], got {log.meta.get('motion_start_s')!r}") from None
    if not (math.isfinite(start_s) and start_s >= 0.0):
        raise LogFormatError(f"motion_start_s metadata must be a finite time >= 0 s, got {start_s!r}")
    return int(round(start_s * rate_hz))


START_TRANSIENT_S = 0.3
"""The first seconds of a replay [s] that the selection's replay criterion leaves out (the
start transient: it depends on how the replay is initialised, not on the effects)."""
STALL_PERIODS = 2.0
"""A host stall: a tick whose command left at least this many periods after the previous
tick's, or whose reading was at least this many periods old when its command left (the
device held a command, or the loop acted on an old reading, for longer than the replay's
timing is known to)."""
STALL_SETTLE_S = 0.1
"""After a host stall, the replay is not judged for this long [s] (about the loop's settling
time: the PD's ringing is near 11 Hz)."""


@dataclass(frozen=True)
class JudgedRows:
    """Which rows of a log a replay criterion judges (:func:`judged_rows`): ``mask`` (N,) bool;
    ``start_s`` the first judged time [s from the first row]; ``stalls`` the host stalls found
    and ``stall_s`` the time their windows leave out [s]."""

    mask: np.ndarray
    start_s: float
    stalls: int
    stall_s: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (the report's settings)."""
        return {"judged_from_s": self.start_s, "host_stalls": self.stalls, "stall_windows_s": self.stall_s,
                "judged_share": float(np.mean(self.mask)) if self.mask.size else 0.0}


SETTLED_MOVE_COUNTS = 2
"""A leg has left the pose the approach put it in once its counts are this far from it."""


def settled_start_s(log: FalconLog, rate_hz: float) -> float:
    """When the replay of ``log`` (at ``rate_hz`` [Hz]) has forgotten its start [s from the
    first row]: the motion's start (``motion_start_s``; the approach and the hold before it),
    at least :data:`START_TRANSIENT_S`, and not before every leg that moves after it has left
    the pose it held there (by :data:`SETTLED_MOVE_COUNTS`; at most half the log). The replay
    starts from the first row at rest and does not know the device's state or its clock's
    phase when the loop took it: on a device in wall-clock time the approach from rest is off
    by a period or so (several counts at full command), which the hold after it rings off
    unless friction holds the leg where the approach left it (anywhere within the band the
    PD's pull cannot break away from) until the motion moves it."""
    t = np.asarray(log.t_s, float) - float(log.t_s[0])
    start = max(START_TRANSIENT_S, motion_start_slot(log, rate_hz) / rate_hz)
    first = int(np.searchsorted(t, start - 1e-9))
    enc = np.asarray(log.enc)
    if first >= len(t):
        return start
    moved = np.abs(enc[first:] - enc[first]) >= SETTLED_MOVE_COUNTS
    left = [first + int(np.argmax(moved[:, leg])) for leg in range(moved.shape[1]) if moved[:, leg].any()]
    return max(start, min(float(t[max(left)]), float(t[-1]) / 2)) if left else start


def judged_rows(log: FalconLog, rate_hz: float, start_s: float = 0.0) -> JudgedRows:
    """The rows of ``log`` (at ``rate_hz`` [Hz]) whose replay error a criterion judges: from
    ``start_s`` [s from the first row] on (the open-world check: :func:`settled_start_s`;
    the selection's replay criterion: past its start transient; the practical gate: all, slop
    shows most where the device starts) and, for a log a real-time host recorded
    (:func:`lived_timing`), not within :data:`STALL_SETTLE_S` after a host stall
    (:data:`STALL_PERIODS`): the replay plays the logged times, but through a stall the
    device's own clock and the reading's age are known only to the frame, and the replay
    follows the device there less well than any effect explains. A log that would lose most of
    its rows to stall windows is judged whole (not by its remnants)."""
    t = np.asarray(log.t_s, float) - float(log.t_s[0])
    mask = t >= start_s - 1e-9
    if not mask[:-1].any():    # a log that ends before its motion: judge its second half
        mask = t >= t[-1] / 2
    stalls, stall_s = 0, 0.0
    if lived_timing(log):
        sent = np.asarray(log.sent_us, float) * 1e-6 * rate_hz
        age = sent - np.asarray(log.read_us, float) * 1e-6 * rate_hz
        stalled = np.concatenate([[False], np.diff(sent) >= STALL_PERIODS]) | (age >= STALL_PERIODS)
        # a stall's window: from its row to STALL_SETTLE_S after it (the last stall of a run decides)
        last = np.maximum.accumulate(np.where(stalled, t, -np.inf))
        near = t - last < STALL_SETTLE_S
        stalls = int(np.sum(stalled & ~np.concatenate([[False], stalled[:-1]])))
        keep = mask & ~near
        if keep.sum() >= mask.sum() / 2:    # a log mostly stalled is judged whole, not by its remnants
            stall_s = float(np.sum(mask & near)) / rate_hz
            mask = keep
    return JudgedRows(mask, float(start_s), stalls, stall_s)


def reference_on_grid(log: FalconLog, slot: np.ndarray) -> np.ndarray:
    """The log's reference (K, 3) [counts] on every slot of the nominal grid from its first row's
    (``slot`` (N,): the rows' slots from 0), through the rows' values, and at skipped slots a
    cubic spline through them: the controller's feed-forward differentiates the reference twice,
    and a straight line over a gap would give it an acceleration impulse at each end that the
    executor, which had the planned reference, never commanded."""
    from scipy.interpolate import CubicSpline

    ref = np.asarray(log.ref, float)
    grid = np.arange(int(slot[-1]) + 1)
    if slot.size == grid.size or slot.size < 4:
        return np.stack([np.interp(grid, slot, ref[:, i]) for i in range(3)], axis=1)
    return CubicSpline(slot, ref, axis=0)(grid)


T = TypeVar("T")
REPLAY_THREADS = 2
"""Threads that run a stage's independent replays side by side (:func:`side_by_side`: a
stage's first trials, a selection round's fits, the check replays; a search's refinement
stays one trial at a time). The compiled plant releases the interpreter lock, so two replays
take about the time of one on two free cores. On the 21 live logs of issue 26 (2-core VM) the
workflow's median fell from 3.23 to 2.88 s (backlash 6.74 to 5.79 s) with the other core
free, and did not change with a CPU-stress process on it (3.36 and 3.13 s): identical
results either way."""
_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()
_IN_POOL = threading.local()


def side_by_side(jobs: Sequence[Callable[[], T]]) -> list[T]:
    """The results of ``jobs`` (independent calls, e.g. closed-loop replays of one log under
    trial effects), in order, run on :data:`REPLAY_THREADS` threads; one at a time when there
    is one job or when called from one of those threads. Each replay builds its own plant
    (its own buffers), so the results are those of running the jobs one by one; the first
    exception of a job is raised (after every job has ended)."""
    global _POOL
    if len(jobs) < 2 or getattr(_IN_POOL, "inside", False):
        return [job() for job in jobs]
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(REPLAY_THREADS, thread_name_prefix="falcon-plan replay")

    def inside(job: Callable[[], T]) -> T:
        _IN_POOL.inside = True
        return job()
    futures = [_POOL.submit(inside, job) for job in jobs]
    errors = [f.exception() for f in futures]
    for error in errors:
        if error is not None:
            raise error
    return [f.result() for f in futures]


def at_points(f: Callable[[float], float], xs: Sequence[float]) -> dict[float, float]:
    """{x: f(x)} for the trial points ``xs`` of a search whose every trial is a replay, the
    trials side by side (:func:`side_by_side`)."""
    return dict(zip(xs, side_by_side([functools.partial(f, x) for x in xs])))


def closed_loop_replay(log: FalconLog, effects: Effects, model: FalconModel, rate_hz: float,
                       controller: Controller | None, compliant_substeps: int | None = None,
                       initial_offset_counts: float = 0.0) -> np.ndarray:
    """Counts (N, 3) of the simulated plant with ``effects`` replaying the log in closed loop
    under ``controller`` (run at ``rate_hz``; its feed-forward uses ``model``'s parameters),
    or, with ``controller`` None, driven open loop by the logged commands.

    The replay starts at the first row's pose, at rest (after the log's
    :func:`zero_force_periods`), or, when the log starts moving, with the velocity of
    :func:`start_velocity` (open loop: :func:`initial_state`'s guess). Each command acts
    for the time it really acted (the module docstring: the log's timing columns, or its
    slots; zero-order hold through skipped slots, a fractional :func:`transport_delay_samples`);
    the result is the counts each row read. Raises LogFormatError if a closed-loop replay has
    no reference. ``compliant_substeps`` overrides the plant's RK4 substeps when the cable model
    is on (fewer make the many trial replays of a fit cheaper; None keeps the plant's
    default; a sharp friction smoothing can raise the count, :func:`friction_substeps`).
    ``initial_offset_counts`` shifts the starting pose by that many counts on every
    leg (to measure how much the replay error changes with sub-count details of the start).
    """
    schedule = tick_schedule(log, rate_hz)
    k = schedule.slot
    delay = transport_delay_samples(log, effects, model)
    compliant = effects.backlash_rad > 0 or math.isfinite(effects.cable_stiffness_Nm_rad)
    substeps = None
    if compliant and compliant_substeps is not None:
        substeps = max(compliant_substeps, friction_substeps(effects, model.params, rate_hz))
    plant = SimPlant(model.with_effects(Effects()), rate_hz=rate_hz, effects=effects, substeps=substeps)
    compiled = schedule.regular and delay == plant.delay_samples
    if controller is None:
        _start(plant, log, rate_hz, model, effects, initial_offset_counts)
        if not compiled:  # the logged commands through the timed loop: no feedback, ff = the command
            pd = Controller(rate_hz, kp=0.0, kd=0.0).pd()
            return _run_timed(plant, schedule, delay, pd, np.zeros((len(log), 3)), np.asarray(log.tc, float))
        # row j holds the counts read at the start of period j: the end of period j - 1
        counts = np.vstack([plant.counts[None, :], plant.run_open_loop(np.asarray(log.tc, float))[:-1]])
        return counts.astype(float)
    if log.ref is None:
        raise LogFormatError("closed-loop replay needs the log's reference (ref0..ref2 columns); "
                             "without it replay the logged commands with --controller open-loop")
    ref = reference_on_grid(log, k)
    controller = controller.replace(rate_hz=rate_hz)
    if not compiled and controller.kind != "pd":
        raise LogFormatError(
            f"this log was run with the {controller.kind.upper()} controller and records its host's timing "
            "(skipped ticks, or a device on wall-clock time); a replay with that timing re-runs the PD law "
            "only: record identification runs with --controller pd (experiment run and calibrate do), or "
            "replay the logged commands with --controller open-loop")
    _start(plant, log, rate_hz, model, effects, initial_offset_counts, controller, ref)
    if not compiled:
        return _run_timed(plant, schedule, delay, controller.pd(), np.asarray(log.ref, float),
                          controller.offsets(ref, model)[k])
    run = controller.run_on(plant, ref, model, motion_start=motion_start_slot(log, rate_hz))
    return run.counts.astype(float)


def _run_timed(plant: SimPlant, schedule: TickSchedule, delay: float, pd: EncoderPD, ref: np.ndarray,
               offsets: np.ndarray) -> np.ndarray:
    """Counts (N, 3) each row read when ``plant`` replays the rows' ticks of ``schedule``
    with the PD ``pd`` tracking the rows' ``ref`` (N, 3) with their open-loop ``offsets``
    (N, 3), the commands acting after ``delay`` periods (:func:`_timed_inputs`)."""
    key = (schedule.read.tobytes(), schedule.sent.tobytes(), schedule.slot.tobytes(), schedule.fresh.tobytes(),
           schedule.held, delay, plant.hold_periods, pd.rate_hz)
    timed = _TIMED_CACHE.get(key)
    if timed is None:
        timed = _timed_inputs(schedule, delay, plant.hold_periods, pd.rate_hz)
        with _CACHE_LOCK:
            if len(_TIMED_CACHE) > 16:
                _TIMED_CACHE.clear()
            _TIMED_CACHE[key] = timed
    j, ticks, weights = timed
    refs = np.zeros((ticks.shape[0], 3))
    ffs = np.zeros_like(refs)
    refs[j], ffs[j] = ref, offsets
    counts, _ = plant.run_timed_pd(pd, ticks, refs, ffs, weights)
    return counts[j]


START_FALL_ITERATIONS = 4
"""Fixed-point steps that place a replay's plant at rest where falling through the log's
zero-force periods brings it to the first row's counts."""


def _start(plant: SimPlant, log: FalconLog, rate_hz: float, model: FalconModel, effects: Effects,
           offset_counts: float, controller: Controller | None = None, ref: np.ndarray | None = None) -> None:
    """Put the replay's plant where the log starts: at rest before the log's zero-force periods
    (where falling through them reaches the first row's counts),
    or, for a log that starts moving, with :func:`start_velocity` (closed loop) or
    :func:`initial_state`'s guess (open loop). Counts are read with ``effects``' encoder
    offset."""
    p0, v0 = initial_state(log, rate_hz, effects.encoder_params(model.params), offset_counts)
    # a hold's force acts until the first command arrives (:func:`held_before`): the first
    # row's command stands for it in the plant's firmware (the timed loop, which bypasses it,
    # does the same in :func:`_timed_inputs`)
    held = np.asarray(log.tc[0], float) if held_before(log) else None
    if v0.any():
        plant.reset(p0, v0 if controller is None else start_velocity(log, model, rate_hz, controller, ref),
                    commands=held)
        return
    # at rest before the zero-force periods, where falling through them ends at the first row
    params = effects.encoder_params(model.params)
    target = np.asarray(log.enc[0], float) + offset_counts
    start = target.copy()
    periods = zero_force_periods(log)

    def fall_from(counts: np.ndarray) -> np.ndarray:
        plant.reset(counts_to_position(counts, params), v0, commands=held)
        for _ in range(periods):
            plant.step([0, 0, 0])
        return angles_to_counts(plant.motor_angle_rad, params)

    for _ in range(START_FALL_ITERATIONS):
        miss = target - fall_from(start)
        if periods == 0 or np.abs(miss).max() < 1e-3:
            break
        start = start + miss
    # a device that rested at whole counts (e.g. at home after homing) is found exactly
    whole = np.floor(start + 0.5)
    if periods and np.array_equal(np.floor(fall_from(whole) + 0.5), target):
        return
    fall_from(start)


@dataclass(frozen=True)
class TrackingError:
    """Replay error against the logged counts, per leg: ``rms_counts`` [counts] and ``rms_mm``
    [mm] (counts times the local effector displacement per count, summed in quadrature over
    the legs' columns)."""

    rms_counts: tuple[float, float, float]
    rms_mm: tuple[float, float, float]

    @property
    def rms_counts_all(self) -> float:
        """RMS over all legs [counts]."""
        return float(math.sqrt(np.mean(np.square(self.rms_counts))))

    @property
    def rms_mm_all(self) -> float:
        """RMS over all legs [mm]."""
        return float(math.sqrt(np.mean(np.square(self.rms_mm))))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {"rms_counts": list(self.rms_counts), "rms_mm": list(self.rms_mm),
                "rms_counts_all": self.rms_counts_all, "rms_mm_all": self.rms_mm_all}


def tracking_error(log: FalconLog, simulated_counts: np.ndarray, model: FalconModel) -> TrackingError:
    """RMS of ``simulated_counts`` (N, 3) minus the counts of ``log`` per leg, in counts and in
    mm at the effector (``model``'s parameter set turns counts into points)."""
    err = np.asarray(simulated_counts, float) - np.asarray(log.enc, float)
    rms = np.sqrt(np.mean(err ** 2, axis=0))
    p = counts_to_position(np.asarray(log.enc, float), model.params)
    mm_per_count = np.linalg.norm(encoder_resolution_m_per_count(p, model.params), axis=-2) * 1e3
    rms_mm = np.sqrt(np.mean((err * mm_per_count) ** 2, axis=0))
    return TrackingError(tuple(float(x) for x in rms), tuple(float(x) for x in rms_mm))


def windowed_replay(motion: MotionEstimate, model: FalconModel, delay_samples: int,
                    window_s: float = 0.08, max_windows: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Open-loop replay over windows (see the module docstring).

    Each of at most ``max_windows`` windows of ``window_s`` [s] starts at a valid sample of
    ``motion`` from the measured (smoothed) state and is driven by the logged commands issued
    ``delay_samples`` periods earlier, held over each period, with RK4 on ``model``'s forward
    dynamics. Returns (start indices (W,), error (W, L, 3) of
    simulated minus measured counts at the window's L samples after the start).
    """
    rate = motion.rate_hz
    h = 1.0 / rate
    length = max(2, int(round(window_s * rate)))
    contiguous = np.concatenate([[0], np.cumsum(np.diff(motion.k) != 1)])
    candidates = [i for i in np.flatnonzero(motion.valid)
                  if i - delay_samples >= 0 and i + length < motion.n
                  and contiguous[i + length] == contiguous[i - delay_samples]]
    if not candidates:
        return np.zeros(0, dtype=int), np.zeros((0, length, 3))
    starts = np.array(candidates[:: max(1, len(candidates) // max_windows)][:max_windows])
    p = motion.position_m[starts].copy()
    v = motion.velocity_m_s[starts].copy()
    params = model.params
    errs = np.zeros((starts.size, length, 3))
    f = model.forward_dynamics
    for j in range(length):
        u = motion.commands[starts + j - delay_samples]
        k1v = f(p, v, u)
        k2v = f(p + 0.5 * h * v, v + 0.5 * h * k1v, u)
        k3v = f(p + 0.5 * h * (v + 0.5 * h * k1v), v + 0.5 * h * k2v, u)
        k4v = f(p + h * (v + 0.5 * h * k2v), v + h * k3v, u)
        p = p + h * v + (h * h / 6.0) * (k1v + k2v + k3v)
        v = v + (h / 6.0) * (k1v + 2 * k2v + 2 * k3v + k4v)
        errs[:, j] = position_to_counts(p, params) - motion.counts[starts + j + 1]
    return starts, errs
