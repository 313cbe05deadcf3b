"""The command bound a plan must respect: a constant tc_max or the device's speed-dependent
limit, minus a reserve kept free for feedback.

- ``kind="constant"``: |Tc| <= tc_max - reserve everywhere.
- ``kind="device"``: |Tc| <= L(w_s) - reserve, L the device's speed-dependent saturation
  (:mod:`falcon_plan.model.saturation`, the rule the simulated plant applies). The device
  sets L once per control period from the speed at the period's start, so the plan uses the
  lowest leg speed the period can start with: w_s = max(|w| - |dw/dt| T, 0), w = J(p) v the
  leg (motor) speeds [rad/s] of the planned motion, dw/dt = J a + (dJ/dt) v, and
  T = :data:`SPEED_SAMPLE_PERIOD_S`. This matters where a leg reverses: there L dips to its
  static value for ~2 ms, about two control periods. At rest L = 2500, so a plan that starts
  from rest starts within what the device gives there, and uses up to 4096 once moving.

The reserve [command units] is what the executor's PD may add on top of the feed-forward
(its P and D terms react to tracking errors of a few counts: 10 units per count, plus
damping) without the *executed* command passing the device's limit.
"""
from __future__ import annotations

import dataclasses
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.model.saturation import SaturationModel, is_symbolic

if TYPE_CHECKING:  # CasADi and the dynamics load when a bound is evaluated, not on import
    import casadi as ca

    from falcon_plan.model.dynamics import FalconModel

LIMIT_KINDS = ("constant", "device")
"""Values of PlanOptions.limit."""
SPEED_SAMPLE_PERIOD_S = 1.0 / 800.0
"""The longest control period the device's limit is held over [s] (800 Hz, the slowest rate
the project runs; at 1 kHz the bound is slightly conservative)."""
RATE_SMOOTHING_RAD_S2 = 10.0
"""|dw/dt| enters as sqrt(rate^2 + this^2) [rad/s^2] (planned leg accelerations are hundreds
of rad/s^2): smooth where a leg's acceleration changes sign."""
TIGHTEN_SAFETY = 1.5
"""A repair re-solve's bound is tightened by this multiple of the overshoot it repairs
(:meth:`CommandBound.tightened`): where the excess is additive (a friction torque changing
sign between two constraint points) it comes back about as large, and half as much again
leaves room for the re-solve's own between-node error."""


@dataclass(frozen=True)
class CommandBound:
    """|Tc| <= allowed(p, v) along a plan (see the module docstring).

    Attributes
    ----------
    kind : "constant" or "device".
    tc_max : the constant limit [command units] (kind "constant").
    reserve : command units kept free for feedback, subtracted from the limit.
    saturation : the device's rule (kind "device"; also what "executed within the device
        limit" is measured against).
    """

    kind: str
    tc_max: float
    reserve: float
    saturation: SaturationModel

    @property
    def at_rest(self) -> float:
        """The allowed |Tc| of a still device [command units] (holding, guesses, references)."""
        base = self.tc_max if self.kind == "constant" else self.saturation.static
        return base - self.reserve

    def describe(self) -> str:
        """e.g. ``device limit 2500..4096 - 150 reserve`` (for reports)."""
        if self.kind == "constant":
            text = f"constant {self.tc_max:g}"
        else:
            text = f"device limit {self.saturation.static:g}..{self.saturation.full:g}"
        return text + (f" - {self.reserve:g} reserve" if self.reserve else "")

    def tightened(self, excess_ratio: float) -> "CommandBound":
        """This bound with the reserve raised by what a plan that reached ``excess_ratio``
        (> 1, its worst |Tc| over this bound) overshot, with :data:`TIGHTEN_SAFETY` on top:
        the bound a repair re-solve imposes (its plan is still checked against this one)."""
        extra = TIGHTEN_SAFETY * max(excess_ratio - 1.0, 0.0) * self.at_rest
        return dataclasses.replace(self, reserve=self.reserve + extra)

    def device_limit(self, model: FalconModel, p: Any, v: Any, a: Any = None) -> np.ndarray:
        """The device's limit along a motion of ``model`` [command units], (n, 3), no
        reserve: L(w) at points p [m] and velocities v [m/s] (n, 3); with accelerations ``a``
        (n, 3) [m/s^2], L(w_s), the limit of a control period that contains this point (see
        the module docstring)."""
        p, v = np.atleast_2d(np.asarray(p, float)), np.atleast_2d(np.asarray(v, float))
        acc = np.zeros_like(v) if a is None else np.atleast_2d(np.asarray(a, float))
        speed, rate = leg_motion(model, p, v, acc)
        return np.asarray(self.saturation.limit(speed if a is None else sampled_speed(speed, rate)))

    def allowed(self, model: FalconModel, p: Any, v: Any, a: Any) -> np.ndarray:
        """The bound on |Tc| [command units], (n, 3), of ``model``'s device at points p [m],
        velocities v [m/s] and accelerations a [m/s^2] (n, 3 each)."""
        n = np.atleast_2d(np.asarray(p, float)).shape[0]
        if self.kind == "constant":
            return np.full((n, 3), self.tc_max - self.reserve)
        return self.device_limit(model, p, v, a) - self.reserve


