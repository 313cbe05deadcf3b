"""The safe stop: brake a running reference to rest within the command limit, then hold.

When a run is cancelled at tick k, the commands from tick k on may change; the commands
already issued act until tick k + d (d = the command delay, ``feedforward_lead_samples``). So the
reference follows the running plan to tick s = k + ceil(d) and brakes from the plan's state
there (position p_s, velocity v_s, base frame) along the direction of motion::

    p(t) = p_s + v_s t - a (v_s / |v_s|) t^2 / 2     for t <= |v_s| / a,   then held

a constant deceleration a [m/s^2] on the tangent, continuous with the plan in position and
velocity at s (the minimum-time stop among constant decelerations on that line). a is the
largest (to :data:`DECELERATION_RESOLUTION`) whose feed-forward, the model's inverse
dynamics of the spliced reference in encoder counts (exactly what the controller will send
before feedback), stays within the planner's default bound (the static saturation less the
feedback reserve, :data:`BRAKE_TC_MAX`); its path stays in the workspace if any does (a harder
brake's path is the start of a softer one's). The stop point is then held with the gravity
feed-forward.

The stop must begin at the first deadline after the cancel, and the loop must not compute it
(a brake takes a millisecond or more, a control period at 800 Hz is 1.25 ms), so it is made in
three parts:

* :func:`first_commands`, with the plan (before any cancel): for every command tick, the first
  :data:`FIRST_BRAKE_TICKS` commands of the brake tried first (reference, points, velocities and
  exact feed-forward; whether they are within the bound and the workspace), all ticks in one
  batch. Its deceleration is closed-form, :func:`start_deceleration` (the model's inverse
  dynamics is affine in the acceleration: two batches of it give the largest a within
  :data:`START_MARGIN` of the bound at the brake's start and at rest at its stop). At a cancel
  the loop looks its tick's up and follows it;
* :func:`continue_brake`, off the loop (:func:`falcon_plan.execution.splice.finish_stop`) from a
  tick after its measured latency, before those commands run out: :func:`quick_brake` from
  their state there (the closed-form candidate checked by the full feed-forward and the
  workspace: usually within, one batch of inverse kinematics and inverse dynamics; when it is
  not, softer ones :data:`QUICK_LADDER`, 2^(1/8) apart, a few per batch, the hardest within the
  bound taken), near the workspace's edge :func:`plan_brake`; on the same line, so continuous in
  position and velocity; :func:`joined_stop` is the whole stop from the cancel;
* :func:`plan_brake`, the minimum-time brake: the same first candidate doubled or halved to a
  bracket, then bisection (one batch per trial: a few milliseconds), run off the loop from
  the stop's state a little later and spliced in at a tick
  (:mod:`falcon_plan.execution.splice`). All of them lie on the same line, so the hand-overs
  are continuous in position and velocity.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.lqr import DEFAULT_FEEDBACK_UNITS, LATE_ACTING_TICKS, model_feedforward
from falcon_plan.model.kinematics import angles_to_counts, inverse_kinematics, jacobian
from falcon_plan.model.workspace import in_workspace

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.effects import Effects

BRAKE_TC_MAX = 2500.0 - DEFAULT_FEEDBACK_UNITS
"""Peak feed-forward of a brake [command units]: the planner's default bound (the static
saturation 2500 less the feedback reserve), so the feedback keeps its room."""
DECELERATION_RANGE_M_S2 = (0.1, 1000.0)
"""The decelerations the search considers [m/s^2]."""
DECELERATION_RESOLUTION = 0.02
"""The bisection stops when the bracket is within this fraction of a."""
START_MARGIN = 0.95
"""The closed-form first candidate (:func:`start_deceleration`) uses this share of the bound at
the brake's ends, leaving the rest for the change of the dynamics along its path."""
QUICK_LADDER = 2.0 ** (-np.arange(0, 33) / 8.0)
"""The loop's brake tries these multiples of :func:`start_deceleration`, hardest first (1 down to
1/16, steps of 2^(1/8)): the first alone, then in batches of :data:`QUICK_BATCH`
(:func:`quick_brake`)."""
QUICK_BATCH = 4
"""Candidates per batch of inverse dynamics in :func:`quick_brake` after the first."""
FIRST_BRAKE_TICKS = 24
"""Commands of the stop :func:`first_commands` makes exactly for every tick (30 ms at 800 Hz): the
loop follows them from a cancel while a worker computes the rest (:func:`continue_brake`) and
hands it over before they run out."""
STOP_HOLD_S = 0.25
"""Shortest hold at the stop point after a brake [s] (the run's settle time if longer)."""


