"""The inverse-dynamics residual and its fit (the CasADi code of the discrepancy package).

For a log with estimated motion (p, v, a) and logged commands Tc, a model with smooth-effect
vector ``eff`` and a transport delay of ``delay`` samples predicts

    r_k(theta) = Tc_{k - delay} - ID(p_k, v_k, a_k, eff(theta))        [command units]

for every valid sample k and leg. The regressor columns dr/dtheta = -dID/deff come from one
CasADi Function (inverse dynamics and its Jacobian with respect to ``eff``), mapped over the
samples. A fit evaluates them hundreds of times at new ``eff``, so a problem reads the
rigid-body part off that Function once (:class:`RigidTerms`: the leg torques are affine in the
link-mass scale, the payload and the gravity vector) and each evaluation after that composes
it with the friction and motor laws (compiled, small): the same numbers to rounding, for
about a third of the cost. Friction, payload and Stribeck amplitude are linear in ``eff``;
motor gain, Kd sign, tilt and the Stribeck velocity are not, so the fit is Gauss-Newton: each step solves the
linearised, *bounded* least-squares problem with OSQP (a QP with box constraints), which is
exact in one step for the linear parameters.

Parameter uncertainties are sqrt(diag(s^2 (J^T J)^-1)) with s^2 = RSS / (n - k), inflated by
the residual's integrated autocorrelation time (the filtered, closed-loop residual is not
white: ``n / inflation`` samples carry independent information).
"""
from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import osqp
import scipy.sparse as sp

from falcon_plan.discrepancy.library import CandidateEffect, EffectParameter, clip_to_bounds
from falcon_plan.discrepancy.motion import MotionEstimate
from falcon_plan.errors import FalconPlanError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import LEG_COULOMB_FIELDS, LEG_GAIN_FIELDS, SMOOTH_EFFECT_FIELDS
from falcon_plan.model.params import FalconParams
from falcon_plan.model.symbolic import (N_EFFECTS, dynamics_functions, friction_torque, gravity_vector,
                                        motor_torque_per_command)
from falcon_plan.model.workspace import WorkspaceLimits
from falcon_plan.compiled import BufferedFunction, build_library, compiled_points
from falcon_plan.compiled.build import library_by_recipe, recipe_file

LOG = logging.getLogger(__name__)

LINEAR_FIELDS = frozenset({"coulomb_Nm", "viscous_Nms", "stribeck_Nm", "payload_kg", "link_mass_scale",
                           *LEG_COULOMB_FIELDS})
"""Smooth-effect fields in which the inverse dynamics is exactly linear (one step fits them)."""
SATURATION_MARGIN = 0.95
"""Samples with an acting command above this fraction of the static saturation are skipped."""
SLOW_LEG_RAD_S = 0.05
"""A leg slower than this [rad/s] is left out of the residual at that sample: at rest a
friction torque can take any value up to break-away (stiction), which no smooth friction law
predicts, so such samples say nothing reliable about the dynamics once friction is present."""
GN_MAX_ITERATIONS = 15
GN_STEP_TOLERANCE = 1e-5
"""Gauss-Newton stops when every step is below this fraction of the parameter's scale."""


class IdentificationError(FalconPlanError, RuntimeError):
    """A fit could not be carried out (too few valid samples, singular regressors)."""


CHUNK_ROWS = 512
"""Samples per call of the compiled inverse-dynamics-and-Jacobian function."""

_evaluators: dict[tuple, "BufferedFunction"] = {}
EVALUATOR_SOURCES = ("discrepancy/identify.py", "compiled/inplace.py", "compiled/build.py", "model")
"""The sources the inverse-dynamics evaluator is made from (relative to the package): a change
in any of them is a new recipe (:func:`_chunk_evaluator`)."""


