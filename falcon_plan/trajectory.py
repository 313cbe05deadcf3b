"""Trajectory: a time-stamped end-effector motion with its leg angles, counts and commands.

Arrays have time as the first axis: ``t_s`` (N,), everything else (N, 3). Between two
samples the acceleration is either held constant (``interpolation="constant"``:
``acceleration_m_s2[k]`` acts on [t_k, t_{k+1}), position and velocity are piecewise
quadratics and lines) or varies linearly from one sample's value to the next
(``"linear"``: piecewise cubic positions). Either way :meth:`Trajectory.at_time` is exact for
the planner's own transcription, and any dense sampling of another motion approximates it.
Leg angles and encoder counts follow from the position by inverse kinematics. The commands
are the model's inverse dynamics at the samples; :meth:`Trajectory.sample` recomputes them
from a model, never by interpolating between samples (across an acceleration step that is
off by thousands of command units).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.kinematics import angles_to_counts, inverse_kinematics
from falcon_plan.model.params import get_params

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel

SCHEMA_VERSION = 1
INTERPOLATIONS = ("constant", "linear")
"""How the acceleration varies between two samples (see the module docstring)."""


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
    meta : free-form details (JSON-ready).
    interpolation : "constant" (acceleration held between samples) or "linear" (acceleration
        linear between samples), see :data:`INTERPOLATIONS`.
    """

    t_s: np.ndarray
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    acceleration_m_s2: np.ndarray
    commands: np.ndarray
    params_name: str = "acra2009"
    source: str = "casadi"
    meta: dict[str, Any] = field(default_factory=dict, compare=False)
    interpolation: str = "constant"

    def __post_init__(self) -> None:
        if self.interpolation not in INTERPOLATIONS:
            raise InvalidProblemError(f"trajectory interpolation must be one of {INTERPOLATIONS}, "
                                      f"got {self.interpolation!r}")
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
        each of shape t.shape + (3,). Exact for the trajectory's interpolation."""
        tq = np.clip(np.asarray(t, dtype=float), self.t_s[0], self.t_s[-1])
        k = np.clip(np.searchsorted(self.t_s, tq, side="right") - 1, 0, len(self.t_s) - 2)
        tau = (tq - self.t_s[k])[..., None]
        a0 = self.acceleration_m_s2[k]
        if self.interpolation == "linear":
            jerk = (self.acceleration_m_s2[k + 1] - a0) / (self.t_s[k + 1] - self.t_s[k])[..., None]
        else:
            jerk = np.zeros_like(a0)
        acc = a0 + jerk * tau
        vel = self.velocity_m_s[k] + (a0 + 0.5 * jerk * tau) * tau
        pos = self.position_m[k] + (self.velocity_m_s[k] + (0.5 * a0 + jerk * tau / 6.0) * tau) * tau
        at_end = (tq >= self.t_s[-1])[..., None]
        pos = np.where(at_end, self.position_m[-1], pos)
        vel = np.where(at_end, self.velocity_m_s[-1], vel)
        acc = np.where(at_end, self.acceleration_m_s2[-1], acc)
        return pos, vel, acc

    def commands_at(self, t: Any) -> np.ndarray:
        """The stored commands at time(s) t [s], linear between samples, (..., 3). Only a
        rough picture: across an acceleration step it is far off; use :meth:`sample` with a
        model for commands along the motion."""
        tq = np.clip(np.asarray(t, dtype=float), self.t_s[0], self.t_s[-1])
        return np.stack([np.interp(tq, self.t_s, self.commands[:, i]) for i in range(3)], axis=-1)

    def sample(self, rate_hz: float, model: FalconModel | None = None) -> "Trajectory":
        """The same motion sampled at ``rate_hz`` [Hz] from t = 0 to the end (the last sample
        is the final state), with the commands of ``model`` (a FalconModel, the one the plan
        was made with: its inverse dynamics at every sample; payloads are part of the model's
        effects). Without a model it refuses (InvalidProblemError): commands cannot be
        interpolated between samples across an acceleration step."""
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise InvalidProblemError(f"rate_hz must be a positive number, got {rate_hz}")
        if model is None:
            raise InvalidProblemError(
                "Trajectory.sample needs the model to compute the commands: sample(rate_hz, model) "
                "with the FalconModel the trajectory was planned with")
        if model.params.name != self.params_name:
            raise InvalidProblemError(f"the model's parameters {model.params.name!r} differ from the "
                                      f"trajectory's {self.params_name!r}")
        n = int(math.floor(self.duration_s * rate_hz + 1e-9))
        t = self.t_s[0] + np.arange(n + 1) / rate_hz
        if t[-1] < self.t_s[-1] - 1e-12:
            t = np.append(t, self.t_s[-1])
        pos, vel, acc = self.at_time(t)
        cmd = model.inverse_dynamics(pos, vel, acc)
        return Trajectory(t - t[0], pos, vel, acc, cmd, self.params_name, self.source, dict(self.meta),
                          self.interpolation)

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
            "interpolation": self.interpolation,
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
                   dict(data.get("meta", {})), data.get("interpolation", "constant"))

    def to_json(self, path: str | Path | None = None) -> str:
        """JSON text; also written to ``path`` if given."""
        text = json.dumps(self.to_dict())
        if path is not None:
            Path(path).write_text(text)
        return text

    @classmethod
    def from_json(cls, text_or_path: str | Path) -> "Trajectory":
        """Read from ``text_or_path``: JSON text or a file path."""
        text = str(text_or_path)
        if not text.lstrip().startswith("{"):
            text = Path(text_or_path).read_text()
        return cls.from_dict(json.loads(text))