@dataclass(frozen=True)
class Brake:
    """A brake spliced into a run at the command tick ``tick`` (the first command it changes).

    Attributes
    ----------
    tick : the command splice tick k; ``lead`` : ticks the reference still follows the plan
        (ceil of the command delay), so the brake starts at tick k + lead.
    ref_counts : (m, 3) the reference from tick k on: the plan to k + lead, the brake, the hold [counts].
    position_m : (m, 3) its points [m, base frame]; velocity_m_s : (m, 3) their velocities [m/s].
    feedforward : (m, 3) its feed-forward [command units] (the controller's, before feedback).
    deceleration_m_s2 : a [m/s^2]; ``stop_s`` : the brake's length [s].
    stop_counts : (3,) where the reference comes to rest [counts].
    position_jump_counts, velocity_jump_counts_s : max over legs of the brake's start minus
        the plan at tick k + lead, in position [counts] (inverse kinematics against the plan's
        counts: zero to rounding) and rate [counts/s] (the brake's initial leg rates against the
        plan's fourth-order central difference: zero to its O(T^4) error, well under a count per second).
    command_jump : max over legs of the feed-forward's change at tick k against the running
        plan's [command units] (a minimum-time stop starts at full command: not zero).
    peak_feedforward : max |feedforward| [command units] (<= :data:`BRAKE_TC_MAX`).
    compute_s : how long its first command took to compute in the loop [s] (set by the executor;
        the rest is computed once that command is sent).
    """

    tick: int
    lead: int
    ref_counts: np.ndarray
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    feedforward: np.ndarray
    deceleration_m_s2: float
    stop_s: float
    stop_counts: np.ndarray
    position_jump_counts: float
    velocity_jump_counts_s: float
    command_jump: float
    peak_feedforward: float
    compute_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no arrays but the stop point)."""
        return {"tick": self.tick, "lead_ticks": self.lead, "deceleration_m_s2": self.deceleration_m_s2,
                "stop_s": self.stop_s, "stop_counts": [float(x) for x in self.stop_counts],
                "position_jump_counts": self.position_jump_counts,
                "velocity_jump_counts_s": self.velocity_jump_counts_s, "command_jump": self.command_jump,
                "peak_feedforward": self.peak_feedforward, "compute_ms": 1e3 * self.compute_s}


def brake_points(p0: np.ndarray, v0: np.ndarray, decel: Any, t: np.ndarray) -> np.ndarray:
    """Points (..., 3) [m] at times ``t`` (...) [s] of the brake from p0 (..., 3) [m] at
    v0 (..., 3) [m/s] with deceleration ``decel`` [m/s^2, scalar or shape (...)] along v0,
    held where it stops (broadcast over the leading axes)."""
    speed = np.linalg.norm(v0, axis=-1)
    safe = np.where(speed > 0, speed, 1.0)
    t = np.minimum(t, speed / np.asarray(decel, dtype=float))[..., None]
    return p0 + v0 * t - 0.5 * (np.asarray(decel, dtype=float) / safe)[..., None] * v0 * t * t


def brake_profile(p0: np.ndarray, v0: np.ndarray, decel: float, rate_hz: float) -> tuple[np.ndarray, float]:
    """Points (J, 3) [m] on the grid t_j = j / rate_hz, j = 0 .. J - 1, braking from p0 (3,) [m]
    at v0 (3,) [m/s] with deceleration ``decel`` [m/s^2] along v0 until it stops (the last
    sample at or after the stop), and the brake's length [s]."""
    t_stop = float(np.linalg.norm(v0)) / decel
    t = np.arange(int(math.ceil(t_stop * rate_hz - 1e-9)) + 1) / rate_hz
    return brake_points(p0, v0, decel, t), t_stop