@lru_cache(maxsize=None)
def _id_jacobian(params: FalconParams, limits: WorkspaceLimits) -> ca.Function:
    """The symbolic Function of :func:`_chunk_evaluator` for the parameter set ``params``."""
    fns = dynamics_functions(params, limits)
    ex = fns.expressions
    tc = fns.inverse_dynamics(ex.p, ex.v, ex.a, ex.eff)
    # dense: the buffers hold every entry (per-leg effects make the Jacobian structurally sparse)
    one = ca.Function("id_jacobian", [ex.p, ex.v, ex.a, ex.eff], [tc, ca.densify(ca.jacobian(tc, ex.eff))],
                      {"cse": True})
    mapped = one.map("id_jacobian_map", "serial", CHUNK_ROWS, [3], [])
    inputs = mapped.mx_in()
    return ca.Function(f"falcon_id_jacobian_{params.name}_{CHUNK_ROWS}", inputs, mapped.call(inputs))


def _chunk_evaluator(model: FalconModel) -> "BufferedFunction":
    """Compiled (C, cached per machine) Function of CHUNK_ROWS samples: (p, v, a (3 x C), eff)
    -> (Tc (3 x C), dTc/deff (3 x n_eff C)). A later process finds the library by its recipe
    (:func:`~falcon_plan.compiled.build.library_by_recipe`) and loads it without building the
    symbolic Jacobian (0.1 s a process). Falls back to the CasADi virtual machine without a
    compiler."""
    key = (model.params, model.limits)
    if key not in _evaluators:
        def build() -> tuple[Path | None, str]:
            fn = _id_jacobian(*key)
            return build_library(fn), fn.name()

        built = library_by_recipe(recipe_file("falcon_id_jacobian", EVALUATOR_SOURCES, *key, CHUNK_ROWS), build)
        _evaluators[key] = BufferedFunction(_id_jacobian(*key)) if built is None else \
            BufferedFunction(ca.external(built[1], str(built[0])), library=built[0])
    return _evaluators[key]


LOADS_FLAGS = ("-O2",)
_LOADS_LOCK = threading.Lock()


@dataclass(frozen=True)
class _Loads:
    """The friction and motor laws at given leg speeds, compiled over CHUNK_ROWS samples
    (``function``: (w (3,) [rad/s], eff) -> one column: friction torque f (3) [N.m], vec of
    df/deff over ``friction_columns``, motor torque per command t (3) [N.m per command unit],
    vec of dt/deff over ``motor_columns``; the CasADi Function itself without a compiler)."""

    function: "BufferedFunction | ca.Function"
    friction_columns: np.ndarray
    motor_columns: np.ndarray


_loads: dict[FalconParams, _Loads] = {}


def _depends_on(expr: ca.SX, eff: ca.SX) -> np.ndarray:
    """The entries of ``eff`` that ``expr`` depends on (structurally)."""
    return np.unique(np.array(ca.jacobian(expr, eff).sparsity().get_col(), dtype=int))


def _loads_evaluator(params: FalconParams) -> _Loads:
    """:class:`_Loads` of :func:`~falcon_plan.model.symbolic.friction_torque` and
    :func:`~falcon_plan.model.symbolic.motor_torque_per_command` for ``params`` (built once)."""
    if params not in _loads:
        w, eff = ca.SX.sym("w", 3), ca.SX.sym("eff", N_EFFECTS)
        f, t = friction_torque(w, eff), motor_torque_per_command(w, eff, params)
        fc, mc = _depends_on(f, eff), _depends_on(t, eff)
        # each Jacobian as vec of its transpose: leg-major, so that a sample's row reads (3, k) in order
        dense = lambda e, cols: ca.vec(ca.densify(ca.jacobian(e, eff)[:, [int(c) for c in cols]]).T)  # noqa: E731
        fn = ca.Function("loads", [w, eff], [ca.vertcat(f, dense(f, fc), t, dense(t, mc))])
        compiled = compiled_points(fn, f"id_loads_{params.name}", CHUNK_ROWS, LOADS_FLAGS)
        _loads[params] = _Loads(compiled if compiled is not None else fn, fc, mc)
    return _loads[params]


@lru_cache(maxsize=None)
def _gravity_function() -> tuple[ca.Function, np.ndarray]:
    """(eff -> (gravity vector (3,) [m/s^2], its Jacobian (3, k) over the tilt entries), those
    k entries of eff)."""
    eff = ca.SX.sym("eff", N_EFFECTS)
    g = gravity_vector(eff)
    tilt = _depends_on(g, eff)
    return ca.Function("gravity_of_tilt", [eff], [g, ca.densify(ca.jacobian(g, eff)[:, [int(c) for c in tilt]])]), tilt


