"""FalconModel: the parameter set, the effects and the compiled dynamics, seen from numpy.

Coordinates: end-effector point p [m], velocity v [m/s], acceleration a [m/s^2], base frame.
Commands Tc are real-valued here (the device edge rounds them). Single points are (3,),
batches (n, 3); both run a compiled C loop over chunks of points (CasADi ``map`` of the
Function with common subexpressions eliminated: about 2x fewer operations), or CasADi's
virtual machine without a compiler.
"""
from __future__ import annotations

import threading
from functools import cached_property
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

from falcon_plan.model.effects import NOMINAL, Effects
from falcon_plan.model.params import ACRA2009, FalconParams
from falcon_plan.model.symbolic import DynamicsFunctions, dynamics_functions
from falcon_plan.model.workspace import DEFAULT_LIMITS, WorkspaceLimits

if TYPE_CHECKING:
    from falcon_plan.compiled import BufferedFunction


BATCH_CHUNK = 64
"""Points per call of the compiled batched Functions (the last call is padded: with 512 a
plan's ~40 nodes cost as much as 512 points, ~0.35 ms; the call itself costs ~5 us)."""
SMALL_BATCH_CHUNK = 4
"""Points per call for single points and batches of up to :data:`SMALL_BATCH_MAX` (the
virtual machine took 120 us for one point and 480 us for 9, CasADi building a new map
for every call; this chunk takes ~5 us a call), once :meth:`FalconModel.prepare_small_batches`
has built them: a single point never starts a compilation (a real-time loop that stalls for
one trips the device's watchdog; the doctor did)."""
SMALL_BATCHED = ("inverse_dynamics", "forward_dynamics", "workspace_margins")
"""The Functions :meth:`FalconModel.prepare_small_batches` builds (the planner's)."""
SMALL_BATCH_MAX = 16
"""Largest batch evaluated in chunks of :data:`SMALL_BATCH_CHUNK`."""
BATCH_FLAGS = ("-O3", "-march=native")
_batch_cache: dict[tuple[int, str, int], tuple[BufferedFunction, threading.Lock] | None] = {}


def _compiled_batch(functions: DynamicsFunctions, name: str, chunk: int,
                    build: bool = True) -> tuple[BufferedFunction, threading.Lock] | None:
    """The Function ``name`` mapped over ``chunk`` points with common subexpressions
    eliminated, compiled to C once per machine (a BufferedFunction, with the lock that
    guards its buffers: planner threads share it); None without a compiler, when the
    Function is not a map of (3,) inputs (``eff`` last) to one column output, or when it is
    not built yet and ``build`` is False."""
    key = (id(functions), name, chunk)
    if key not in _batch_cache:
        if not build:
            return None
        from falcon_plan.compiled import compiled_points

        fn: ca.Function = getattr(functions, name)
        if fn.n_out() != 1 or fn.size2_out(0) != 1 or \
                any(fn.size_in(i) != (3, 1) for i in range(fn.n_in() - 1)):
            _batch_cache[key] = None         # not a (3,)... -> column map: the VM path handles it
            return None
        compiled = compiled_points(fn, name, chunk, BATCH_FLAGS)
        _batch_cache[key] = (compiled, threading.Lock()) if compiled is not None else None
    return _batch_cache[key]


def _run_batch(batch: tuple[BufferedFunction, threading.Lock], arrays: list[np.ndarray],
               eff: np.ndarray) -> np.ndarray:
    """Evaluate a compiled batch Function over (n, 3) arrays chunk by chunk -> (n, k)."""
    function, lock = batch
    with lock:
        function.inputs[len(arrays)][:] = eff
        return function.map_columns([x.T for x in arrays])[0].T


