"""Excitation trajectories for identification experiments.

Each kind excites different effects (and a good training log mixes them):

- ``fourier``: a sum of sinusoids per Cartesian axis (0.3-2.5 Hz, random phases): rich in
  speed and acceleration together (inertia, payload, motor gain, Kd sign, viscous friction);
- ``holds``: still poses joined by smooth moves: the gravity load in many postures (tilt,
  payload, motor gain) and stiction at the holds;
- ``sweep``: slow constant-speed sweeps with reversals: friction (Coulomb, Stribeck, viscous)
  and cable slop at every reversal;
- ``p2p``: fast minimum-jerk point-to-point moves: high acceleration (inertia, delay,
  compliance);
- ``reversals``: short fast oscillations, up and down then in and out, that take every leg's
  drive load through zero. In the other designs gravity keeps each leg's load on one side
  (on a 6 s ``mixed`` log the commands changed sign 0-6 times a leg), so the cable's slop is
  never crossed and backlash is a constant offset, invisible beside the replay's noise on a
  log recorded through the USB path;
- ``mixed``: sweep, fourier, reversals (half as long), holds and p2p segments, one after the
  other (:data:`MIXED_PARTS`).

Every trajectory starts and ends with a 0.5 s hold at its first point, stays in the workspace
(checked), and is returned as a :class:`~falcon_plan.trajectory.Trajectory` sampled at
the control rate (feed-forward commands from the nominal inverse dynamics), whose encoder
counts are the reference the PD tracks.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Callable

import numpy as np

from falcon_plan.errors import InvalidParameterError

if TYPE_CHECKING:  # the model loads when a design is made (the command line reads KINDS only)
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.trajectory import Trajectory

KINDS = ("fourier", "holds", "sweep", "p2p", "reversals", "mixed")
CENTRE_M = np.array([0.0, 0.0, 0.125])
"""Centre of the excitation [m]: in the middle of the reachable z range."""
RADIUS_M = 0.025
"""Largest excursion from the centre per axis [m] (the workspace is about +-40 mm here)."""
SETTLE_S = 0.5
REVERSAL_AMPLITUDE_M = 0.003
REVERSAL_HZ = 8.0
"""Amplitude [m] and frequency [Hz] of the ``reversals`` oscillations: 7.6 m/s^2 at the peaks,
which swings every leg's nominal command through zero (from a holding load of 180-710 of the
2500 command units) and stays below 1800 in magnitude. Chosen on live logs (the independent
world inside the emulated Falcon, a stress process beside it, three draws each) with the
reversals as a fifth part of ``mixed``: at 8 Hz and 3 mm, backlash, cable compliance, a
reversed Kd and a hidden dead band were named right in 17 of 18; at 12 Hz and 1.3 mm (the same
swing at two thirds of the speed) in 9 of 18."""
REVERSAL_AXES = (1, 2)
"""Axes of the ``reversals`` oscillations in turn: y (up: against gravity) and z; along x,
leg 1's load does not change sign."""
REVERSAL_RAMP_S = 0.1
"""Minimum-jerk ramp [s] in and out of each axis' oscillation."""
MIXED_PARTS = (("sweep", 1.0), ("fourier", 1.0), ("reversals", 0.5), ("holds", 1.0), ("p2p", 1.0))
"""The parts of ``mixed`` in order, with their shares of its length. Without the reversals,
live logs (the independent world inside the emulated Falcon, a stress process beside it, three
draws) named backlash, cable compliance, a reversed Kd and a hidden dead band right in 10 of 18
cases; with them, in 17 of 18. Half a share is enough: at 8 Hz the oscillation takes each
leg's load through zero 16 times a second. Near the paper's PD's resonance a nominal device
behind framed USB rings in that stretch where its replay does not; a command delay therefore
has to show everywhere, not only there (:data:`~.checks.EVERYWHERE_EFFECTS`)."""


