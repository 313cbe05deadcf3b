"""The paper's validation controller: a PD in encoder space (MODEL-CONVENTIONS "Time and
communication").

    v  += alpha (raw - v),   raw = (n_k - n_{k-1}) * rate,   alpha = 1 - exp(-2 pi f_c / rate)
    Tc  = round(kp (n - ref) + kd v + ff),   clamped to +-4096

n are encoder counts, ref the encoder-space setpoint [counts], v the low-passed encoder
velocity [counts/s] (f_c = 50 Hz), ff an optional feed-forward [command units]. Sign: a
positive Tc drives theta1 down (toward smaller counts), so kp (n - ref) with kp > 0 pushes
the leg back toward ref (restoring), and kd v with kd > 0 opposes the motion (the paper prints
"D gain -0.1" in its own sign convention). Rounding is half up (floor(x + 0.5)), the same in
the numpy and the CasADi form.

The law is written once, over an "ops" namespace (:func:`pd_law`), so that the plant's
batched closed-loop path (:meth:`falcon_plan.sim.plant.SimPlant.run_pd`) compiles exactly the
same arithmetic into C.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidParameterError

DEFAULT_KP = 10.0
"""Proportional gain [command units per count]."""
DEFAULT_KD = 0.1
"""Derivative gain [command units per count/s]."""
DEFAULT_VELOCITY_CUTOFF_HZ = 50.0
"""Cut-off of the first-order low-pass on the encoder velocity [Hz]."""
COMMAND_LIMIT = 4096
"""|Tc| never exceeds this (the firmware's range)."""

NUMPY_OPS = SimpleNamespace(floor=np.floor, fmin=np.minimum, fmax=np.maximum)


def velocity_filter_alpha(rate_hz: float, cutoff_hz: float = DEFAULT_VELOCITY_CUTOFF_HZ) -> float:
    """alpha = 1 - exp(-2 pi f_c / rate) of the discrete first-order low-pass."""
    return 1.0 - math.exp(-2.0 * math.pi * cutoff_hz / rate_hz)


def pd_law(n: Any, n_prev: Any, v_prev: Any, ref: Any, ff: Any, kp: Any, kd: Any, alpha: Any,
           rate_hz: Any, limit: Any, ops: SimpleNamespace = NUMPY_OPS) -> tuple[Any, Any]:
    """One PD update, elementwise over the legs: returns (Tc, v).

    n, n_prev [counts]; v_prev [counts/s]; ref [counts]; ff [command units]; Tc is a whole
    number in [-limit, limit] (still a float/SX here).
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
        """Commands (int64, shape (3,)) from the counts read now, the setpoint ref [counts] and
        an optional feed-forward [command units]."""
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


__all__ = ["EncoderPD", "pd_law", "velocity_filter_alpha", "DEFAULT_KP", "DEFAULT_KD",
           "DEFAULT_VELOCITY_CUTOFF_HZ", "COMMAND_LIMIT"]