def _gravity(eff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gravity vector (3,) [m/s^2] at the tilts of ``eff`` and its Jacobian over them (3, k)."""
    g, dg = _gravity_function()[0](eff)
    return np.asarray(g).reshape(3), np.asarray(dg)


_LINK, _PAYLOAD, _VISCOUS = (SMOOTH_EFFECT_FIELDS.index(f) for f in ("link_mass_scale", "payload_kg", "viscous_Nms"))
RIGID_READ_AFTER = 4
"""A problem's first few evaluations run the compiled Function itself; :class:`RigidTerms`
(four such evaluations) is read at the next: the home-angle variants of a log's problem are
often evaluated only once or twice."""
_TILTS = ((0.0, 0.0), (0.0, math.pi / 2), (math.pi / 2, 0.0), (math.pi, 0.0))
"""(tilt about x, tilt about z) [rad] at which :meth:`RigidTerms.read` evaluates the inverse
dynamics: gravity along -y, +x, -z and +y, so that its affine dependence on gravity is solved
exactly."""


@dataclass(frozen=True)
class RigidTerms:
    """The leg torques the rigid-body dynamics needs at a problem's samples [N.m], as they depend
    on the link-mass scale s, the payload m [kg] and the gravity vector g (3,) [m/s^2]:
    tau = a + s b + m c + (D + s E + m F) g (exactly: masses and inertias enter the virtual power
    linearly, and gravity only through the bodies' weights). a, b, c (n, 3); D, E, F (n, 3, 3)
    [leg, component of g]; ``w`` (n, 3) the leg speeds [rad/s]."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    D: np.ndarray
    E: np.ndarray
    F: np.ndarray
    w: np.ndarray

    @staticmethod
    def read(evaluate: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], base_eff: np.ndarray,
             per_command_at: Callable[[np.ndarray], np.ndarray]) -> "RigidTerms":
        """The terms from the inverse dynamics and its Jacobian (``evaluate(eff)``, the compiled
        Function) at four gravity directions, from ``base_eff`` with every friction off, unit
        motor gains and no Kd term, where the command is the torque over the motor's torque per
        command (``per_command_at(eff)`` (n, 3) [N.m per command unit], the same at any speed
        there)."""
        eff = np.array(base_eff, dtype=float)
        for name in ("coulomb_Nm", "viscous_Nms", "stribeck_Nm", "kd_sign", *LEG_COULOMB_FIELDS):
            eff[SMOOTH_EFFECT_FIELDS.index(name)] = 0.0
        for name in ("motor_gain", *LEG_GAIN_FIELDS):
            eff[SMOOTH_EFFECT_FIELDS.index(name)] = 1.0
        eff[_LINK], eff[_PAYLOAD] = 1.0, 0.0
        rows, gravity = [], []
        per_command = per_command_at(eff)
        for tx, tz in _TILTS:
            eff[SMOOTH_EFFECT_FIELDS.index("gravity_tilt_x_rad")] = tx
            eff[SMOOTH_EFFECT_FIELDS.index("gravity_tilt_z_rad")] = tz
            tc, jac = evaluate(eff)
            rows.append((tc * per_command, jac[:, :, _LINK] * per_command, jac[:, :, _PAYLOAD] * per_command,
                         jac[:, :, _VISCOUS] * per_command))
            gravity.append(_gravity(eff)[0])
        basis = np.linalg.inv(np.column_stack([np.ones(4), np.array(gravity)]))     # [1, g] per direction

        def affine(k: int) -> tuple[np.ndarray, np.ndarray]:
            coef = np.tensordot(basis, np.stack([r[k] for r in rows]), axes=1)     # (4, n, 3)
            return coef[0], np.moveaxis(coef[1:], 0, -1)

        ab, de = affine(0)          # at s = 1, m = 0: (a + b) + (D + E) g
        b, e = affine(1)            # d tau / d s = b + E g
        c, f = affine(2)            # d tau / d m = c + F g
        return RigidTerms(ab - b, b, c, de - e, e, f, rows[0][3])     # w = d tau / d viscous


@dataclass
class ResidualProblem:
    """The inverse-dynamics residual of one log, ready to be fitted.

    ``model`` gives the parameter set and the nominal effect vector; ``motion`` the log's
    smoothed motion and commands; ``nominal_delay`` the command delay [samples, may be
    fractional: 2.5 is the plant's 2 plus half a period of hold] before any fitted extra
    delay. ``stride`` keeps every stride-th valid sample (the smoothed signals are strongly
    correlated over the low-pass time scale, so little information is lost and fits run faster).
    ``start_s`` [s from the first sample]: the samples before it are left out (the motion's
    start: in the approach from rest before it the device's state and the clock's phase when
    the loop took it are unknown, and on the logs a real host recorded its fast, sharply
    changing commands left a residual the nominal model has on a nominal device; unless that
    leaves too few samples).
    """

    model: FalconModel
    motion: MotionEstimate
    nominal_delay: float
    stride: int = 4
    start_s: float = 0.0
    _rows: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        valid = self.motion.valid & (self.motion.t_s - self.motion.t_s[0] >= self.start_s - 1e-9)
        rows = np.flatnonzero(valid if valid.sum() >= 20 * self.stride else self.motion.valid)[:: self.stride]
        if rows.size < 20:
            from falcon_plan.discrepancy.motion import BRIDGE_S, EDGE_S

            valid = int(self.motion.valid.sum())
            raise IdentificationError(
                f"only {valid} usable samples ({valid / self.motion.rate_hz:.2f} s) in a log of "
                f"{self.motion.n}: identification needs at least {20 * self.stride} ({20 * self.stride / self.motion.rate_hz:.2f} s), "
                f"a sample being usable {EDGE_S * 1e3:.0f} ms or more from an end or from a gap longer than "
                f"{BRIDGE_S * 1e3:.0f} ms (the smoothing filter needs that much of the motion on either side; "
                "shorter gaps are bridged). Record a longer run, or on a less busy machine")
        self._rows = rows
        self._evaluator = _chunk_evaluator(self.model)
        self._p = self.motion.position_m[rows].T
        self._v = self.motion.velocity_m_s[rows].T
        self._a = self.motion.acceleration_m_s2[rows].T
        self._measured: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}
        self._rigid: RigidTerms | None = None
        self._compiled_evaluations = 0
        self.home_variants: dict[float, ResidualProblem] = {}
        """The same log's problems read with other home angles, by the offset [rad] (filled by
        :class:`~falcon_plan.discrepancy.smooth_stage.SmoothStage`, shared by its stages)."""
        self._loads_cache: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}

    @property
    def rows(self) -> np.ndarray:
        """Indices of the samples used (into the motion's arrays)."""
        return self._rows

    def measured(self, extra_delay: int) -> tuple[np.ndarray, np.ndarray]:
        """Logged (smoothed) commands acting at the used samples under the nominal delay plus
        ``extra_delay`` whole samples, shape (m, 3), and a mask (m, 3) of the entries used: the command exists, is not
        saturated, and the leg is moving (see :data:`SLOW_LEG_RAD_S`)."""
        if extra_delay not in self._measured:
            delay = self.nominal_delay + int(extra_delay)
            cmd, ok = self.motion.shifted_commands(delay)
            # Samples whose acting commands (raw, unfiltered, over the filter's time scale)
            # reach the static saturation are left out: the motor torque is not the
            # command's there.
            raw, raw_ok = self.motion.shifted_commands(delay, smooth=False)
            limit = SATURATION_MARGIN * self.model.params.command_saturation
            hot = np.abs(raw).max(axis=1) >= limit
            spread = max(1, int(round(self.motion.rate_hz / (2 * self.motion.cutoff_hz))))
            hot = np.convolve(hot.astype(float), np.ones(2 * spread + 1), "same") > 0
            ok = ok & raw_ok & ~hot
            moving = np.abs(self.motion.theta1_dot_rad_s) >= SLOW_LEG_RAD_S
            mask = ok[:, None] & moving
            self._measured[extra_delay] = (cmd[self._rows], mask[self._rows])
        return self._measured[extra_delay]

    def evaluate(self, eff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inverse dynamics (m, 3) [command units] and its Jacobian w.r.t. eff (m, 3, n_eff) at
        ``eff``, composed from the problem's :class:`RigidTerms` and the friction and motor laws
        at the samples' leg speeds (the same numbers as :meth:`evaluate_compiled`, to rounding;
        the last few evaluations are cached: every candidate's fit starts at the same point)."""
        key = np.asarray(eff, float).tobytes()
        if key in self._cache:
            return self._cache[key]
        eff = np.asarray(eff, float)
        if self._rigid is None and self._compiled_evaluations < RIGID_READ_AFTER:
            self._compiled_evaluations += 1   # a problem evaluated a few times only: not worth a read
            tc, jac = self.evaluate_compiled(eff)
            self._remember(key, tc, jac)
            return tc, jac
        rigid, loads = self.rigid_terms, _loads_evaluator(self.model.params)
        g, dg = _gravity(eff)
        s, m = eff[_LINK], eff[_PAYLOAD]
        n = rigid.a.shape[0]
        weights = (rigid.D + s * rigid.E + m * rigid.F).reshape(3 * n, 3)     # (leg rows, g)
        tau = rigid.a + s * rigid.b + m * rigid.c + (weights @ g).reshape(n, 3)
        friction, dfriction, per_command, dper_command = self._loads(eff)
        inverse = 1.0 / per_command            # (multiplying by it: a third of the time of dividing)
        tc = (tau - friction) * inverse
        # d tc / d eff = (d tau - d friction - tc d per_command) / per_command, each on its columns
        jac = np.zeros((n, 3, len(SMOOTH_EFFECT_FIELDS)))
        jac[:, :, _gravity_function()[1]] = (weights @ dg).reshape(n, 3, -1) * inverse[:, :, None]
        jac[:, :, _LINK] = (rigid.b + (rigid.E.reshape(3 * n, 3) @ g).reshape(n, 3)) * inverse
        jac[:, :, _PAYLOAD] = (rigid.c + (rigid.F.reshape(3 * n, 3) @ g).reshape(n, 3)) * inverse
        jac[:, :, loads.friction_columns] = dfriction * -inverse[:, :, None]
        jac[:, :, loads.motor_columns] = dper_command * -(tc * inverse)[:, :, None]
        self._remember(key, tc, jac)
        return tc, jac

    @property
    def rigid_terms(self) -> RigidTerms:
        """The rigid-body part of the inverse dynamics at the samples (read once)."""
        if self._rigid is None:
            still = np.zeros((self._rows.size, 3))
            self._rigid = RigidTerms.read(self.evaluate_compiled, self.model.effect_vector,
                                          lambda eff: self._loads(eff, still)[2])
        return self._rigid

    def _loads(self, eff: np.ndarray, w: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Friction torque (n, 3), its Jacobian (n, 3, k_f) over :class:`_Loads`'s friction
        columns, torque per command (n, 3) and its Jacobian (n, 3, k_m) over the motor columns,
        at the samples' leg speeds (or ``w`` (n, 3) [rad/s])."""
        loads = _loads_evaluator(self.model.params)
        key = None
        if w is None:   # at the samples' speeds they change only with the laws' own entries of eff
            key = np.asarray(eff, float)[np.concatenate([loads.friction_columns, loads.motor_columns])].tobytes()
            if key in self._loads_cache:
                return self._loads_cache[key]
            w = self.rigid_terms.w
        fn = loads.function
        if isinstance(fn, BufferedFunction):
            with _LOADS_LOCK:
                fn.inputs[1][:] = eff
                out = fn.map_columns([w.T])[0]
        else:
            out = np.asarray(fn.map(w.shape[0])(w.T, eff))
        rows = np.ascontiguousarray(out.T)                                   # (n, outputs)
        n, kf, km = rows.shape[0], loads.friction_columns.size, loads.motor_columns.size
        end = 3 + 3 * kf
        result = (rows[:, :3], rows[:, 3:end].reshape(n, 3, kf), rows[:, end:end + 3],
                  rows[:, end + 3:].reshape(n, 3, km))
        if key is not None:
            if len(self._loads_cache) > 4:
                self._loads_cache.pop(next(iter(self._loads_cache)))
            self._loads_cache[key] = result
        return result

    def evaluate_compiled(self, eff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`evaluate` at ``eff`` by the compiled inverse-dynamics-and-Jacobian Function
        itself (the definition; :class:`RigidTerms` is read from it)."""
        m, n_eff, fn = self._rows.size, len(SMOOTH_EFFECT_FIELDS), self._evaluator
        tc = np.zeros((m, 3))
        jac = np.zeros((m, 3, n_eff))
        fn.inputs[3][:] = np.asarray(eff, float)
        for start in range(0, m, CHUNK_ROWS):
            used = min(CHUNK_ROWS, m - start)
            for i, src in enumerate((self._p, self._v, self._a)):
                fn.inputs[i][:, :used] = src[:, start:start + used]
                fn.inputs[i][:, used:] = src[:, start:start + 1]      # padding: any valid sample
            fn()
            tc[start:start + used] = fn.outputs[0][:, :used].T
            jac[start:start + used] = fn.outputs[1].reshape(3, CHUNK_ROWS, n_eff)[:, :used].transpose(1, 0, 2)
        return tc, jac

    def _remember(self, key: bytes, tc: np.ndarray, jac: np.ndarray) -> None:
        if len(self._cache) > 8:
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = (tc, jac)

    def residual(self, eff: np.ndarray, extra_delay: int = 0) -> np.ndarray:
        """r = measured - ID [command units], shape (m, 3), at the effect vector ``eff`` and
        ``extra_delay`` samples of extra delay; entries not used are zero."""
        tc, _ = self.evaluate(eff)
        meas, ok = self.measured(extra_delay)
        return np.where(ok, meas - tc, 0.0)


@dataclass(frozen=True)
class SmoothFit:
    """Result of a fit of smooth parameters (and a delay) to the residual.

    ``values``/``std`` map Effects field -> value/standard deviation; ``extra_delay`` the
    extra delay fitted or used [samples]; ``rss`` is the residual sum of squares [command
    units^2] over ``n`` scalar residuals; ``eff`` the fitted vector; ``jacobian`` and
    ``residual`` below.
    """

    values: dict[str, float]
    std: dict[str, float]
    extra_delay: int
    rss: float
    n: int
    eff: np.ndarray
    jacobian: np.ndarray
    """Regressor columns at the solution, (n, k) (for correlation diagnostics)."""
    residual: np.ndarray
    """Residual at the solution, (m, 3) [command units]."""


UNCONSTRAINED_MAX_CONDITION = 1e10
"""Condition number of the scaled normal matrix below which a bounded least-squares step
takes the unconstrained minimiser when no bound is active (a dense solve of at most the 18
smooth-effect fields instead of an OSQP set-up, about 1 ms, on every Gauss-Newton step of every
candidate's fit)."""


def _bounded_least_squares(jac: np.ndarray, r: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                           scale: np.ndarray) -> np.ndarray:
    """min ||r - J delta||^2 subject to lower <= delta <= upper, on the scaled step
    z = delta / scale: the unconstrained minimiser when it is well determined and inside the
    bounds (then it is the bounded one), else solved with OSQP. Shapes: jac (n, k), r (n,),
    bounds (k,)."""
    js = jac * scale[None, :]
    hess = js.T @ js
    grad = -js.T @ r
    norm = max(float(np.max(np.abs(np.diag(hess)))), 1e-300)
    hess, grad = hess / norm, grad / norm
    k = jac.shape[1]
    lo = np.where(np.isfinite(lower), lower / scale, -1e20)
    hi = np.where(np.isfinite(upper), upper / scale, 1e20)
    if np.linalg.cond(hess) < UNCONSTRAINED_MAX_CONDITION:
        z = np.linalg.solve(hess, -grad)
        if np.all((lo <= z) & (z <= hi)):
            return z * scale
    result = _box_qp_solver(k).solve(hess, grad, lo, hi)
    if result.x is None or not np.all(np.isfinite(result.x)):
        raise IdentificationError(f"OSQP failed on the bounded least-squares step ({result.info.status})")
    return np.asarray(result.x) * scale


OSQP_SETTINGS = {"verbose": False, "eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 20000, "polishing": False}
_solvers = threading.local()


class _BoxQP:
    """min 1/2 z' H z + g' z subject to lo <= z <= hi for dense (k, k) H, by one OSQP instance
    set up once and updated for every problem: its set-up (sparse matrices, the interface's own
    checks) took 1 ms of the 1.1 ms a bounded step cost, some 400 times a case. Each solve starts
    from zero and the default step size, as a fresh instance would."""

    def __init__(self, k: int) -> None:
        upper = sp.csc_matrix(np.triu(np.ones((k, k))))         # every entry of the upper triangle
        self._rows, self._cols = upper.indices, np.repeat(np.arange(k), np.diff(upper.indptr))
        self._solver = osqp.OSQP()
        self._solver.setup(P=upper, q=np.zeros(k), A=sp.identity(k, format="csc"), l=-np.ones(k), u=np.ones(k),
                           **OSQP_SETTINGS)
        self._rho = self._solver.settings.rho
        self._k = k

    def solve(self, hess: np.ndarray, grad: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> Any:
        """OSQP's result (``x``: the solution z, ``info.status``)."""
        self._solver.update(Px=hess[self._rows, self._cols], q=grad, l=lo, u=hi)
        self._solver.update_settings(rho=self._rho)
        self._solver.warm_start(x=np.zeros(self._k), y=np.zeros(self._k))
        return self._solver.solve(raise_error=False)


def _box_qp_solver(k: int) -> _BoxQP:
    """This thread's :class:`_BoxQP` for k variables."""
    solvers = getattr(_solvers, "by_size", None)
    if solvers is None:
        solvers = _solvers.by_size = {}
    if k not in solvers:
        solvers[k] = _BoxQP(k)
    return solvers[k]


def fit_smooth(problem: ResidualProblem, parameters: list[EffectParameter], base_eff: np.ndarray,
               extra_delay: int = 0, start: dict[str, float] | None = None,
               inflation: float = 1.0, max_iterations: int = GN_MAX_ITERATIONS,
               rows: np.ndarray | None = None) -> SmoothFit:
    """Fit ``parameters`` (smooth-effect fields) on top of ``base_eff`` by bounded Gauss-Newton
    on the residual of ``problem``, at ``extra_delay`` whole samples of extra delay.

    ``start`` overrides the starting values (default: the base vector's). ``inflation``
    multiplies the covariance (see the module docstring). With ``max_iterations`` = 1 the
    result is one linearised step (used to rank delays cheaply). ``rows`` (bool, one per used
    sample) restricts the fit to those samples (cross-validation folds).
    """
    eff = np.array(base_eff, dtype=float)
    idx = np.array([SMOOTH_EFFECT_FIELDS.index(p.field) for p in parameters], dtype=int)
    for p in parameters:
        if start and p.field in start:
            eff[SMOOTH_EFFECT_FIELDS.index(p.field)] = start[p.field]
    lower = np.array([p.lower for p in parameters])
    upper = np.array([p.upper for p in parameters])
    scale = np.array([p.scale for p in parameters])
    meas, ok = problem.measured(extra_delay)
    if rows is not None:
        ok = ok & np.asarray(rows, bool)[:, None]
    mask = ok.reshape(-1)
    linear = all(p.field in LINEAR_FIELDS for p in parameters)
    tc, jac = problem.evaluate(eff)
    r = (meas - tc).reshape(-1)[mask]
    jr = jac[:, :, idx].reshape(jac.shape[0] * 3, idx.size)[mask]   # d ID / d theta
    for iteration in range(max_iterations if idx.size else 0):
        step = _bounded_least_squares(jr, r, lower - eff[idx], upper - eff[idx], scale)
        eff[idx] += step
        if linear or iteration == max_iterations - 1:
            r = r - jr @ step            # exact when the inverse dynamics is linear in these
            break
        tc, jac = problem.evaluate(eff)
        r = (meas - tc).reshape(-1)[mask]
        jr = jac[:, :, idx].reshape(jac.shape[0] * 3, idx.size)[mask]
        if np.all(np.abs(step) <= GN_STEP_TOLERANCE * scale):
            break
    resid = np.zeros_like(meas)
    resid.reshape(-1)[mask] = r
    rss = float(r @ r)
    n = int(mask.sum())
    values = clip_to_bounds({p.field: float(eff[i]) for p, i in zip(parameters, idx)})
    eff[idx] = [values[p.field] for p in parameters]
    std: dict[str, float] = {}
    if idx.size:
        sigma2 = rss / max(n - idx.size, 1)
        try:
            cov = np.linalg.inv(jr.T @ jr) * sigma2 * inflation
            std = {p.field: float(math.sqrt(max(cov[j, j], 0.0))) for j, p in enumerate(parameters)}
        except np.linalg.LinAlgError:
            std = {p.field: math.inf for p in parameters}
    return SmoothFit(values, std, int(extra_delay), rss, n, eff, jr, resid)


def fit_effect_set(problem: ResidualProblem, effects: list[CandidateEffect], base_eff: np.ndarray,
                   delays: range = range(0, 7), inflation: float = 1.0,
                   start: dict[str, float] | None = None, rows: np.ndarray | None = None) -> SmoothFit:
    """Fit a set of smooth candidates ``effects`` of ``problem`` on top of the effect vector
    ``base_eff`` and, if ``command_delay`` is among them, the delay. ``inflation`` and ``rows``
    as in :func:`fit_smooth`; ``start`` a warm start.

    The delay is a discrete search over ``delays`` (extra whole samples, the best fit wins);
    without it the nominal delay is used. The Stribeck velocity is nonlinear and
    badly scaled, so its fit is started from three values (0.1, 0.3, 1 rad/s) and the best kept,
    unless ``start`` (values of a fitted subset, a warm start) gives it.
    """
    params = [p for c in effects if c.kind == "smooth" for p in c.parameters]
    assert not any(c.kind in ("encoder", "replay") for c in effects), "not an inverse-dynamics effect"
    with_delay = any(c.kind == "delay" for c in effects)
    starts: list[dict[str, float]] = [dict(start or {})]
    if any(p.field == "stribeck_velocity_rad_s" for p in params) and "stribeck_velocity_rad_s" not in starts[0]:
        starts = [{"stribeck_velocity_rad_s": v, "stribeck_Nm": 0.005} for v in (0.1, 0.3, 1.0)]
    candidates_d = [d for d in delays if d > 0] if with_delay else [0]
    if len(candidates_d) > 1:
        # rank the delays by one linearised step each, then fit at the best one only
        ranked = {d: min(fit_smooth(problem, params, base_eff, d, s, max_iterations=1, rows=rows).rss
                         for s in starts) for d in candidates_d}
        candidates_d = [min(ranked, key=lambda d: ranked[d])]
    best: SmoothFit | None = None
    for d in candidates_d:
        for start in starts:
            fit = fit_smooth(problem, params, base_eff, d, start, inflation, rows=rows)
            if best is None or fit.rss < best.rss:
                best = fit
    assert best is not None
    return best


def autocorrelation_time(residual: np.ndarray, max_lag: int = 400) -> float:
    """Integrated autocorrelation time [samples] of a residual (m, 3): 1 + 2 sum of the
    autocorrelation up to its first non-positive value (at most ``max_lag`` lags), averaged
    over the legs (>= 1)."""
    taus = []
    for leg in range(residual.shape[1]):
        x = residual[:, leg] - residual[:, leg].mean()
        var = float(x @ x)
        if var <= 0:
            continue
        tau = 1.0
        for lag in range(1, min(max_lag, x.size // 4)):
            rho = float(x[:-lag] @ x[lag:]) / var
            if rho <= 0:
                break
            tau += 2.0 * rho
        taus.append(tau)
    return max(1.0, float(np.mean(taus))) if taus else 1.0