def start_deceleration(p0: np.ndarray, v0: np.ndarray, dynamics: FalconModel, tc_max: float) -> np.ndarray:
    """The closed-form first candidate of a brake from p0 (..., 3) [m] at v0 (..., 3) [m/s]
    [m/s^2, shape (...), within :data:`DECELERATION_RANGE_M_S2`]: the commands of
    ``dynamics``' inverse dynamics (affine in the acceleration) at the brake's start
    (p0, v0, -a u) and at rest at its stop (p_stop, 0, -a u), u = v0 / |v0|, are within
    :data:`START_MARGIN` times ``tc_max`` [command units]; the stop point
    p_stop = p0 + u |v0|^2 / (2 a) from a first pass at p0 alone. Two batches of inverse
    dynamics (tens of microseconds for one brake); at rest: the range's top."""
    lo, hi = DECELERATION_RANGE_M_S2
    p0, v0 = (np.asarray(x, dtype=float) for x in (p0, v0))
    shape = p0.shape[:-1]
    p0, v0 = p0.reshape(-1, 3), v0.reshape(-1, 3)
    speed = np.linalg.norm(v0, axis=1)
    u = v0 / np.where(speed > 0, speed, 1.0)[:, None]
    zero, bound = np.zeros_like(v0), START_MARGIN * tc_max

    def largest(stop: np.ndarray) -> np.ndarray:
        """(m,) the largest a within the bound at (p0, v0) and at rest at ``stop`` (m, 3)."""
        tau = np.asarray(dynamics.inverse_dynamics(np.concatenate([p0, p0, stop, stop]),
                                                   np.concatenate([v0, v0, zero, zero]),
                                                   np.concatenate([zero, -u, zero, -u])), dtype=float)
        tau = tau.reshape(4, -1, 3)
        base, slope = tau[[0, 2]], tau[[1, 3]] - tau[[0, 2]]
        with np.errstate(divide="ignore", invalid="ignore"):
            room = np.where(slope > 0, (bound - base) / slope, np.where(slope < 0, (-bound - base) / slope, np.inf))
        return np.clip(room.min(axis=(0, 2)), lo, hi)

    a = np.full(speed.shape, hi)
    moving = speed > 0
    if moving.any():
        p0, v0, u, zero, speed = p0[moving], v0[moving], u[moving], zero[moving], speed[moving]
        first = largest(p0)
        a[moving] = largest(p0 + u * (speed * speed / (2.0 * first))[:, None])
    return a.reshape(shape)


