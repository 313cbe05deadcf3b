"""The controller: one typed description of the encoder-space loop, run everywhere.

:class:`Controller` (frozen) says everything about the loop that produced a falcon log: rate,
PD gains, the derivative's form, the velocity filter, the feed-forward (mode, lead, and the
effects of the model whose inverse dynamics it uses) and the command limit. The executor, the
simulated experiments (``experiment synth``), the discrepancy replay and the planner's plant
check all run the same value, and it is written into a log's metadata and read back without
loss (:meth:`Controller.to_meta`, :meth:`Controller.from_meta`).

Per period k, with n_k the counts read now and ref_k the setpoint [counts]::

    v_k  += alpha (raw_k - v_k),     raw_k = (n_k - n_{k-1}) * rate,   alpha = 1 - exp(-2 pi f_c / rate)
    Tc_k  = round(kp (n_k - ref_k) + kd v_k + u_k),   clamped to +-limit

(the PD arithmetic is :func:`pd_law`, the same in numpy and in the plant's compiled loop).
u_k is an open-loop offset that depends only on the reference sequence and the model
(:meth:`Controller.offsets`), so a replay recomputes it from the logged reference:

- feed-forward "model": the inverse dynamics of the reference motion over the period
  [k + L, k + L + 1] that the command will act on (L = ``feedforward_lead_samples``; the
  device applies a command 2 samples after it is sent): positions are the forward kinematics
  of the reference counts, the state at the period's midpoint, the velocity its mean and the
  acceleration the centred second difference around it. "none": 0.
- derivative "error": minus kd times the reference's count rate through the same filter, so
  the D term damps the velocity error (v - v_ref); "measurement": kd v alone (the paper's
  form, right for still references).

Sign: a positive Tc drives theta1 down (toward smaller counts), so kp (n - ref) with kp > 0
pushes the leg back toward ref, and kd v with kd > 0 opposes the motion (the paper prints "D
gain -0.1" in its own sign convention). Rounding is half up (floor(x + 0.5)).

Log metadata (``controller`` key, name=number words after ``pd``)::

    pd kp=10 kd=0.1 fc=50 d_on_error=1 ff=1 ff_lead=2 limit=4096

plus ``rate_hz`` and, when ff=1, ``feedforward_effects`` (the Effects JSON of the
feed-forward model, ``{}`` for nominal). The conventions' plain ``pd kp=10 kd=0.1`` reads as
the paper's controller: fc 50 Hz, derivative on the measurement, no feed-forward, limit 4096.

The second kind, ``lqr`` (the executor's default), is the time-varying LQR with an observer of
:mod:`falcon_plan.lqr`, designed from the reference counts and the model whose effects the log
names (``feedforward_effects``), so a replay regenerates its gain schedule exactly::

    lqr e_pos=1.5 e_vel=300 e_u=150 delay=2 limit=4096

(Bryson's rule: position error [counts], count-rate error [counts/s], feedback [command units];
the command delay the design and the feed-forward assume [samples, may be fractional]).
Every kind runs through one per-tick interface, :class:`Tracker` (``start``, ``update``,
``state``/``restore``), made by :meth:`Controller.tracker`.
"""
from __future__ import annotations

import dataclasses
import json
import math
import threading
from dataclasses import dataclass
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from falcon_plan.errors import InvalidParameterError, LogFormatError
from falcon_plan.lqr import LqrWeights
from falcon_plan.model.effects import NOMINAL, Effects
from falcon_plan.model.params import ACRA2009

if TYPE_CHECKING:
    from falcon_plan.lqr import GainSchedule
    from falcon_plan.model.dynamics import FalconModel

@dataclass(frozen=True)
class PDRun:
    """What a closed loop did: per period k, its start time ``t_s`` [s] (K,), the ``counts``
    read at its start and the ``commands`` issued from them [command units] (what a falcon log
    row holds), shapes (K, 3) int64. Made by :meth:`ClosedLoopPlant.run_pd`."""

    t_s: np.ndarray
    counts: np.ndarray
    commands: np.ndarray


class ClosedLoopPlant(Protocol):
    """A plant that runs the encoder PD against itself (the simulated Falcon,
    :class:`falcon_plan.sim.plant.SimPlant`): the controller states what it needs from it
    here, so that the loop's description does not depend on the simulator."""

    rate_hz: float
    dt_s: float
    time_s: float

    def run_pd(self, controller: EncoderPD, ref_counts: Any, feedforward: Any = None) -> PDRun:
        """Run ``controller`` tracking ``ref_counts`` (K, 3) [counts] with ``feedforward``
        (K, 3) [command units] or None from the plant's current state."""
        ...

    def step(self, commands: Any) -> np.ndarray:
        """One period under ``commands`` (3,); returns the counts read at its end (3,)."""
        ...

    @property
    def counts(self) -> np.ndarray:
        """The counts read now (3,)."""
        ...


DEFAULT_KP = 10.0
"""Proportional gain [command units per count]."""
DEFAULT_KD = 0.1
"""Derivative gain [command units per count/s]."""
DEFAULT_VELOCITY_CUTOFF_HZ = 50.0
"""Cut-off of the first-order low-pass on the encoder velocity [Hz]."""
COMMAND_LIMIT = ACRA2009.command_limit
"""|Tc| never exceeds this [command units]: the firmware's range, from the parameter set."""