def _min_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk blend 10 s^3 - 15 s^4 + 6 s^5 of s in [0, 1]."""
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10 - 15 * s + 6 * s * s)


def _random_point(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return CENTRE_M + rng.uniform(-1, 1, 3) * RADIUS_M * scale


def _fourier(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    freqs = np.array([0.3, 0.55, 0.9, 1.4, 2.1, 2.5])
    out = np.zeros((t.size, 3))
    for axis in range(3):
        amp = rng.uniform(0.4, 1.0, freqs.size) / freqs ** 0.7
        amp *= RADIUS_M / amp.sum()
        phase = rng.uniform(0, 2 * math.pi, freqs.size)
        # sin(phase + 2 pi f t) - sin(phase): zero at t = 0 so the motion starts at the centre
        out[:, axis] = (amp[None, :] * (np.sin(phase[None, :] + 2 * math.pi * freqs[None, :] * t[:, None])
                                        - np.sin(phase)[None, :])).sum(axis=1)
    ramp = _min_jerk(t / 0.5) * _min_jerk((t[-1] - t) / 0.5)
    return CENTRE_M + out * ramp[:, None]


def _segments(t: np.ndarray, step: Callable[[np.ndarray], tuple[np.ndarray, float, float]]) -> np.ndarray:
    """Poses joined by minimum-jerk moves, from the centre back to the centre by t[-1].

    ``step(previous_point)`` gives (hold before the move [s], move duration [s], next point).
    Moves are added while they fit; the last one returns to the centre in the time left.
    """
    points, holds, moves = [CENTRE_M.copy()], [], []
    total, end = 0.0, float(t[-1])
    while True:
        hold, move, point = step(points[-1])
        if total + hold + move + 0.6 > end:
            break
        holds.append(hold)
        moves.append(move)
        points.append(point)
        total += hold + move
    holds.append(0.05)
    moves.append(max(0.3, end - total - 0.1))
    points.append(CENTRE_M.copy())
    out = np.tile(points[0], (t.size, 1))
    t0 = 0.0
    for i in range(len(points) - 1):
        t0 += holds[i]
        s = _min_jerk((t - t0) / moves[i])
        active = t >= t0
        out[active] = points[i] + (points[i + 1] - points[i]) * s[active, None]
        t0 += moves[i]
    return out


def _holds(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return _segments(t, lambda _: (rng.uniform(0.4, 0.8), rng.uniform(0.3, 0.5), _random_point(rng)))


def _sweep(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    state = {"direction": None}

    def step(previous: np.ndarray) -> tuple[float, float, np.ndarray]:
        # alternate: out along a random direction, then through the centre to the other side
        if state["direction"] is None:
            d = rng.normal(size=3)
            state["direction"] = d / np.linalg.norm(d)
            target = CENTRE_M + state["direction"] * RADIUS_M * rng.uniform(0.6, 1.0)
        else:
            target = CENTRE_M - state["direction"] * RADIUS_M * rng.uniform(0.6, 1.0)
            state["direction"] = None
        speed = rng.uniform(0.02, 0.06)                                 # slow: 2-6 cm/s
        return 0.05, max(0.4, float(np.linalg.norm(target - previous)) / speed), target

    return _segments(t, step)


def _p2p(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return _segments(t, lambda _: (rng.uniform(0.15, 0.3), rng.uniform(0.15, 0.25), _random_point(rng)))


def _reversals(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Oscillations about the centre along each of :data:`REVERSAL_AXES` in turn, ramped in and
    out, each starting at a random phase."""
    out = np.tile(CENTRE_M, (t.size, 1))
    edges = np.linspace(0.0, float(t[-1]) if t.size else 0.0, len(REVERSAL_AXES) + 1)
    for axis, lo, hi in zip(REVERSAL_AXES, edges[:-1], edges[1:]):
        sel = (t >= lo) & (t <= hi)
        local, length = t[sel] - lo, hi - lo
        ramp = _min_jerk(local / REVERSAL_RAMP_S) * _min_jerk((length - local) / REVERSAL_RAMP_S)
        phase = rng.uniform(0, 2 * math.pi)
        out[sel, axis] += REVERSAL_AMPLITUDE_M * ramp * np.sin(phase + 2 * math.pi * REVERSAL_HZ * local)
    return out


def _mixed(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    shares = np.array([share for _, share in MIXED_PARTS])
    edges = np.concatenate([[0.0], np.cumsum(shares) / shares.sum() * t[-1]])
    out = np.tile(CENTRE_M, (t.size, 1))
    for (kind, _), lo, hi in zip(MIXED_PARTS, edges[:-1], edges[1:]):
        sel = (t >= lo) & (t <= hi)
        out[sel] = _DESIGNS[kind](t[sel] - lo, rng)
    return out


_DESIGNS: dict[str, Callable[[np.ndarray, np.random.Generator], np.ndarray]] = {
    "fourier": _fourier, "holds": _holds, "sweep": _sweep, "p2p": _p2p, "reversals": _reversals, "mixed": _mixed}


def design_trajectory(kind: str, duration_s: float = 8.0, seed: int = 0, rate_hz: float = 800.0,
                      model: FalconModel | None = None) -> Trajectory:
    """An excitation trajectory of ``kind`` (see :data:`KINDS`) lasting ``duration_s`` [s]
    plus a 0.5 s settling hold at each end, sampled at ``rate_hz`` [Hz], reproducible from
    ``seed``. Feed-forward commands come from ``model``'s inverse dynamics (nominal default).
    """
    if kind not in _DESIGNS:
        raise InvalidParameterError(f"unknown trajectory kind {kind!r}; choose one of {', '.join(KINDS)}")
    if not (math.isfinite(duration_s) and 1.0 <= duration_s <= 600.0):
        raise InvalidParameterError(f"duration must be in [1, 600] s, got {duration_s}")
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise InvalidParameterError(f"rate must be a positive number of Hz, got {rate_hz}")
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.workspace import require_in_workspace
    from falcon_plan.trajectory import Trajectory

    model = model or FalconModel()
    rng = np.random.default_rng(seed)
    h = 1.0 / rate_hz
    n_core = int(round(duration_s * rate_hz)) + 1
    core = _DESIGNS[kind](np.arange(n_core) * h, rng)
    settle = np.tile(core[0], (int(round(SETTLE_S * rate_hz)), 1))
    pos = np.vstack([settle, core, np.tile(core[-1], (int(round(SETTLE_S * rate_hz)), 1))])
    require_in_workspace(pos, model.params, model.limits)
    vel = np.gradient(pos, h, axis=0)
    acc = np.gradient(vel, h, axis=0)
    t = np.arange(pos.shape[0]) * h
    commands = model.inverse_dynamics(pos, vel, acc)
    return Trajectory(t, pos, vel, acc, commands, model.params.name, f"excitation-{kind}",
                      {"kind": kind, "seed": seed, "rate_hz": rate_hz})