def sampled_speed(speed: Any, rate: Any) -> Any:
    """The lowest |speed| [rad/s] a control period containing this instant can start with,
    max(|w| - |dw/dt| T, 0), w = ``speed`` [rad/s], dw/dt = ``rate`` [rad/s^2],
    T = :data:`SPEED_SAMPLE_PERIOD_S` (numpy arrays or CasADi expressions)."""
    if is_symbolic(speed):
        import casadi as ca

        # |rate| smoothed (an upper bound, so still conservative) to keep the NLP smooth
        change = ca.sqrt(rate * rate + RATE_SMOOTHING_RAD_S2 ** 2) * SPEED_SAMPLE_PERIOD_S
        return ca.fmax(ca.fabs(speed) - change, 0.0)
    change = np.sqrt(rate * rate + RATE_SMOOTHING_RAD_S2 ** 2) * SPEED_SAMPLE_PERIOD_S
    return np.maximum(np.abs(speed) - change, 0.0)


def leg_motion_expressions(model: FalconModel, p: Any, v: Any, a: Any, eff: Any) -> tuple[Any, Any]:
    """Leg speeds w = J(p) v [rad/s] and their rates dw/dt = J a + (dJ/dt) v [rad/s^2] of
    ``model`` (CasADi expressions of p [m], v [m/s], a [m/s^2] and the effect vector ``eff``)."""
    import casadi as ca

    w = model.functions.jacobian(p, eff) @ v
    return w, ca.jtimes(w, p, v) + model.functions.jacobian(p, eff) @ a


LEG_MOTION_CHUNK = 64
"""Points per call of the compiled leg-motion batch."""
LEG_MOTION_FLAGS = ("-O3", "-march=native")
"""Compiler options of the compiled leg-motion batch (those of the model's batches)."""
_LEG_MOTION: dict[Any, tuple[Any, bool, threading.Lock]] = {}
"""Leg-motion batches per (parameters, limits, effect count): compiled once per machine
(or, without a compiler, the CasADi Function), whether compiled, and the lock that guards
their buffers."""
_LEG_MOTION_LOCK = threading.Lock()