class _BrakeSearch:
    """The brakes a run cancelled at command tick ``tick`` can take (see :func:`plan_brake`):
    candidate decelerations tried alone or many in one batch of inverse dynamics."""

    def __init__(self, ref_counts: np.ndarray, positions_m: np.ndarray, velocities_m_s: np.ndarray, tick: int,
                 model: FalconModel, effects: Effects, rate_hz: float, lead_samples: float, tc_max: float) -> None:
        self.ref_counts, self.positions_m, self.velocities_m_s = ref_counts, positions_m, velocities_m_s
        self.tick, self.model, self.effects, self.rate_hz = tick, model, effects, rate_hz
        self.lead_samples, self.tc_max = lead_samples, tc_max
        self.lead = int(math.ceil(lead_samples - 1e-9))
        self.s = min(tick + self.lead, ref_counts.shape[0] - 1)
        self.p0, self.v0 = positions_m[self.s], velocities_m_s[self.s]
        self.encoder = effects.encoder_params(model.params)
        self.dynamics = model.with_effects(effects)          # the controller's model
        self.pad = self.lead + 3                              # hold samples the feed-forward reads
        self._old_ff: np.ndarray | None = None               # the running feed-forward at the tick

    def guess(self) -> float:
        """The first candidate deceleration [m/s^2] (:func:`start_deceleration`)."""
        return float(start_deceleration(self.p0, self.v0, self.dynamics, self.tc_max))

    def profile(self, decel: float) -> tuple[np.ndarray, np.ndarray, float]:
        """The brake at ``decel`` [m/s^2] on the loop's grid: points [m], velocities [m/s], length [s]."""
        pos, t_stop = brake_profile(self.p0, self.v0, decel, self.rate_hz)
        speed = float(np.linalg.norm(self.v0))
        t = np.minimum(np.arange(pos.shape[0]) / self.rate_hz, t_stop)[:, None]
        return pos, self.v0 - decel * (self.v0 / speed if speed > 0 else 0.0) * t, t_stop

    def counts(self, pos: np.ndarray) -> np.ndarray:
        """Reference counts of the points ``pos`` [m] (NaN where unreachable)."""
        return angles_to_counts(inverse_kinematics(pos, self.model.params, strict=False).theta1, self.encoder)

    def assemble(self, braking: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                 extra: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(reference [counts], points [m], velocities [m/s]) from the tick on: the plan for the
        command delay, the brake (``braking`` counts of ``pos``, ``vel``), its stop held
        ``pad + extra`` samples."""
        hold = self.pad + extra
        k, s = self.tick, self.s
        ref = np.concatenate([self.ref_counts[k:s], braking, np.repeat(braking[-1:], hold, axis=0)])
        points = np.concatenate([self.positions_m[k:s], pos, np.repeat(pos[-1:], hold, axis=0)])
        vels = np.concatenate([self.velocities_m_s[k:s], vel, np.zeros((hold, 3))])
        return ref, points, vels

    def candidate(self, decel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(reference, points, velocities, brake length) of the brake at ``decel`` (:meth:`assemble`)."""
        pos, vel, t_stop = self.profile(decel)
        return (*self.assemble(self.counts(pos), pos, vel), t_stop)

    def feedforward(self, ref: np.ndarray, points: np.ndarray) -> np.ndarray:
        return model_feedforward(ref, self.model, self.effects, self.rate_hz, self.lead_samples, positions_m=points)

    def within(self, ff: np.ndarray) -> bool:
        """Whether the feed-forward ``ff`` [command units] is within the bound (an unreachable
        point's is NaN: not within)."""
        peak = np.abs(ff).max()
        return bool(np.isfinite(peak) and peak <= self.tc_max)

    def trial(self, decel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float] | None:
        """The brake at ``decel`` (reference, points, velocities, feed-forward, length), None when
        its feed-forward exceeds the bound."""
        ref, points, vels, t_stop = self.candidate(decel)
        ff = self.feedforward(ref, points)
        return (ref, points, vels, ff, t_stop) if self.within(ff) else None

    def old_window(self) -> tuple[np.ndarray, np.ndarray, int]:
        """The running reference around the tick (counts, points) and the tick's index in it:
        enough samples for its feed-forward there (what the commands were before the brake)."""
        lo = max(0, self.tick - 2)
        hi = self.tick + self.lead + 4
        return self.ref_counts[lo:hi], self.positions_m[lo:hi], self.tick - lo

    def batch(self, decels: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float] | None]:
        """:meth:`trial` of every deceleration with ONE call each of the inverse kinematics and
        the inverse dynamics: the candidates end to end, each with ``pad`` more hold samples so
        that the feed-forward of its own samples reads none of the next one's (dropped after);
        the running reference's feed-forward at the tick rides along (kept for :meth:`finish`)."""
        if self.lead_samples < 1.0:                      # the feed-forward would read back across segments
            return [self.trial(float(a)) for a in decels]
        profiles = [self.profile(float(a)) for a in decels]
        sizes = [p[0].shape[0] for p in profiles]
        counts = np.split(self.counts(np.concatenate([p[0] for p in profiles])), np.cumsum(sizes)[:-1])
        built = [self.assemble(c, p[0], p[1], extra=self.pad) for c, p in zip(counts, profiles)]
        old_ref, old_points, at_tick = self.old_window()
        ff_all = self.feedforward(np.concatenate([old_ref] + [b[0] for b in built]),
                                  np.concatenate([old_points] + [b[1] for b in built]))
        self._old_ff = ff_all[at_tick]
        out: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float] | None] = []
        at = old_ref.shape[0]
        for (ref, points, vels), (_, _, t_stop) in zip(built, profiles):
            m = ref.shape[0] - self.pad
            ff = ff_all[at:at + m]
            at += ref.shape[0]
            out.append((ref[:m], points[:m], vels[:m], ff, t_stop) if self.within(ff) else None)
        return out

    def finish(self, best: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float], decel: float,
               hold_samples: int, workspace: bool = True) -> Brake | None:
        """The :class:`Brake` of the trial ``best`` at ``decel``, its stop held ``hold_samples``;
        None when its path leaves the workspace (not checked when ``workspace`` is False)."""
        ref, points, vels, ff, t_stop = best
        lead, tick = self.lead, self.tick
        if workspace and not np.all(in_workspace(points[lead:], self.model.params, self.model.limits)):
            return None
        more = max(0, hold_samples - self.pad)
        ref, points, ff = (np.concatenate([x, np.repeat(x[-1:], more, axis=0)]) for x in (ref, points, ff))
        vels = np.concatenate([vels, np.zeros((more, 3))])
        jumps = self.jumps(ref[self.s - tick], ff[0])
        return Brake(tick=tick, lead=self.s - tick, ref_counts=ref, position_m=points, velocity_m_s=vels, feedforward=ff,
                     deceleration_m_s2=float(decel), stop_s=float(t_stop), stop_counts=ref[-1].copy(),
                     position_jump_counts=jumps[0], velocity_jump_counts_s=jumps[1], command_jump=jumps[2],
                     peak_feedforward=float(np.abs(ff).max()))

    def jumps(self, start_counts: np.ndarray, first_ff: np.ndarray) -> tuple[float, float, float]:
        """A brake's discontinuities against the running reference (see :class:`Brake`): its
        start ``start_counts`` (3,) [counts] against the reference at s, the brake's initial leg
        rates (the Jacobian of v_s) against the difference quotient of the reference's counts,
        and its first feed-forward ``first_ff`` (3,) against the running one at the tick."""
        s, n_total, ref_counts, rate_hz = self.s, self.ref_counts.shape[0], self.ref_counts, self.rate_hz
        old_ff = self._old_ff
        if old_ff is None:
            old_ref, old_points, at_tick = self.old_window()
            old_ff = self.feedforward(old_ref, old_points)[at_tick]
        at = lambda j: ref_counts[min(max(s + j, 0), n_total - 1)]  # noqa: E731
        plan_rate = (8.0 * (at(1) - at(-1)) - (at(2) - at(-2))) * (rate_hz / 12.0)  # fourth order
        brake_rate = jacobian(self.p0, self.model.params) @ self.v0 * self.encoder.counts_per_rad
        return (float(np.abs(start_counts - ref_counts[s]).max()), float(np.abs(brake_rate - plan_rate).max()),
                float(np.abs(first_ff - old_ff).max()))


