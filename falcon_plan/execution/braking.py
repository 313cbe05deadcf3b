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
brake's path is the start of a softer one's). The search: first guess the
plan's own peak acceleration, doubled or halved to a bracket, then bisection; each trial is
one small batch of inverse dynamics (closed-form inverse kinematics, no forward kinematics),
so the whole brake takes about a millisecond or two. The stop point is then held with the
gravity feed-forward.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.lqr import DEFAULT_FEEDBACK_UNITS, model_feedforward
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
    position_m : (m, 3) its points [m, base frame].
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
    compute_s : how long the brake took to compute [s] (set by the executor).
    """

    tick: int
    lead: int
    ref_counts: np.ndarray
    position_m: np.ndarray
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


def brake_profile(p0: np.ndarray, v0: np.ndarray, decel: float, rate_hz: float) -> tuple[np.ndarray, float]:
    """Points (J, 3) [m] on the grid t_j = j / rate_hz, j = 0 .. J - 1, braking from p0 (3,) [m]
    at v0 (3,) [m/s] with deceleration ``decel`` [m/s^2] along v0 until it stops (the last
    sample at or after the stop), and the brake's length [s]."""
    speed = float(np.linalg.norm(v0))
    t_stop = speed / decel
    t = np.minimum(np.arange(int(math.ceil(t_stop * rate_hz - 1e-9)) + 1) / rate_hz, t_stop)[:, None]
    direction = v0 / speed if speed > 0 else np.zeros(3)
    return p0 + v0 * t - 0.5 * decel * direction * t * t, t_stop


def plan_brake(ref_counts: np.ndarray, positions_m: np.ndarray, velocities_m_s: np.ndarray, tick: int,
               model: FalconModel, effects: Effects, rate_hz: float, lead_samples: float, hold_samples: int,
               tc_max: float = BRAKE_TC_MAX) -> Brake | None:
    """The brake for a run cancelled at command tick ``tick``: ``ref_counts`` (n, 3) [counts] is the
    running reference, ``positions_m`` (n, 3) [m] and ``velocities_m_s`` (n, 3) [m/s] its planned
    points and velocities; ``model`` with ``effects`` (the controller's) gives the feed-forward
    at the controller's ``rate_hz`` and command delay ``lead_samples``; the stop is held
    ``hold_samples``. None when no brake within ``tc_max`` keeps the path in the workspace
    (then the running plan is the stop)."""
    n_total = ref_counts.shape[0]
    lead = int(math.ceil(lead_samples - 1e-9))
    s = min(tick + lead, n_total - 1)
    p0, v0 = positions_m[s], velocities_m_s[s]
    encoder = effects.encoder_params(model.params)
    pad = lead + 3                                            # hold samples the feed-forward reads

    def trial(decel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        pos, t_stop = brake_profile(p0, v0, decel, rate_hz)
        braking = angles_to_counts(inverse_kinematics(pos, model.params).theta1, encoder)
        ref = np.concatenate([ref_counts[tick:s], braking, np.repeat(braking[-1:], pad, axis=0)])
        points = np.concatenate([positions_m[tick:s], pos, np.repeat(pos[-1:], pad, axis=0)])
        ff = model_feedforward(ref, model, effects, rate_hz, lead_samples, positions_m=points)
        if np.abs(ff).max() > tc_max:
            return None
        return ref, points, ff, t_stop

    lo, hi = DECELERATION_RANGE_M_S2
    if not np.any(v0):                                        # at rest: nothing to brake
        best, best_a = trial(hi), hi
    else:
        # first guess: the plan's own peak acceleration (feasible there); double or halve it
        # to a feasible a below an infeasible 2a, then bisect between them
        accel = np.diff(velocities_m_s, axis=0) * rate_hz
        best_a = min(max(float(np.sqrt((accel * accel).sum(axis=1)).max()), lo), hi)
        best = trial(best_a)
        if best is not None:
            while best_a * 2.0 <= hi and (got := trial(best_a * 2.0)) is not None:
                best, best_a = got, best_a * 2.0
        while best is None and best_a * 0.5 >= lo:
            best_a *= 0.5
            best = trial(best_a)
        if best is None:
            return None
        low, high = best_a, best_a * 2.0
        while high - low > DECELERATION_RESOLUTION * low:
            mid = math.sqrt(low * high)
            got = trial(mid)
            if got is None:
                high = mid
            else:
                low, best, best_a = mid, got, mid
    if best is None:
        return None
    ref, points, ff, t_stop = best
    # a harder brake's path is a part of a softer one's: one workspace check, of the hardest
    if not np.all(in_workspace(points[lead:], model.params, model.limits)):
        return None
    more = max(0, hold_samples - pad)
    ref = np.concatenate([ref, np.repeat(ref[-1:], more, axis=0)])
    points = np.concatenate([points, np.repeat(points[-1:], more, axis=0)])
    ff = np.concatenate([ff, np.repeat(ff[-1:], more, axis=0)])
    lo_w = max(0, tick - 2)
    old_ff = model_feedforward(ref_counts[lo_w:tick + lead + 4], model, effects, rate_hz, lead_samples,
                               positions_m=positions_m[lo_w:tick + lead + 4])[tick - lo_w]
    # the brake's start against the plan at s, each from its own computation: the counts by
    # inverse kinematics against the plan's counts, the leg rates by the Jacobian of the
    # brake's initial velocity against the difference quotient of the plan's counts
    at = lambda j: ref_counts[min(max(s + j, 0), n_total - 1)]  # noqa: E731
    plan_rate = (8.0 * (at(1) - at(-1)) - (at(2) - at(-2))) * (rate_hz / 12.0)  # fourth order
    brake_rate = jacobian(p0, model.params) @ v0 * encoder.counts_per_rad
    return Brake(tick=tick, lead=s - tick, ref_counts=ref, position_m=points, feedforward=ff,
                 deceleration_m_s2=float(best_a), stop_s=float(t_stop), stop_counts=ref[-1].copy(),
                 position_jump_counts=float(np.abs(ref[s - tick] - ref_counts[s]).max()),
                 velocity_jump_counts_s=float(np.abs(brake_rate - plan_rate).max()),
                 command_jump=float(np.abs(ff[0] - old_ff).max()), peak_feedforward=float(np.abs(ff).max()))


__all__ = ["Brake", "brake_profile", "plan_brake", "BRAKE_TC_MAX", "STOP_HOLD_S"]