NUMPY_OPS = SimpleNamespace(floor=np.floor, fmin=np.minimum, fmax=np.maximum)


def velocity_filter_alpha(rate_hz: float, cutoff_hz: float = DEFAULT_VELOCITY_CUTOFF_HZ) -> float:
    """alpha = 1 - exp(-2 pi f_c / rate) of the discrete first-order low-pass sampled at
    ``rate_hz`` [Hz] with cut-off ``cutoff_hz`` = f_c [Hz] (both > 0); alpha is in (0, 1)."""
    return 1.0 - math.exp(-2.0 * math.pi * cutoff_hz / rate_hz)


def low_pass(raw: np.ndarray, alpha: float) -> np.ndarray:
    """The velocity filter run over a whole signal ``raw`` (K, ...) along its first axis, from
    rest: v_k = v_{k-1} + ``alpha`` (raw_k - v_{k-1}), v_{-1} = 0, the update of :func:`pd_law`
    (the loop costs ~1 us a sample; scipy.signal.lfilter would cost its ~0.5 s import)."""
    out = np.empty_like(raw, dtype=float)
    v = np.zeros(raw.shape[1:])
    for k, x in enumerate(raw):
        v = v + alpha * (x - v)
        out[k] = v
    return out


def pd_law(n: Any, n_prev: Any, v_prev: Any, ref: Any, ff: Any, kp: Any, kd: Any, alpha: Any,
           rate_hz: Any, limit: Any, ops: SimpleNamespace = NUMPY_OPS) -> tuple[Any, Any]:
    """One PD update, elementwise over the legs: returns (Tc, v).

    n, n_prev: counts read now and one period before [counts]; v_prev: the previous filtered
    count rate [counts/s]; ref: setpoint [counts]; ff: open-loop offset [command units];
    kp [command units per count], kd [command units per count/s]: the gains; alpha: the
    velocity filter's coefficient (:func:`velocity_filter_alpha`); rate_hz: the rate the
    count difference is scaled by [Hz] (the loop rate, divided by the periods between the two
    readings); limit: clamp [command units]. ``ops`` gives floor / fmin / fmax (numpy by
    default, CasADi for the plant's compiled loop). Tc is a whole number in [-limit, limit]
    (still a float/SX here); v the new filtered count rate [counts/s].
    """
    v = v_prev + alpha * ((n - n_prev) * rate_hz - v_prev)
    raw = kp * (n - ref) + kd * v + ff
    tc = ops.fmin(ops.fmax(ops.floor(raw + 0.5), -limit), limit)
    return tc, v


@dataclass
class EncoderPD:
    """The paper's encoder-space PD (see the module docstring), with its filter state.

    Call :meth:`update` once per control period with the counts just read; it returns the
    integer commands to send. The first update after construction or :meth:`reset` sees zero
    velocity (no derivative kick).

    Attributes
    ----------
    rate_hz : loop rate [Hz], > 0.
    kp : proportional gain [command units per count]; kd : derivative gain [command units
        per count/s]; both finite.
    cutoff_hz : cut-off of the low-pass on the count rate [Hz], > 0.
    limit : commands are clamped to +-this [command units], in (0, 4096].
    """

    rate_hz: float = 800.0
    kp: float = DEFAULT_KP
    kd: float = DEFAULT_KD
    cutoff_hz: float = DEFAULT_VELOCITY_CUTOFF_HZ
    limit: int = COMMAND_LIMIT

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise InvalidParameterError(f"rate_hz must be > 0, got {self.rate_hz}")
        if not (math.isfinite(self.cutoff_hz) and self.cutoff_hz > 0):
            raise InvalidParameterError(f"cutoff_hz must be > 0, got {self.cutoff_hz}")
        if not (math.isfinite(self.kp) and math.isfinite(self.kd)):
            raise InvalidParameterError("kp and kd must be finite")
        if not 0 < self.limit <= COMMAND_LIMIT:
            raise InvalidParameterError(f"limit must be in (0, {COMMAND_LIMIT}], got {self.limit}")
        self.reset()

    @property
    def alpha(self) -> float:
        """The velocity filter's alpha (depends on rate and cut-off)."""
        return velocity_filter_alpha(self.rate_hz, self.cutoff_hz)

    @property
    def metadata(self) -> str:
        """The falcon-log ``controller`` metadata value, e.g. ``pd kp=10 kd=0.1``."""
        return f"pd kp={self.kp:g} kd={self.kd:g}"

    def reset(self) -> None:
        """Forget the previous count and the filtered velocity."""
        self.n_prev: np.ndarray | None = None
        self.velocity_counts_s = np.zeros(3)

    def update(self, counts: Any, ref: Any, feedforward: Any = None) -> np.ndarray:
        """Commands (int64, shape (3,)) from the ``counts`` read now (3,), the setpoint ``ref``
        (3,) [counts] and an optional ``feedforward`` (3,) [command units] (None: zero)."""
        n = np.asarray(counts, dtype=float).reshape(3)
        r = np.asarray(ref, dtype=float).reshape(3)
        ff = np.zeros(3) if feedforward is None else np.asarray(feedforward, dtype=float).reshape(3)
        if not (np.isfinite(r).all() and np.isfinite(ff).all()):
            raise InvalidParameterError(f"ref {r} and feedforward {ff} must be finite")
        n_prev = n if self.n_prev is None else self.n_prev
        tc, v = pd_law(n, n_prev, self.velocity_counts_s, r, ff, self.kp, self.kd, self.alpha,
                       self.rate_hz, float(self.limit))
        self.n_prev = n
        self.velocity_counts_s = v
        return tc.astype(np.int64)