def leg_motion(model: FalconModel, p: np.ndarray, v: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leg speeds w [rad/s] and their rates dw/dt [rad/s^2], (n, 3) each, of ``model`` at
    points p [m], velocities v [m/s] and accelerations a [m/s^2] (n, 3 each): a compiled loop
    over chunks of :data:`LEG_MOTION_CHUNK` points (~0.2 ms for a plan's nodes; CasADi's own
    map took ~25 ms, built anew for every number of points)."""
    n_eff = model.functions.expressions.eff.numel()
    key = (model.params, model.limits, n_eff)
    with _LEG_MOTION_LOCK:
        if key not in _LEG_MOTION:
            import casadi as ca

            from falcon_plan.compiled import compiled_points

            sp, sv, sa = ca.SX.sym("p", 3), ca.SX.sym("v", 3), ca.SX.sym("a", 3)
            seff = ca.SX.sym("eff", n_eff)
            fn = ca.Function("leg_motion", [sp, sv, sa, seff],
                             [ca.vertcat(*leg_motion_expressions(model, sp, sv, sa, seff))])
            compiled = compiled_points(fn, "leg_motion", LEG_MOTION_CHUNK, LEG_MOTION_FLAGS)
            _LEG_MOTION[key] = (compiled or fn, compiled is not None, threading.Lock())
    batch, is_compiled, lock = _LEG_MOTION[key]
    p, v, a = (np.atleast_2d(np.asarray(x, float)) for x in (p, v, a))
    if is_compiled:
        with lock:
            batch.inputs[3][:] = model.effect_vector
            out = batch.map_columns([p.T, v.T, a.T])[0]
    else:  # no compiler: the virtual machine
        out = np.asarray(batch.map(len(p))(p.T, v.T, a.T, np.repeat(model.effect_vector[:, None], len(p), axis=1)))
    return out[:3].T, out[3:].T


def device_limit_rows(model: FalconModel, p: ca.SX, v: ca.SX, a: ca.SX, eff: ca.SX) -> ca.SX:
    """L(w_s) of ``model``'s device as a CasADi expression (3 rows) of the point p [m],
    velocity v [m/s], acceleration a [m/s^2] and effect vector ``eff``, for the NLP's
    device-limit constraint."""
    w, rate = leg_motion_expressions(model, p, v, a, eff)
    return SaturationModel.of(model.params).limit(sampled_speed(w, rate))


LIMIT_NEWTON_STEPS = 2
"""Newton steps of :func:`command_on_limit` after one fixed-point step from the limit at rest
(at random moving states: 0.02 command units off after one step, < 1e-6 after two)."""


def command_on_limit(model: FalconModel, saturation: SaturationModel, p: ca.SX, v: ca.SX, sign: ca.SX,
                     eff: ca.SX, reserve: ca.SX, delta: ca.SX) -> ca.SX:
    """The command that rides the device's limit ``saturation`` of ``model``,
    u = sign * (L(w_s) - reserve) + delta (elementwise, 3 rows) [command units], as a CasADi
    expression of the point p [m],
    velocity v [m/s], sign in [-1, 1] per leg (+-1 on the limit, between on a command ramp),
    the effect vector ``eff``, the ``reserve`` and an offset ``delta`` [command units].

    It is implicit: w_s depends on dw/dt, so on the acceleration the command itself causes
    (``model``'s forward dynamics, affine in u): solved by :data:`LIMIT_NEWTON_STEPS` Newton
    steps (the 3x3 system written out), which keeps it a smooth expression for the
    switching-time solve's RK4 step and its derivatives."""
    import casadi as ca

    n_eff = eff.numel()
    ps, vs, us, ss, es = (ca.SX.sym(n, k) for n, k in (("p", 3), ("v", 3), ("u", 3), ("s", 3), ("eff", n_eff)))
    rs, ds = ca.SX.sym("reserve"), ca.SX.sym("delta", 3)
    w, rate = leg_motion_expressions(model, ps, vs, model.functions.forward_dynamics(ps, vs, us, es), es)
    residual = us - ss * (saturation.limit(sampled_speed(w, rate)) - rs) - ds
    equations = ca.Function("command_on_limit_equations", [us, ps, vs, ss, es, rs, ds],
                            [residual, ca.jacobian(residual, us)])
    u = sign * (saturation.static - reserve) + delta
    u = u - equations(u, p, v, sign, eff, reserve, delta)[0]  # a fixed-point step
    for _ in range(LIMIT_NEWTON_STEPS):
        r, jac = equations(u, p, v, sign, eff, reserve, delta)
        u = u - ca.solve(jac, r)
    return u


__all__ = ["CommandBound", "command_on_limit", "LIMIT_KINDS", "SPEED_SAMPLE_PERIOD_S", "device_limit_rows",
           "leg_motion", "leg_motion_expressions", "sampled_speed"]