def plan_brake(ref_counts: np.ndarray, positions_m: np.ndarray, velocities_m_s: np.ndarray, tick: int,
               model: FalconModel, effects: Effects, rate_hz: float, lead_samples: float, hold_samples: int,
               tc_max: float = BRAKE_TC_MAX) -> Brake | None:
    """The minimum-time brake for a run cancelled at command tick ``tick`` (to
    :data:`DECELERATION_RESOLUTION`): ``ref_counts`` (n, 3) [counts] is the running reference,
    ``positions_m`` (n, 3) [m] and ``velocities_m_s`` (n, 3) [m/s] its planned points and
    velocities; ``model`` with ``effects`` (the controller's) gives the feed-forward at the
    controller's ``rate_hz`` and command delay ``lead_samples``; the stop is held
    ``hold_samples``. None when no brake within ``tc_max`` keeps the path in the workspace
    (then the running plan is the stop). A few milliseconds: off the loop
    (:func:`quick_brake` is the loop's)."""
    search = _BrakeSearch(ref_counts, positions_m, velocities_m_s, tick, model, effects, rate_hz, lead_samples, tc_max)
    lo, hi = DECELERATION_RANGE_M_S2
    if not np.any(search.v0):                                 # at rest: nothing to brake
        best, best_a = search.trial(hi), hi
    else:
        # first guess: the closed-form start deceleration; double or halve it to a feasible a
        # below an infeasible 2a, then bisect between them
        best_a = search.guess()
        best = search.trial(best_a)
        if best is not None:
            while best_a * 2.0 <= hi and (got := search.trial(best_a * 2.0)) is not None:
                best, best_a = got, best_a * 2.0
        while best is None and best_a * 0.5 >= lo:
            best_a *= 0.5
            best = search.trial(best_a)
        if best is None:
            return None
        low, high = best_a, best_a * 2.0
        while high - low > DECELERATION_RESOLUTION * low:
            mid = math.sqrt(low * high)
            got = search.trial(mid)
            if got is None:
                high = mid
            else:
                low, best, best_a = mid, got, mid
    if best is None:
        return None
    # a harder brake's path is a part of a softer one's: one workspace check, of the hardest
    return search.finish(best, best_a, hold_samples)


