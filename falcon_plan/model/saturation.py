"""The device's speed-dependent command limit: the ONE definition of the saturation rule.

The paper (Section 4) found that the motor torque stopped growing past |Tc| = 2500 in static
tests and that the limit lifts once the motor turns (up to the firmware's 4096). The rule the
project uses for it, shared by the simulated plant (:mod:`falcon_plan.sim.plant`) and the
planner's ``limit="device"`` constraint (:mod:`falcon_plan.planning.transcription`)::

    L(w) = static + (full - static) * smoothstep(min(|w| / w_r, 1)),   smoothstep(u) = 3u^2 - 2u^3

w is the motor speed in leg units [rad/s] (the theta1 rate for a rigid drive), ``static`` the
static saturation (``FalconParams.command_saturation``, 2500), ``full`` the firmware's range
(``FalconParams.command_limit``, 4096) and w_r :data:`SATURATION_RELEASE_SPEED_RAD_S`. So a
still motor saturates at 2500, one turning faster than w_r (2 rad/s at the leg, about 3100
counts/s) can use the full 4096, with a smooth blend in between. L is continuously
differentiable in w (smoothstep has zero slope at both ends), so an optimiser can use it.

:func:`speed_limit` works on numpy arrays and on CasADi SX/MX expressions alike.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

from falcon_plan.model.params import FalconParams

SATURATION_RELEASE_SPEED_RAD_S = 2.0
"""Motor speed (in leg units, theta1 rate) above which the static saturation is fully lifted."""


def is_symbolic(x: Any) -> bool:
    """True when ``x`` is a CasADi SX, MX or DM (CasADi is not imported for the question: a
    process that has not loaded it holds no CasADi values)."""
    ca = sys.modules.get("casadi")
    return ca is not None and isinstance(x, (ca.SX, ca.MX, ca.DM))


def speed_limit(speed_rad_s: Any, static: Any, full: Any,
                release_speed_rad_s: Any = SATURATION_RELEASE_SPEED_RAD_S) -> Any:
    """L(w) [command units] at motor speed(s) ``speed_rad_s`` [rad/s, leg units], elementwise.

    ``static``, ``full`` [command units] and ``release_speed_rad_s`` may be numbers or
    symbols (the plant passes them as runtime parameters). Numpy in, numpy out; CasADi in,
    CasADi out.
    """
    if is_symbolic(speed_rad_s) or any(is_symbolic(x) for x in (static, full, release_speed_rad_s)):
        import casadi as ca

        u = ca.fmin(ca.fabs(speed_rad_s) / release_speed_rad_s, 1.0)
    else:
        u = np.minimum(np.abs(np.asarray(speed_rad_s, dtype=float)) / release_speed_rad_s, 1.0)
    return static + (full - static) * u * u * (3.0 - 2.0 * u)


def saturate(command: Any, speed_rad_s: Any, static: Any, full: Any,
             release_speed_rad_s: Any = SATURATION_RELEASE_SPEED_RAD_S) -> Any:
    """The command acting on the motors: ``command`` [command units] clipped to
    +-L(``speed_rad_s``) (elementwise), with ``static``, ``full`` and
    ``release_speed_rad_s`` as in :func:`speed_limit`."""
    lim = speed_limit(speed_rad_s, static, full, release_speed_rad_s)
    if is_symbolic(command) or is_symbolic(lim):
        import casadi as ca

        return ca.fmin(ca.fmax(command, -lim), lim)
    return np.clip(command, -lim, lim)


@dataclass(frozen=True)
class SaturationModel:
    """The numbers of the rule for one device: ``static`` and ``full`` limits [command units]
    and the release speed ``release_speed_rad_s`` w_r [rad/s, leg units], > 0."""

    static: float
    full: float
    release_speed_rad_s: float = SATURATION_RELEASE_SPEED_RAD_S

    @classmethod
    def of(cls, params: FalconParams) -> "SaturationModel":
        """The rule for the parameter set ``params`` (its ``command_saturation`` and
        ``command_limit``; the default release speed)."""
        return cls(float(params.command_saturation), float(params.command_limit))

    def limit(self, speed_rad_s: Any) -> Any:
        """L(``speed_rad_s``) [command units] at motor speed(s) [rad/s, leg units] (numpy or
        CasADi)."""
        return speed_limit(speed_rad_s, self.static, self.full, self.release_speed_rad_s)


__all__ = ["SATURATION_RELEASE_SPEED_RAD_S", "SaturationModel", "saturate", "speed_limit"]
