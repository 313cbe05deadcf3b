"""Replaying a falcon log through a model.

Two replays:

- :func:`closed_loop_replay`: the simulated plant (:class:`~falcon_plan.sim.plant.SimPlant`,
  any effects) under the log's controller (:class:`~falcon_plan.control.Controller`, read
  from the metadata: the same value the executor or ``experiment synth`` ran, feed-forward
  included) tracking the log's reference, from the log's first pose at rest. Its counts
  against the logged counts are the tracking-replay error (the held-out measure, and the
  criterion for the plant-only effects). For a log whose controller is unknown
  (``--controller open-loop``) the plant plays the logged commands instead.
- :func:`windowed_replay`: open loop over short windows (default 80 ms): the model's forward
  dynamics driven by the logged commands (delayed as the plant delays them), re-initialised at
  every window from the measured state. Shows where and how fast the model drifts from the
  data without the PD hiding it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.control import OPEN_LOOP, Controller
from falcon_plan.discrepancy.motion import MotionEstimate, sample_index
from falcon_plan.errors import FalconPlanError, LogFormatError
from falcon_plan.falconlog import parse_rate_hz
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import (angles_to_counts, counts_to_position,
                                           encoder_resolution_m_per_count, jacobian, position_to_counts)
from falcon_plan.sim.equations import BACKLASH_CONTACT_STIFFNESS_NM_RAD, friction_substeps
from falcon_plan.sim.plant import SimPlant

if TYPE_CHECKING:
    from falcon_plan.falconlog import FalconLog


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
    text = (log.meta or {}).get("zero_force_periods_before", "0")
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
    key = (enc.tobytes(), ref[:n].tobytes(), rate_hz, controller, model.params)
    if key in _START_CACHE:
        return _START_CACHE[key]
    p0, v0 = initial_state(log, rate_hz, model.params)
    to_cartesian = np.linalg.inv(jacobian(p0, model.params)) / model.params.counts_per_rad
    plant = SimPlant(model.with_effects(Effects()), rate_hz=rate_hz)

    def mismatch(dv_counts: np.ndarray) -> float:
        plant.reset(p0, v0 + to_cartesian @ dv_counts)
        return float(np.sum((controller.run_on(plant, ref, model, samples=n).counts - enc) ** 2))

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
    if len(_START_CACHE) > 64:
        _START_CACHE.clear()
    _START_CACHE[key] = velocity
    return velocity


FIT_STEP_PHASE_RAD = 1.2
"""Largest phase [rad] of the drive's fastest mode per RK4 substep in the trial replays of a
fit (h omega; e.g. 3 substeps for a backlash contact at 800 Hz, 1 for a 30 N.m/rad cable)."""
CHECK_STEP_PHASE_RAD = 0.4
"""The same for the check replays (held-out error; 6 substeps for a backlash contact)."""
CABLE_SUBSTEP_CHOICES = (1, 2, 6)
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


def closed_loop_replay(log: FalconLog, effects: Effects, model: FalconModel, rate_hz: float,
                       controller: Controller | None, compliant_substeps: int | None = None,
                       initial_offset_counts: float = 0.0) -> np.ndarray:
    """Counts (N, 3) of the simulated plant with ``effects`` replaying the log in closed loop
    under ``controller`` (run at ``rate_hz``; its feed-forward uses ``model``'s parameters),
    or, with ``controller`` None, driven open loop by the logged commands.

    The replay starts at the first row's pose, at rest (after the log's
    :func:`zero_force_periods`), or, when the log starts moving, with the velocity of
    :func:`start_velocity` (open loop: :func:`initial_state`'s guess). Lost
    samples are filled by interpolating the reference on the sample grid (open
    loop: no command is issued in a lost sample, the firmware holds the last); the result is
    returned at the logged samples only. Raises LogFormatError if a closed-loop replay has no
    reference. ``compliant_substeps`` overrides the plant's RK4 substeps when the cable model
    is on (fewer make the many trial replays of a fit cheaper; None keeps the plant's
    default; a sharp friction smoothing can raise the count, :func:`friction_substeps`).
    ``initial_offset_counts`` shifts the starting pose by that many counts on every
    leg (to measure how much the replay error changes with sub-count details of the start).
    """
    k = sample_index(log.t_s, rate_hz)
    grid = np.arange(int(k[-1]) + 1)
    compliant = effects.backlash_rad > 0 or math.isfinite(effects.cable_stiffness_Nm_rad)
    substeps = None
    if compliant and compliant_substeps is not None:
        substeps = max(compliant_substeps, friction_substeps(effects, model.params, rate_hz))
    plant = SimPlant(model.with_effects(Effects()), rate_hz=rate_hz, effects=effects, substeps=substeps)
    if controller is None:
        _start(plant, log, rate_hz, model, effects, initial_offset_counts)
        commands = np.full((grid.size, 3), np.nan)
        commands[k] = np.asarray(log.tc, float)
        # row j holds the counts read at the start of period j: the end of period j - 1
        counts = np.vstack([plant.counts[None, :], plant.run_open_loop(commands)[:-1]])
        return counts[k].astype(float)
    if log.ref is None:
        raise LogFormatError("closed-loop replay needs the log's reference (ref0..ref2 columns); "
                             "without it replay the logged commands with --controller open-loop")
    ref = np.stack([np.interp(grid, k, np.asarray(log.ref, float)[:, i]) for i in range(3)], axis=1)
    controller = controller.replace(rate_hz=rate_hz)
    _start(plant, log, rate_hz, model, effects, initial_offset_counts, controller, ref)
    run = controller.run_on(plant, ref, model)
    return run.counts[k].astype(float)


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
    if v0.any():
        plant.reset(p0, v0 if controller is None else start_velocity(log, model, rate_hz, controller, ref))
        return
    # at rest before the zero-force periods, where falling through them ends at the first row
    params = effects.encoder_params(model.params)
    target = np.asarray(log.enc[0], float) + offset_counts
    start = target.copy()
    periods = zero_force_periods(log)

    def fall_from(counts: np.ndarray) -> np.ndarray:
        plant.reset(counts_to_position(counts, params), v0)
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