@dataclass(frozen=True)
class StopStart:
    """The first commands of the stop from one command tick k (a row of :class:`FirstCommands`).

    Attributes
    ----------
    ref_counts, position_m, velocity_m_s : (W, 3) the reference from tick k on [counts], its
        points [m, base frame] and velocities [m/s]: the plan's for the command delay, then the
        brake :func:`quick_brake` tries first (held where it stops); W = :data:`FIRST_BRAKE_TICKS`
        + lead + 5, so that :func:`continue_brake` can take over at any of the exact commands.
    feedforward : (E, 3) the feed-forward of the first E = :data:`FIRST_BRAKE_TICKS` commands
        [command units], exact (each reads only samples of the rows above).
    deceleration_m_s2 : the brake's deceleration [m/s^2].
    """

    ref_counts: np.ndarray
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    feedforward: np.ndarray
    deceleration_m_s2: float

    @property
    def exact(self) -> int:
        """The commands it holds exactly (E)."""
        return self.feedforward.shape[0]


@dataclass(frozen=True)
class FirstCommands:
    """The stop's first :data:`FIRST_BRAKE_TICKS` commands for every command tick of ``ticks``
    (:func:`first_commands`), computed before any cancel (with the plan), so that the loop's
    part at a cancel is a look-up.

    Attributes
    ----------
    ticks : the command ticks covered (a range).
    ref_counts, position_m, velocity_m_s : (N, W, 3) each tick's :attr:`StopStart.ref_counts`,
        ``position_m``, ``velocity_m_s``.
    feedforward : (N, E, 3) each tick's exact feed-forward [command units].
    deceleration_m_s2 : (N,) each tick's brake deceleration [m/s^2].
    within : (N,) whether its E commands' feed-forward is within the bound and the brake's
        points among the rows they follow are in the workspace.
    """

    ticks: range
    ref_counts: np.ndarray
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    feedforward: np.ndarray
    deceleration_m_s2: np.ndarray
    within: np.ndarray

    def row(self, tick: int) -> StopStart | None:
        """The stop's start from ``tick`` (one of :attr:`ticks`, or later when the last one is at
        rest: a run holding its last point); None when it is not :attr:`within` (or not covered)."""
        i, last = tick - self.ticks.start, self.ref_counts.shape[0] - 1
        if i > last and len(self.ticks) == last + 1 and not np.any(self.velocity_m_s[last]):
            i = last                                  # (the whole table, its end at rest: held)
        if not (0 <= i < len(self.ticks)) or not self.within[i]:
            return None
        return StopStart(self.ref_counts[i], self.position_m[i], self.velocity_m_s[i], self.feedforward[i],
                         float(self.deceleration_m_s2[i]))

    def at(self, tick: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(reference (E, 3) [counts], feed-forward (E, 3) [command units]) of the first exact
        commands from ``tick`` (:meth:`row`); None when that row is not within."""
        row = self.row(tick)
        return None if row is None else (row.ref_counts[:row.exact], row.feedforward)

    def after(self, tick: int) -> "FirstCommands":
        """This table for its ticks before ``tick`` only (a new reference from ``tick`` on)."""
        return dataclasses.replace(self, ticks=range(self.ticks.start, max(self.ticks.start, min(tick, self.ticks.stop))))

    def shifted(self, start: int) -> "FirstCommands":
        """This table with its first tick at ``start`` (made for a reference that starts there)."""
        return dataclasses.replace(self, ticks=range(start, start + len(self.ticks)))


def first_commands(ref_counts: np.ndarray, positions_m: np.ndarray, velocities_m_s: np.ndarray, ticks: range,
                   model: FalconModel, effects: Effects, rate_hz: float, lead_samples: float,
                   tc_max: float = BRAKE_TC_MAX) -> FirstCommands:
    """The first :data:`FIRST_BRAKE_TICKS` commands of the brake :func:`quick_brake` tries first,
    for a cancel at each tick of ``ticks`` (``ref_counts``, ``positions_m``,
    ``velocities_m_s``, ``model``, ``effects``, ``rate_hz``, ``lead_samples`` and ``tc_max`` as
    there), all at once: the closed-form deceleration, then one batch of inverse kinematics, of
    inverse dynamics and of the workspace check for every tick together (no search). The executor
    computes it with the plan (and with every new plan spliced in), before any cancel, so that
    at a cancel the loop only looks its tick's up and follows it while a worker computes the
    rest (:func:`continue_brake`)."""
    n = ref_counts.shape[0]
    lead = int(math.ceil(lead_samples - 1e-9))
    exact = FIRST_BRAKE_TICKS
    width = exact + lead + 5
    k = np.arange(ticks.start, ticks.stop)
    plan = np.minimum(k[:, None] + np.arange(lead), n - 1)      # the plan's samples (the end holds)
    s = np.minimum(k + lead, n - 1)
    p0, v0 = positions_m[s], velocities_m_s[s]
    decel = start_deceleration(p0, v0, model.with_effects(effects), tc_max)
    t = np.arange(width - lead) / rate_hz
    points = brake_points(p0[:, None], v0[:, None], decel[:, None], t)
    speed = np.linalg.norm(v0, axis=1)
    u = v0 / np.where(speed > 0, speed, 1.0)[:, None]
    left = np.maximum(speed[:, None] - decel[:, None] * t, 0.0)          # the speed along the brake [m/s]
    vels = u[:, None] * left[..., None]
    counts = angles_to_counts(inverse_kinematics(points.reshape(-1, 3), model.params, strict=False).theta1,
                              effects.encoder_params(model.params)).reshape(points.shape)
    ref = np.concatenate([ref_counts[plan], counts], axis=1)
    points_all = np.concatenate([positions_m[plan], points], axis=1)
    vels = np.concatenate([velocities_m_s[plan], vels], axis=1)
    if lead_samples >= 1.0:
        # every tick's rows end to end in one batch; row j reads samples j .. j + lead + 2 only
        flat = points_all.reshape(-1, 3)
        ff = model_feedforward(flat, model, effects, rate_hz, lead_samples, positions_m=flat).reshape(points_all.shape)
        ff = ff[:, :exact]
    else:                     # the feed-forward reads back across rows: one each
        ff = np.stack([model_feedforward(r, model, effects, rate_hz, lead_samples, positions_m=p)[:exact]
                       for r, p in zip(ref, points_all)])
    followed = points[:, :max(exact - lead, 0)]
    inside = np.asarray(in_workspace(followed.reshape(-1, 3), model.params, model.limits)).reshape(followed.shape[:2])
    within = (np.isfinite(ff).all(axis=(1, 2)) & (np.abs(ff).max(axis=(1, 2), initial=0.0) <= tc_max)
              & inside.all(axis=1))
    return FirstCommands(ticks, ref, points_all, vels, ff, decel, within)


def stop_commands(ref_counts: np.ndarray, positions_m: np.ndarray, velocities_m_s: np.ndarray, start: int,
                  model: FalconModel, effects: Effects, rate_hz: float, lead_samples: float) -> FirstCommands:
    """:func:`first_commands` along a reference that the run follows from its tick ``start`` on
    (``ref_counts``, ``positions_m``, ``velocities_m_s`` from that tick), for its ticks up to
    where it comes to rest for good (later ones look the last row up: a held goal), the table's
    ticks the run's; ``model``, ``effects``, ``rate_hz`` and ``lead_samples`` as for
    :func:`first_commands`."""
    moving = np.flatnonzero(np.any(velocities_m_s, axis=1))
    ticks = range(min(ref_counts.shape[0], int(moving[-1]) + 2 if moving.size else 1))
    return first_commands(ref_counts, positions_m, velocities_m_s, ticks, model, effects, rate_hz,
                          lead_samples).shifted(start)


def quick_brake(ref_counts: np.ndarray, positions_m: np.ndarray, velocities_m_s: np.ndarray, tick: int,
                model: FalconModel, effects: Effects, rate_hz: float, lead_samples: float, hold_samples: int,
                tc_max: float = BRAKE_TC_MAX, *, workspace: bool = True) -> Brake | None:
    """The loop's brake, with the same arguments as :func:`plan_brake` (``ref_counts``,
    ``positions_m``, ``velocities_m_s``, ``tick``, ``model``, ``effects``, ``rate_hz``,
    ``lead_samples``, ``hold_samples``, ``tc_max``): the hardest of :data:`QUICK_LADDER` times
    the closed-form :func:`start_deceleration` whose feed-forward is within ``tc_max``, the
    first alone (usually the answer: one batch of inverse kinematics and inverse dynamics,
    well under a millisecond), then :data:`QUICK_BATCH` at a time; it starts as
    :func:`first_commands` does when the first is within (:func:`plan_brake` refines it off
    the loop). None when no candidate is within the bound and the workspace (with ``workspace``
    False: the hardest within the bound, wherever its path goes)."""
    search = _BrakeSearch(ref_counts, positions_m, velocities_m_s, tick, model, effects, rate_hz, lead_samples, tc_max)
    lo, hi = DECELERATION_RANGE_M_S2
    if not np.any(search.v0):
        best = search.trial(hi)
        return None if best is None else search.finish(best, hi, hold_samples, workspace)
    decels = np.unique(np.clip(search.guess() * QUICK_LADDER, lo, hi))[::-1]   # hardest first
    for first, end in zip([0, *range(1, decels.size, QUICK_BATCH)], [*range(1, decels.size, QUICK_BATCH), decels.size]):
        batch = decels[first:end]
        for decel, got in zip(batch, search.batch(batch)):
            if got is not None:
                return search.finish(got, float(decel), hold_samples, workspace)
    return None


def continue_brake(ref_counts: np.ndarray, positions_m: np.ndarray, velocities_m_s: np.ndarray, tick: int,
                   model: FalconModel, effects: Effects, rate_hz: float, lead_samples: float, hold_samples: int,
                   *, must_stop: bool = False) -> Brake | None:
    """The rest of a stop from command tick ``tick`` of the reference ``ref_counts`` (with
    ``positions_m``, ``velocities_m_s``, ``model``, ``effects``, ``rate_hz``, ``lead_samples``
    and ``hold_samples`` as for :func:`quick_brake`), off the loop: the quick brake, else (near the workspace's edge) the
    minimum-time one, :func:`plan_brake`. None when no brake within the bound keeps to the
    workspace, unless ``must_stop`` (the reference already brakes and cannot go back to the
    plan): then the quick brake wherever it goes (the workspace guard watches the device)."""
    args = (ref_counts, positions_m, velocities_m_s, tick, model, effects, rate_hz, lead_samples, hold_samples)
    brake = quick_brake(*args) or plan_brake(*args)
    if brake is None and must_stop:
        brake = quick_brake(*args, workspace=False)
    return brake


def joined_stop(ref_counts: np.ndarray, positions_m: np.ndarray, velocities_m_s: np.ndarray, tick: int,
                start: StopStart, rest: Brake, model: FalconModel, effects: Effects, rate_hz: float,
                lead_samples: float) -> Brake:
    """The whole stop from the cancel's command tick ``tick`` of the running reference
    (``ref_counts``, ``positions_m``, ``velocities_m_s``; ``model``, ``effects``, ``rate_hz``,
    ``lead_samples`` as :func:`plan_brake`): the table's first commands ``start``
    (:meth:`FirstCommands.row`) up to ``rest``'s tick (:func:`continue_brake` from them), then
    ``rest``; its deceleration is ``rest``'s (``start``'s when that stopped before ``rest``
    began), its discontinuities those of ``start`` against the running reference, its length
    from the brake's start to the stop."""
    search = _BrakeSearch(ref_counts, positions_m, velocities_m_s, tick, model, effects, rate_hz, lead_samples,
                          BRAKE_TC_MAX)
    h = rest.tick
    ref, points, vels, ff = (np.concatenate([a[:h], b]) for a, b in (
        (start.ref_counts, rest.ref_counts), (start.position_m, rest.position_m),
        (start.velocity_m_s, rest.velocity_m_s), (start.feedforward, rest.feedforward)))
    lead = search.s - tick
    jumps = search.jumps(start.ref_counts[lead], start.feedforward[0])
    if np.any(start.velocity_m_s[h + rest.lead]):    # still moving where the rest's brake starts
        stop_s, decel = (h + rest.lead - lead) / rate_hz + rest.stop_s, rest.deceleration_m_s2
    else:                                             # the first commands' brake stopped before it
        decel = start.deceleration_m_s2
        stop_s = float(np.linalg.norm(start.velocity_m_s[lead])) / decel
    return Brake(tick=tick, lead=lead, ref_counts=ref, position_m=points, velocity_m_s=vels, feedforward=ff,
                 deceleration_m_s2=decel, stop_s=stop_s,
                 stop_counts=rest.stop_counts, position_jump_counts=jumps[0], velocity_jump_counts_s=jumps[1],
                 command_jump=jumps[2], peak_feedforward=float(np.abs(ff).max()))


__all__ = ["Brake", "FirstCommands", "StopStart", "stop_commands", "continue_brake", "joined_stop", "FIRST_BRAKE_TICKS", "brake_points", "brake_profile", "first_commands", "plan_brake", "quick_brake", "start_deceleration", "QUICK_LADDER", "START_MARGIN",
           "BRAKE_TC_MAX", "STOP_HOLD_S"]