DERIVATIVE_FORMS = ("error", "measurement")
"""error: kd (v - v_ref) (the executor's default, for moving references); measurement: kd v
(the paper's form)."""
KINDS = ("pd", "lqr")
"""pd: the encoder PD (+ feed-forward); lqr: the time-varying LQR with an observer
(:mod:`falcon_plan.lqr`)."""
FEEDFORWARD_MODES = ("model", "none")
"""model: the inverse dynamics of the reference motion (see the module docstring); none: PD
only."""
OPEN_LOOP = "open-loop"
"""The ``--controller`` value that asks a replay to play the logged commands instead of
re-running a controller (for logs whose controller is unknown)."""
CONTROLLER_OPTION_HELP = ('give it with --controller "pd kp=10 kd=0.1" (optional words fc=<Hz>, '
                          "d_on_error=0|1, ff=0|1, ff_lead=<samples>, limit=<units>) or "
                          '"lqr" (optional words e_pos=<counts>, e_vel=<counts/s>, e_u=<units>, '
                          "delay=<samples>, limit=<units>), or replay "
                          "the logged commands with --controller open-loop")
"""How the CLI supplies a controller that a log does not describe (quoted in errors)."""


@dataclass(frozen=True)
class Controller:
    """The loop that drives the device (see the module docstring); defaults are the paper's
    PD at 800 Hz. Use :meth:`executor_default` for the executor's tracking controller.

    Attributes
    ----------
    rate_hz : loop rate [Hz].
    kp : proportional gain [command units per count]; kd : derivative gain [per count/s].
    derivative : one of :data:`DERIVATIVE_FORMS`.
    velocity_cutoff_hz : cut-off of the first-order low-pass on the count rate [Hz].
    feedforward : one of :data:`FEEDFORWARD_MODES`.
    feedforward_lead_samples : the feed-forward is computed for the period this many samples
        ahead (>= 0; 2 matches the device's command delay); for the LQR also the command delay
        it is designed for (may be fractional).
    command_limit : commands are clamped to +-this [command units], 1..4096.
    feedforward_effects : effects of the model whose inverse dynamics make the feed-forward
        (its parameter set is the one the controller runs with); the LQR's design model.
    kind : one of :data:`KINDS`.
    lqr_weights : the LQR's Bryson weights (:class:`falcon_plan.lqr.LqrWeights`; the PD
        ignores them).
    """

    rate_hz: float = 800.0
    kp: float = DEFAULT_KP
    kd: float = DEFAULT_KD
    derivative: str = "measurement"
    velocity_cutoff_hz: float = DEFAULT_VELOCITY_CUTOFF_HZ
    feedforward: str = "none"
    feedforward_lead_samples: int = 0
    command_limit: int = COMMAND_LIMIT
    feedforward_effects: Effects = NOMINAL
    kind: str = "pd"
    lqr_weights: LqrWeights = LqrWeights()

    def __post_init__(self) -> None:
        for name in ("rate_hz", "velocity_cutoff_hz"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise InvalidParameterError(f"controller {name} must be a number > 0, got {value!r}")
        for name in ("kp", "kd"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InvalidParameterError(f"controller {name} must be a finite number >= 0, got {value!r}")
        if self.derivative not in DERIVATIVE_FORMS:
            raise InvalidParameterError(f"controller derivative must be one of {DERIVATIVE_FORMS}, "
                                        f"got {self.derivative!r}")
        if self.feedforward not in FEEDFORWARD_MODES:
            raise InvalidParameterError(f"controller feedforward must be one of {FEEDFORWARD_MODES}, "
                                        f"got {self.feedforward!r}")
        lead = self.feedforward_lead_samples
        if isinstance(lead, bool) or not isinstance(lead, (int, float)) or not math.isfinite(lead) or lead < 0:
            raise InvalidParameterError(f"feedforward_lead_samples must be a number >= 0, got {lead!r}")
        if self.kind not in KINDS:
            raise InvalidParameterError(f"controller kind must be one of {KINDS}, got {self.kind!r}")
        if self.kind == "lqr" and self.feedforward != "model":
            raise InvalidParameterError("the LQR always uses the model's feed-forward (feedforward='model')")
        if not isinstance(self.lqr_weights, LqrWeights):
            raise InvalidParameterError("lqr_weights must be an LqrWeights value")
        limit = self.command_limit
        if isinstance(limit, bool) or not isinstance(limit, (int, float)) or int(limit) != limit \
                or not 1 <= limit <= COMMAND_LIMIT:
            raise InvalidParameterError(f"command_limit must be a whole number in [1, {COMMAND_LIMIT}], "
                                        f"got {limit!r}")
        if not isinstance(self.feedforward_effects, Effects):
            raise InvalidParameterError("feedforward_effects must be an Effects value")
        object.__setattr__(self, "rate_hz", float(self.rate_hz))
        object.__setattr__(self, "kp", float(self.kp))
        object.__setattr__(self, "kd", float(self.kd))
        object.__setattr__(self, "velocity_cutoff_hz", float(self.velocity_cutoff_hz))
        object.__setattr__(self, "feedforward_lead_samples", int(lead) if float(lead).is_integer() else float(lead))
        object.__setattr__(self, "command_limit", int(limit))

    @classmethod
    def executor_default(cls, rate_hz: float = 800.0, model: FalconModel | None = None, *,
                         kind: str = "lqr", delay_samples: float | None = None,
                         delay_s: float | None = None, link_delay_s: float = 0.0) -> "Controller":
        """The executor's tracking controller of ``kind`` (:data:`KINDS`; default the LQR):
        the model's feed-forward (and, for the LQR, its design) for a command delay of
        ``delay_samples`` [samples, may be fractional] or ``delay_s`` [s] (e.g. the delay
        ``doctor`` measured; at most one of them; default the model's
        :attr:`FalconModel.loop_delay_samples`: 2, plus a fitted extra delay, plus the link
        delay ``doctor`` measured, or, when the model has none, the device's known
        ``link_delay_s`` [s]: what its USB path adds, ``Device.link_delay_s``); ``model`` gives
        the effects (nominal if None). The PD has its derivative on the error."""
        if kind not in KINDS:
            raise InvalidParameterError(f"controller kind must be one of {KINDS}, got {kind!r}")
        effects = NOMINAL if model is None else model.effects
        if delay_s is not None:
            if delay_samples is not None:
                raise InvalidParameterError("give the command delay in samples or in seconds, not both")
            delay_samples = float(delay_s) * float(rate_hz)
        if delay_samples is None:      # the model's loop delay: 2, a fitted extra, the measured link
            delay_samples = 2.0 if model is None else model.loop_delay_samples
            if model is None or not model.params.link_delay_samples:   # not measured: the device's
                delay_samples += link_delay_samples(model, link_delay_s, rate_hz)
        return cls(rate_hz, derivative="error", feedforward="model", feedforward_lead_samples=delay_samples,
                   feedforward_effects=effects, kind=kind)

    @property
    def label(self) -> str:
        """The controller in words, for titles and summaries (e.g. "LQR + feed-forward, 2-sample
        delay, 1000 Hz")."""
        delay = f"{_num(self.feedforward_lead_samples)}-sample delay"
        if self.kind == "lqr":
            return f"time-varying LQR + feed-forward ({delay}, {self.rate_hz:g} Hz)"
        ff = f" + feed-forward ({delay})" if self.feedforward == "model" else ""
        return f"PD kp={_num(self.kp)} kd={_num(self.kd)}{ff}, {self.rate_hz:g} Hz"

    def replace(self, **changes: Any) -> "Controller":
        """A copy with the fields named in ``changes`` set to their values (validated)."""
        return dataclasses.replace(self, **changes)

    @property
    def alpha(self) -> float:
        """The velocity filter's alpha."""
        return velocity_filter_alpha(self.rate_hz, self.velocity_cutoff_hz)

    def pd(self) -> "EncoderPD":
        """A fresh stateful PD (filter state at rest) with this controller's gains."""
        return EncoderPD(self.rate_hz, self.kp, self.kd, self.velocity_cutoff_hz, self.command_limit)

    # --- the open-loop part ------------------------------------------------------------------
    def offsets(self, ref_counts: Any, model: FalconModel) -> np.ndarray:
        """u_k (K, 3) [command units] for the reference ref_counts (K, 3) [counts] on the
        controller's sample grid: feed-forward minus, for the error form, kd v_ref (see the
        module docstring). ``model`` (FalconModel) gives the parameter set; its effects are
        replaced by :attr:`feedforward_effects`, whose encoder offset also sets the home angle
        the reference counts are read from (:meth:`Effects.encoder_params`). Samples beyond
        either end hold the end. Deterministic, and kept for the last few references, as
        :meth:`schedule` is."""
        ref = np.ascontiguousarray(ref_counts, dtype=float)
        if ref.ndim != 2 or ref.shape[1] != 3 or not np.isfinite(ref).all():
            raise InvalidParameterError(f"ref_counts must be finite with shape (K, 3), got {ref.shape}")
        if ref.shape[0] == 0:
            return np.zeros((0, 3))
        return _remembered(_OFFSETS, (ref.tobytes(), ref.shape, self, model.params),
                           lambda: self._offsets(ref, model)).copy()

    def _offsets(self, ref: np.ndarray, model: FalconModel) -> np.ndarray:
        """:meth:`offsets`, computed (``ref`` checked)."""
        out = np.zeros((ref.shape[0], 3))
        if self.feedforward == "model":
            from falcon_plan.lqr import model_feedforward

            # the counts are read from the feed-forward model's home angle (encoder offset)
            out = model_feedforward(ref, model, self.feedforward_effects, self.rate_hz,
                                    self.feedforward_lead_samples)
        if self.derivative == "error":
            raw = np.vstack([np.zeros((1, 3)), np.diff(ref, axis=0) * self.rate_hz])
            out = out - self.kd * low_pass(raw, self.alpha)
        return out

    def schedule(self, ref_counts: Any, model: FalconModel) -> "GainSchedule":
        """The LQR's gain schedule along ``ref_counts`` (K, 3) [counts] (:func:`falcon_plan.lqr.design`
        with ``model``'s parameter set and :attr:`feedforward_effects`); deterministic, and cached
        for the last few references (a replay reruns one log many times)."""
        from falcon_plan.lqr import design

        ref = np.ascontiguousarray(ref_counts, dtype=float)
        return _remembered(_SCHEDULES, (ref.tobytes(), ref.shape, self, model.params, model.limits),
                           lambda: design(ref, model, self.feedforward_effects, self.rate_hz,
                                          self.feedforward_lead_samples, self.lqr_weights))

    def schedule_along(self, trajectory: Any, model: FalconModel, hold_s: float = 0.2) -> "GainSchedule":
        """The LQR's gain schedule along ``trajectory`` (a :class:`~falcon_plan.trajectory.Trajectory`)
        sampled at the controller's rate, held ``hold_s`` [s] at both ends (as the executor's
        pre-roll and settle would): to inspect or plot the gains of a plan
        (:func:`falcon_plan.plots.plot_gains`)."""
        from falcon_plan.model.kinematics import angles_to_counts, inverse_kinematics

        n_hold = int(round(hold_s * self.rate_hz))
        n = int(np.ceil(trajectory.duration_s * self.rate_hz - 1e-9)) + 1
        t = (np.arange(n + 2 * n_hold) - n_hold) / self.rate_hz
        pos, _, _ = trajectory.at_time(np.clip(t, 0.0, trajectory.duration_s) + trajectory.t_s[0])
        theta1 = inverse_kinematics(pos, model.params).theta1
        ref = angles_to_counts(theta1, self.feedforward_effects.encoder_params(model.params))
        return self.schedule(ref, model)

    def tracker(self, ref_counts: Any, model: FalconModel, motion_start: int = 0) -> "Tracker":
        """The per-tick law of this controller along ``ref_counts`` (K, 3) [counts], with
        everything that depends only on the reference and ``model`` computed now (the PD's
        offsets, the LQR's gain schedule). Before sample ``motion_start`` (the approach and
        the hold before the motion) the LQR keeps within the device's static limit
        (:meth:`~falcon_plan.lqr.LqrTracker.within_static_until`)."""
        ref = np.asarray(ref_counts, dtype=float)
        if self.kind == "lqr":
            from falcon_plan.lqr import LqrTracker

            tracker = LqrTracker(self.schedule(ref, model), self.command_limit)
            tracker.within_static_until(motion_start)
            return tracker
        return PdTracker(self, ref, self.offsets(ref, model))

    def splice(self, tracker: "Tracker", tick: int, ref_tail: np.ndarray, feedforward_tail: np.ndarray,
               model: FalconModel) -> None:
        """Make ``tracker`` (this controller's, :meth:`tracker`) follow ``ref_tail`` (m, 3)
        [counts] from ``tick`` on, a reference that continues the running one there in position
        and rate and ends at rest (a brake, :mod:`falcon_plan.execution.braking`), with its
        feed-forward ``feedforward_tail`` (m, 3) [command units]. The LQR gets the stationary
        gains of the rest point (:func:`falcon_plan.lqr.hold_design`: one DARE, not a whole
        design), the PD its offsets over the tail."""
        self.apply_tail(tracker, tick, self.splice_tail(tracker, tick, ref_tail, feedforward_tail, model))

    def splice_tail(self, tracker: "Tracker", tick: int, ref_tail: np.ndarray, feedforward_tail: np.ndarray,
                    model: FalconModel, *, full_design: bool = False) -> Any:
        """What :meth:`splice` computes, apart (to compute it off the control loop): the LQR's
        tail schedule (the stop point's stationary gains, or with ``full_design`` the whole
        time-varying design along ``ref_tail``, for a tail that moves: a new plan), the PD's
        (reference, offsets); ``tracker``, ``tick``, ``ref_tail``, ``feedforward_tail`` and
        ``model`` as for :meth:`splice`. Apply it with :meth:`apply_tail`."""
        if self.kind == "lqr":
            from falcon_plan.lqr import design, hold_design

            if full_design:
                return design(ref_tail, model, self.feedforward_effects, self.rate_hz, self.feedforward_lead_samples,
                              self.lqr_weights)
            return hold_design(ref_tail, feedforward_tail, model, self.feedforward_effects, self.rate_hz,
                               self.feedforward_lead_samples, self.lqr_weights, tracker.s.observer)
        # the PD's offsets filter the reference's rate: read it from a window before the tick
        before = tracker.ref[max(0, tick - PD_SPLICE_WINDOW):tick]
        return ref_tail, self.offsets(np.concatenate([before, ref_tail]), model)[before.shape[0]:]

    def quick_tail(self, tracker: "Tracker", tick: int, ref_tail: np.ndarray, feedforward_tail: np.ndarray,
                   model: FalconModel) -> Any:
        """A :meth:`splice_tail` cheap enough for the loop at the tick it takes effect: for
        ``tracker`` to follow ``ref_tail`` (m, 3) [counts] from ``tick`` on, the LQR keeps the
        gain it uses at ``tick`` (:func:`falcon_plan.lqr.carried_design`, with ``model``), the PD
        takes its offsets from ``feedforward_tail`` (minus kd times the tail's filtered rate,
        as :meth:`offsets`)."""
        if self.kind == "lqr":
            from falcon_plan.lqr import carried_design

            return carried_design(tracker.s, tick - tracker.offset, ref_tail, feedforward_tail, model)
        offsets = (np.asarray(feedforward_tail, dtype=float).copy() if self.feedforward == "model"
                   else np.zeros((len(ref_tail), 3)))
        if self.derivative == "error":
            before = tracker.ref[max(0, tick - PD_SPLICE_WINDOW):tick]
            ref = np.concatenate([before, ref_tail])
            raw = np.vstack([np.zeros((1, 3)), np.diff(ref, axis=0) * self.rate_hz])
            offsets -= self.kd * low_pass(raw, self.alpha)[before.shape[0]:]
        return ref_tail, offsets

    def current_tail(self, tracker: "Tracker") -> tuple[int, Any]:
        """What ``tracker`` follows now, as (tick, tail) for :meth:`apply_tail` (to go back to it)."""
        if self.kind == "lqr":
            return tracker.offset, tracker.s
        return 0, (tracker.ref, tracker.offsets)

    def apply_tail(self, tracker: "Tracker", tick: int, tail: Any) -> None:
        """Make ``tracker`` follow a :meth:`splice_tail` ``tail`` from ``tick`` on (cheap: for the loop)."""
        if self.kind == "lqr":
            tracker.splice(tick, tail)
        else:
            tracker.splice(tick, *tail)

    def run_on(self, plant: ClosedLoopPlant, ref_counts: Any, model: FalconModel,
               samples: int | None = None, motion_start: int = 0) -> PDRun:
        """Run the closed loop on ``plant`` (a :class:`~falcon_plan.sim.plant.SimPlant`) from
        its current state, tracking ``ref_counts`` (K, 3) [counts] with what ``model`` gives
        (:meth:`offsets`, :meth:`schedule`), for the first ``samples`` periods (default all K;
        the design still sees the whole reference), the motion starting at sample
        ``motion_start`` (as :meth:`tracker`); returns its PDRun (counts read and
        commands sent per period). The controller starts at rest (the PD's filter; the LQR's
        observer at the first reading, the commands in flight zero). The PD runs in the
        plant's compiled chunks; the LQR per period through :meth:`tracker` (the executor's
        very arithmetic, so a replay reproduces its commands)."""
        ref = np.asarray(ref_counts, dtype=float)
        n = ref.shape[0] if samples is None else int(samples)
        if self.kind == "pd":
            return plant.run_pd(self.pd(), ref[:n], self.offsets(ref, model)[:n])
        tracker = self.tracker(ref, model, motion_start)
        t = plant.time_s + np.arange(n) * plant.dt_s
        counts = np.zeros((n, 3), dtype=np.int64)
        commands = np.zeros((n, 3), dtype=np.int64)
        reading = np.asarray(plant.counts, dtype=float)
        tracker.start(reading)
        for k in range(n):
            tc = tracker.update(k, reading)
            counts[k], commands[k] = reading, tc
            reading = plant.step(tc).astype(float)
        return PDRun(t, counts, commands)

    # --- log metadata ------------------------------------------------------------------------
    @property
    def metadata(self) -> str:
        """The ``controller`` metadata value (module docstring)."""
        if self.kind == "lqr":
            w = self.lqr_weights
            return (f"lqr e_pos={_num(w.position_counts)} e_vel={_num(w.velocity_counts_s)} "
                    f"e_u={_num(w.feedback_units)} delay={_num(self.feedforward_lead_samples)} "
                    f"limit={self.command_limit}")
        return (f"pd kp={_num(self.kp)} kd={_num(self.kd)} fc={_num(self.velocity_cutoff_hz)} "
                f"d_on_error={int(self.derivative == 'error')} ff={int(self.feedforward == 'model')} "
                f"ff_lead={self.feedforward_lead_samples} limit={self.command_limit}")

    def __str__(self) -> str:
        return self.metadata

    def to_meta(self) -> dict[str, str]:
        """The falcon-log metadata entries that describe this controller."""
        meta = {"rate_hz": _num(self.rate_hz), "controller": self.metadata}
        if self.feedforward == "model":
            meta["feedforward_effects"] = json.dumps(self.feedforward_effects.to_dict(), sort_keys=True)
        return meta

    @classmethod
    def from_meta(cls, meta: dict[str, str], *, text: str | None = None,
                  rate_hz: float | None = None) -> "Controller":
        """The controller a log describes: ``meta`` is the log's metadata (name -> text).
        ``text`` (a ``controller`` value) and ``rate_hz`` [Hz] override the metadata (the
        CLI's --controller and --rate).

        Reads this module's format, the conventions' plain ``pd kp=.. kd=..`` and the older
        executor's (``cutoff_hz=``, and ``feedforward`` / ``command_limit`` keys). Raises
        :class:`LogFormatError` naming what is missing and the option that supplies it.
        """
        from falcon_plan.falconlog import parse_controller, parse_rate_hz

        source = "--controller" if text is not None else "the log's 'controller' metadata"
        text = text if text is not None else meta.get("controller")
        if text is None:
            raise LogFormatError(f"the log has no 'controller' metadata: {CONTROLLER_OPTION_HELP}")
        spec = parse_controller(text)
        if spec.kind == "lqr":
            return cls._lqr_from_meta(meta, spec.gains, source, text, rate_hz)
        gains = dict(spec.gains)
        if "cutoff_hz" in gains:  # the older executor's name
            gains.setdefault("fc", gains.pop("cutoff_hz"))
        missing = [g for g in ("kp", "kd") if g not in gains]
        unknown = sorted(set(gains) - set(_META_WORDS))
        if spec.kind != "pd" or missing or unknown:
            problem = (f"kind {spec.kind!r} is not 'pd' or 'lqr'" if spec.kind != "pd" else
                       f"it lacks {' and '.join(missing)}" if missing else f"unknown word(s) {unknown}")
            raise LogFormatError(f"{source} {text!r} cannot be reproduced ({problem}): {CONTROLLER_OPTION_HELP}")
        rate = rate_hz if rate_hz is not None else parse_rate_hz(meta)
        if rate is None:
            raise LogFormatError("the log has no 'rate_hz' metadata: give the loop rate with --rate HZ")
        if "ff" in gains:
            feedforward = "model" if gains["ff"] else "none"
        else:  # the older executor wrote the mode as its own key; plain logs have none
            mode = meta.get("feedforward", "none")
            if mode not in FEEDFORWARD_MODES:
                raise LogFormatError(
                    f"the log's feed-forward {mode!r} (the plan's own commands) is not recorded in the "
                    "log, so its controller cannot be reproduced: replay the logged commands with "
                    "--controller open-loop")
            feedforward = mode
        effects = NOMINAL
        if feedforward == "model" and meta.get("feedforward_effects"):
            try:
                effects = Effects.from_dict(json.loads(meta["feedforward_effects"]))
            except (json.JSONDecodeError, InvalidParameterError) as exc:
                raise LogFormatError(f"feedforward_effects metadata is not an Effects JSON: {exc}") from None
        limit = gains.get("limit", meta.get("command_limit", COMMAND_LIMIT))
        try:
            return cls(rate, gains["kp"], gains["kd"],
                       "error" if gains.get("d_on_error", 0) else "measurement",
                       gains.get("fc", DEFAULT_VELOCITY_CUTOFF_HZ), feedforward,
                       gains.get("ff_lead", 0), float(limit), effects)
        except (InvalidParameterError, ValueError) as exc:
            raise LogFormatError(f"{source} {text!r}: {exc}") from None


    @classmethod
    def _lqr_from_meta(cls, meta: dict[str, str], words: dict[str, float], source: str, text: str,
                       rate_hz: float | None) -> "Controller":
        """:meth:`from_meta` for an ``lqr`` controller value (its name=number ``words``)."""
        from falcon_plan.falconlog import parse_rate_hz

        unknown = sorted(set(words) - set(_LQR_WORDS))
        if unknown:
            raise LogFormatError(f"{source} {text!r} cannot be reproduced (unknown word(s) {unknown}): "
                                 f"{CONTROLLER_OPTION_HELP}")
        rate = rate_hz if rate_hz is not None else parse_rate_hz(meta)
        if rate is None:
            raise LogFormatError("the log has no 'rate_hz' metadata: give the loop rate with --rate HZ")
        effects = NOMINAL
        if meta.get("feedforward_effects"):
            try:
                effects = Effects.from_dict(json.loads(meta["feedforward_effects"]))
            except (json.JSONDecodeError, InvalidParameterError) as exc:
                raise LogFormatError(f"feedforward_effects metadata is not an Effects JSON: {exc}") from None
        default = LqrWeights()
        try:
            weights = LqrWeights(words.get("e_pos", default.position_counts), words.get("e_vel", default.velocity_counts_s),
                                 words.get("e_u", default.feedback_units))
            delay = words.get("delay", 2 + effects.extra_delay_samples)
            return cls(rate, derivative="error", feedforward="model", feedforward_lead_samples=delay,
                       command_limit=words.get("limit", COMMAND_LIMIT), feedforward_effects=effects,
                       kind="lqr", lqr_weights=weights)
        except (InvalidParameterError, ValueError) as exc:
            raise LogFormatError(f"{source} {text!r}: {exc}") from None


class Tracker(Protocol):
    """A controller's per-tick law along one reference (:meth:`Controller.tracker`): ``start``
    once with the first counts read, then ``update`` every tick k = 0, 1, ... (a tick may be
    skipped: a missed deadline); ``state``/``restore`` to recompute a tick."""

    def start(self, counts: Any, issued_before: Any = None) -> None:
        """Initialise from the first reading ``counts`` (3,) [counts] with the commands in flight
        ``issued_before`` (3,) [command units] (None: zero force before)."""
        ...

    def update(self, k: int, counts: Any, slots: int = 1, fresh: bool = True,
               read_for: int | None = None) -> np.ndarray:
        """The commands (3,) [whole command units as floats, clamped] for tick k from the
        ``counts`` read now, ``slots`` periods after the previous exchange; ``fresh`` False:
        the device sent nothing new since the previous reading (``counts`` repeats it);
        ``read_for``: the tick the reading was read for, when it came late
        (:meth:`falcon_plan.timing.HandOvers.reading_tick`; None: the tick after the previous
        exchange)."""
        ...

    def state(self) -> Any:
        """A copy of the law's state."""
        ...

    def restore(self, state: Any) -> None:
        """Go back to a :meth:`state`."""
        ...


class PdTracker:
    """The PD's per-tick law along a reference: :func:`pd_law` with the ``controller``'s gains,
    tracking ``ref`` (K, 3) [counts] with the open-loop ``offsets`` (K, 3) [command units]."""

    def __init__(self, controller: Controller, ref: np.ndarray, offsets: np.ndarray) -> None:
        self.c, self.ref, self.offsets = controller, ref, offsets
        self.alpha = controller.alpha
        self.limit = float(controller.command_limit)
        self.prev = np.zeros(3)
        self.velocity = np.zeros(3)
        self.k_next = 0
        self.unread = 0      # periods since the previous fresh reading, before this exchange

    def start(self, counts: Any, issued_before: Any = None) -> None:
        """At rest at the first reading ``counts`` (3,) [counts] (the PD has no state of the
        commands in flight: ``issued_before`` is not needed)."""
        self.prev = np.asarray(counts, dtype=float).copy()
        self.velocity = np.zeros(3)
        self.k_next = 0
        self.unread = 0

    def update(self, k: int, counts: Any, slots: int = 1, fresh: bool = True,
               read_for: int | None = None) -> np.ndarray:
        """Commands (3,) for tick k from the ``counts`` (3,) read now, ``slots`` periods after
        the previous exchange (the count rate is the difference over the time since the
        previous fresh reading). ``fresh`` False (nothing new was read): the PD acts on the
        previous counts moved on at the count rate it had. The PD has no model to place a
        late reading at its own tick: ``read_for`` is not used (the paper's law, as the
        replay's compiled PD runs it)."""
        c = self.c
        j = min(k, self.ref.shape[0] - 1)
        self.k_next = k + 1
        if not fresh:
            self.unread += slots
            guess = self.prev + self.velocity * (self.unread / c.rate_hz)
            raw = c.kp * (guess - self.ref[j]) + c.kd * self.velocity + self.offsets[j]
            return np.clip(np.floor(raw + 0.5), -self.limit, self.limit)
        n = np.asarray(counts, dtype=float)
        tc, self.velocity = pd_law(n, self.prev, self.velocity, self.ref[j], self.offsets[j], c.kp, c.kd,
                                   self.alpha, c.rate_hz / (slots + self.unread), self.limit)
        self.prev, self.unread = n, 0
        return tc

    def splice(self, tick: int, ref_tail: np.ndarray, offsets_tail: np.ndarray) -> None:
        """Follow ``ref_tail`` (m, 3) [counts] with ``offsets_tail`` (m, 3) from ``tick`` on."""
        self.ref = np.concatenate([self.ref[:tick], ref_tail])
        self.offsets = np.concatenate([self.offsets[:tick], offsets_tail])

    def state(self) -> tuple[np.ndarray, np.ndarray, int, int]:
        """(previous counts, filtered velocity, next tick, periods unread)."""
        return self.prev.copy(), self.velocity.copy(), self.k_next, self.unread

    def restore(self, state: tuple[np.ndarray, np.ndarray, int, int]) -> None:
        """Go back to a :meth:`state`."""
        self.prev, self.velocity, self.k_next, self.unread = state[0].copy(), state[1].copy(), state[2], state[3]


PD_SPLICE_WINDOW = 400
"""Samples of the running reference before a splice from which the PD's offsets are read (its
rate filter settles well within them)."""
_SCHEDULES: dict[tuple, "GainSchedule"] = {}
_OFFSETS: dict[tuple, np.ndarray] = {}
REMEMBERED = 8
"""References whose gain schedule (and, apart, open-loop offsets) a process keeps: a
discrepancy replay reruns one log under many trial effects, and neither depends on them."""


def _remembered(store: dict[tuple, Any], key: tuple, make: Any) -> Any:
    """``store[key]``, made by ``make()`` the first time; the oldest of :data:`REMEMBERED` dropped.
    One thread at a time (replays run side by side: a second caller waits for the first's
    value rather than making it again)."""
    with _REMEMBERING:
        if key not in store:
            if len(store) >= REMEMBERED:
                store.pop(next(iter(store)))
            store[key] = make()
        return store[key]


_REMEMBERING = threading.RLock()


_META_WORDS = ("kp", "kd", "fc", "d_on_error", "ff", "ff_lead", "limit")
"""The name=number words of the ``controller`` metadata."""
_LQR_WORDS = ("e_pos", "e_vel", "e_u", "delay", "limit")
"""The name=number words of an ``lqr`` controller value."""


def link_delay_samples(model: Any, link_delay_s: float, rate_hz: float) -> float:
    """The USB link's delay beyond the device's own command delay [control periods, may be
    fractional] that a run with ``model`` (a :class:`~falcon_plan.model.dynamics.FalconModel`
    or None) on a device whose known link delay is ``link_delay_s`` [s] (``Device.link_delay_s``)
    at ``rate_hz`` [Hz] assumes: the model's measured one (``params.link_delay_samples``, from
    ``doctor`` or fitted by the discrepancy workflow) when it has one, else the device's. The
    controller leads its feed-forward by it and the executor records it in the log
    (:data:`~falcon_plan.falconlog.LINK_DELAY_KEY`), so that a replay delays the commands by it."""
    measured = 0.0 if model is None else float(model.params.link_delay_samples)
    return measured if measured else float(link_delay_s) * float(rate_hz)


def _num(x: float) -> str:
    """Shortest text that reads back as exactly x."""
    return f"{x:g}" if float(f"{x:g}") == x else repr(float(x))


__all__ = ["Controller", "link_delay_samples", "EncoderPD", "PDRun", "ClosedLoopPlant", "Tracker", "PdTracker", "KINDS", "low_pass", "pd_law", "velocity_filter_alpha", "DEFAULT_KP", "DEFAULT_KD",
           "DEFAULT_VELOCITY_CUTOFF_HZ", "COMMAND_LIMIT", "DERIVATIVE_FORMS", "FEEDFORWARD_MODES",
           "OPEN_LOOP", "CONTROLLER_OPTION_HELP"]
