"""Trajectory: a time-stamped end-effector motion with its leg angles, counts and commands.

Arrays have time as the first axis: ``t_s`` (N,), everything else (N, 3). Between two
samples the acceleration is held constant (``acceleration_m_s2[k]`` acts on
[t_k, t_{k+1})), so position and velocity are exact piecewise quadratics/lines: this is the
planner's own transcription, and any dense sampling of another motion approximates it.
Leg angles and encoder counts follow from the position by inverse kinematics; the
feed-forward commands are the planner's (interpolated linearly when resampled, or recomputed
by a model's inverse dynamics).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.kinematics import angles_to_counts, inverse_kinematics
from falcon_plan.model.params import get_params

SCHEMA_VERSION = 1


def _array(name: str, value: Any, shape_tail: tuple[int, ...]) -> np.ndarray:
    arr = np.array(value, dtype=float)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        raise InvalidProblemError(f"trajectory field {name} must have shape (N{''.join(', %d' % s for s in shape_tail)}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidProblemError(f"trajectory field {name} holds NaN or infinite values")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class Trajectory:
    """A planned or sampled motion of the end effector (base frame, SI units).

    Attributes
    ----------
    t_s : (N,) sample times [s], strictly increasing, starting at 0.
    position_m, velocity_m_s, acceleration_m_s2 : (N, 3) end-effector motion.
    commands : (N, 3) feed-forward motor commands Tc (real-valued, command units).
    params_name : the parameter set the leg angles and counts are computed with.
    source : who made it ("casadi", "toppra", "ruckig", "sampled", ...).
    """

    t_s: np.ndarray
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    acceleration_m_s2: np.ndarray
    commands: np.ndarray
    params_name: str = "acra2009"
    source: str = "casadi"
    meta: dict[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        t = _array("t_s", self.t_s, ())
        object.__setattr__(self, "t_s", t)
        for name in ("position_m", "velocity_m_s", "acceleration_m_s2", "commands"):
            arr = _array(name, getattr(self, name), (3,))
            if arr.shape[0] != t.shape[0]:
                raise InvalidProblemError(f"trajectory field {name} has {arr.shape[0]} samples, t_s has {t.shape[0]}")
            object.__setattr__(self, name, arr)
        if t.shape[0] < 2:
            raise InvalidProblemError("a trajectory needs at least 2 samples")
        if np.any(np.diff(t) <= 0):
            raise InvalidProblemError("trajectory times t_s must be strictly increasing")

    def __repr__(self) -> str:
        mm = lambda p: "(" + ", ".join(f"{1e3 * v:.1f}" for v in p) + ")"  # noqa: E731
        return (f"Trajectory({self.source}, {1e3 * self.duration_s:.2f} ms, {len(self.t_s)} samples, "
                f"{mm(self.position_m[0])} -> {mm(self.position_m[-1])} mm)")

    # --- derived --------------------------------------------------------------------------
    @property
    def duration_s(self) -> float:
        """Final time minus start time [s]."""
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def theta1_rad(self) -> np.ndarray:
        """Leg angles [rad], (N, 3), by inverse kinematics."""
        return inverse_kinematics(self.position_m, get_params(self.params_name)).theta1

    @property
    def counts(self) -> np.ndarray:
        """Encoder counts (fractional), (N, 3)."""
        return angles_to_counts(self.theta1_rad, get_params(self.params_name))

    def at_time(self, t: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration at time(s) t [s] (clamped to the ends):
        each of shape t.shape + (3,). Exact for the piecewise-constant acceleration."""
        tq = np.clip(np.asarray(t, dtype=float), self.t_s[0], self.t_s[-1])
        k = np.clip(np.searchsorted(self.t_s, tq, side="right") - 1, 0, len(self.t_s) - 2)
        tau = (tq - self.t_s[k])[..., None]
        acc = self.acceleration_m_s2[k]
        vel = self.velocity_m_s[k] + acc * tau
        pos = self.position_m[k] + self.velocity_m_s[k] * tau + 0.5 * acc * tau * tau
        at_end = (tq >= self.t_s[-1])[..., None]
        pos = np.where(at_end, self.position_m[-1], pos)
        vel = np.where(at_end, self.velocity_m_s[-1], vel)
        acc = np.where(at_end, self.acceleration_m_s2[-1], acc)
        return pos, vel, acc

    def commands_at(self, t: Any) -> np.ndarray:
        """Feed-forward commands at time(s) t [s], linear between samples, (..., 3)."""
        tq = np.clip(np.asarray(t, dtype=float), self.t_s[0], self.t_s[-1])
        return np.stack([np.interp(tq, self.t_s, self.commands[:, i]) for i in range(3)], axis=-1)

    def sample(self, rate_hz: float, model: Any = None) -> "Trajectory":
        """The same motion sampled at ``rate_hz`` from t = 0 to the end (the last sample is
        the final state). With a ``model`` (FalconModel) the commands are recomputed by its
        inverse dynamics, otherwise interpolated."""
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidProblemError(f"rate_hz must be a positive number, got {rate_hz}")
        n = int(math.floor(self.duration_s * rate_hz + 1e-9))
        t = self.t_s[0] + np.arange(n + 1) / rate_hz
        if t[-1] < self.t_s[-1] - 1e-12:
            t = np.append(t, self.t_s[-1])
        pos, vel, acc = self.at_time(t)
        cmd = model.inverse_dynamics(pos, vel, acc) if model is not None else self.commands_at(t)
        return Trajectory(t - t[0], pos, vel, acc, cmd, self.params_name, self.source, dict(self.meta))

    # --- JSON ------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (lists of floats); leg angles and counts included for clients."""
        return {
            "schema_version": SCHEMA_VERSION,
            "params": self.params_name,
            "source": self.source,
            "duration_s": self.duration_s,
            "t_s": self.t_s.tolist(),
            "position_m": self.position_m.tolist(),
            "velocity_m_s": self.velocity_m_s.tolist(),
            "acceleration_m_s2": self.acceleration_m_s2.tolist(),
            "theta1_rad": self.theta1_rad.tolist(),
            "counts": self.counts.tolist(),
            "commands": self.commands.tolist(),
            "meta": self.meta,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Trajectory":
        """Inverse of :meth:`to_dict` (derived fields are ignored and recomputed)."""
        missing = [k for k in ("t_s", "position_m", "velocity_m_s", "acceleration_m_s2", "commands") if k not in data]
        if missing:
            raise InvalidProblemError(f"trajectory JSON lacks field(s) {missing}")
        return cls(data["t_s"], data["position_m"], data["velocity_m_s"], data["acceleration_m_s2"],
                   data["commands"], data.get("params", "acra2009"), data.get("source", "json"),
                   dict(data.get("meta", {})))

    def to_json(self, path: str | Path | None = None) -> str:
        """JSON text; also written to ``path`` if given."""
        text = json.dumps(self.to_dict())
        if path is not None:
            Path(path).write_text(text)
        return text

    @classmethod
    def from_json(cls, text_or_path: str | Path) -> "Trajectory":
        """Read from JSON text or a file path."""
        text = str(text_or_path)
        if not text.lstrip().startswith("{"):
            text = Path(text_or_path).read_text()
        return cls.from_dict(json.loads(text))