class FalconModel:
    """The Falcon's model: parameters, extra effects and workspace limits.

    Immutable in use (build a new one to change anything); the CasADi Functions are built once
    per (params, limits) and shared. ``functions`` exposes them for symbolic reuse (planner,
    identification); the methods below are the numpy face.

    ``params`` is the parameter set, ``effects`` the extra effects (nominal: none) and
    ``limits`` the workspace limits. The methods take the end-effector state in the base
    frame: position ``p`` [m], velocity ``v`` [m/s], acceleration ``a`` [m/s^2], and motor
    commands ``tc`` [command units, real-valued]; each one point (3,) or, where the shape
    says (..., 3), a batch (n, 3) of points.
    """

    def __init__(self, params: FalconParams = ACRA2009, effects: Effects = NOMINAL,
                 limits: WorkspaceLimits = DEFAULT_LIMITS) -> None:
        self.params = params
        self.effects = effects
        self.limits = limits
        self._eff = effects.smooth_vector()

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled as its parameters, effects and limits (its CasADi Functions are built again)."""
        return FalconModel, (self.params, self.effects, self.limits)

    def __repr__(self) -> str:
        extra = f", effects={self.effects.to_dict()}" if not self.effects.is_nominal else ""
        return f"FalconModel(params={self.params.name!r}{extra})"

    @property
    def loop_delay_samples(self) -> float:
        """Control samples from a command being sent to the first reading that shows it acting,
        as a host loop sees it: the device's command delay, a fitted extra delay (effect) and
        the measured link delay (``params.link_delay_samples``); fractional. What a
        controller's delay model and the feed-forward lead compensate."""
        return (self.params.command_delay_samples + float(self.effects.extra_delay_samples)
                + float(self.params.link_delay_samples))

    def with_effects(self, effects: Effects) -> "FalconModel":
        """The same model with other effects (e.g. a fitted correction, or a payload)."""
        return FalconModel(self.params, effects, self.limits)

    @cached_property
    def functions(self) -> DynamicsFunctions:
        """The compiled CasADi Functions (see :class:`DynamicsFunctions`); ``eff`` is
        :attr:`effect_vector`."""
        return dynamics_functions(self.params, self.limits)

    @property
    def effect_vector(self) -> np.ndarray:
        """This model's smooth-effect vector, the last input of every Function."""
        return self._eff.copy()

    def _call(self, name: str, *args: Any) -> np.ndarray:
        fn: ca.Function = getattr(self.functions, name)
        arrays = [np.asarray(x, dtype=float) for x in args]
        single = arrays[0].ndim == 1
        n = 1 if single else arrays[0].shape[0]
        small = n <= SMALL_BATCH_MAX
        batch = _compiled_batch(self.functions, name, SMALL_BATCH_CHUNK if small else BATCH_CHUNK, build=not small)
        if batch is not None:
            out = _run_batch(batch, [a[None, :] for a in arrays] if single else arrays, self._eff)
            return out[0] if single else out
        if single:  # the virtual machine (no compiler, or not a map of points)
            out = fn(*arrays, self._eff)
            return np.asarray(out).squeeze(-1) if np.asarray(out).shape[-1] == 1 else np.asarray(out)
        mapped = fn.map(n)
        out = mapped(*[x.T for x in arrays], np.repeat(self._eff[:, None], n, axis=1))
        return np.asarray(out).T

    def prepare_small_batches(self) -> None:
        """Build (compile once per machine, then load) the compiled chunks that single points
        and small batches of :data:`SMALL_BATCHED` use from then on, in this process (the
        planner calls it; without it they run in the virtual machine)."""
        for name in SMALL_BATCHED:
            _compiled_batch(self.functions, name, SMALL_BATCH_CHUNK)

    def prepare_linearisation(self) -> None:
        """Build (compile once per machine, then load) the compiled chunks of
        :meth:`count_linearisation` (the tracking controller's design)."""
        _compiled_batch(self.functions, "count_linearisation", BATCH_CHUNK)

    # --- dynamics ----------------------------------------------------------------------------
    def mass_matrix(self, p: Any) -> np.ndarray:
        """M(p) [kg], shape (3, 3), for one point p [m]."""
        return np.asarray(self.functions.mass_matrix(np.asarray(p, float), self._eff))

    def bias(self, p: Any, v: Any) -> np.ndarray:
        """Coriolis and centrifugal terms h(p, v) [N], shape (..., 3)."""
        return self._call("bias", p, v)

    def gravity(self, p: Any) -> np.ndarray:
        """Gravity term g(p) = dV/dp [N], shape (..., 3)."""
        return self._call("gravity", p)

    def leg_torques(self, p: Any, v: Any, a: Any) -> np.ndarray:
        """Total pivot torques [N.m] (theta1 sense) that the motion needs, shape (..., 3)."""
        return self._call("leg_torques", p, v, a)

    def inverse_dynamics(self, p: Any, v: Any, a: Any) -> np.ndarray:
        """Commands Tc (real-valued) that produce acceleration a at (p, v), shape (..., 3)."""
        return self._call("inverse_dynamics", p, v, a)

    def forward_dynamics(self, p: Any, v: Any, tc: Any) -> np.ndarray:
        """Acceleration [m/s^2] under commands Tc at (p, v), shape (..., 3)."""
        return self._call("forward_dynamics", p, v, tc)

    def holding_commands(self, p: Any) -> np.ndarray:
        """Commands that hold the device still at p against gravity, shape (..., 3)."""
        zeros = np.zeros_like(np.asarray(p, dtype=float))
        return self.inverse_dynamics(p, zeros, zeros)

    def count_linearisation(self, p: Any, v: Any, tc: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The dynamics linearised in encoder space at the points (p, v) [m, m/s] under the
        commands ``tc`` [command units], each (n, 3): (A21, A22, B2), each (n, 3, 3), of
        d/dt (n, dn/dt) = [[0, I], [A21, A22]] (n, dn/dt) + [[0], [B2]] Tc with n the counts
        [counts] (``DynamicsFunctions.count_linearisation``). In compiled chunks of
        :data:`BATCH_CHUNK` points (built once per machine, ~30 s; :meth:`prepare_linearisation`
        builds them ahead), else CasADi's virtual machine."""
        p, v, tc = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (p, v, tc))
        n = p.shape[0]
        batch = _compiled_batch(self.functions, "count_linearisation", BATCH_CHUNK)
        if batch is not None:
            out = _run_batch(batch, [p, v, tc], self._eff)
        else:
            fn = self.functions.count_linearisation.map(n)
            out = np.asarray(fn(p.T, v.T, tc.T, np.repeat(self._eff[:, None], n, axis=1))).T  # (n, 27)
        mats = out.reshape(n, 3, 3, 3).transpose(1, 0, 3, 2)  # column-major 3x3 blocks
        return mats[0], mats[1], mats[2]

    def energy(self, p: Any, v: Any) -> tuple[float, float]:
        """Kinetic and potential energy [J] at one state (potential up to a constant)."""
        t, vv = self.functions.energy(np.asarray(p, float), np.asarray(v, float), self._eff)
        return float(t), float(vv)

    def workspace_margins(self, p: Any) -> np.ndarray:
        """Workspace constraint values (>= 0 inside), see workspace.CONSTRAINT_NAMES."""
        return self._call("workspace_margins", p)
