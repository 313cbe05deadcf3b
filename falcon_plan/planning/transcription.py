"""The minimum-time transcription: point-to-point motion of the Falcon as a CasADi NLP solved by IPOPT.

With a constant limit the planner uses this transcription at a coarse N only to read the
bang-bang command pattern (:mod:`.pattern`), whose switch times :mod:`.shooting` then solves exactly; the
transcription at the full N plans where that does not apply (the device's limit, a pattern
that is not optimal) and is the reference the switching-time plans are tested against.

Transcription (multiple shooting, exact for :class:`Trajectory`'s interpolation)
--------------------------------------------------------------------------------
- Free final time: one duration variable per segment between via points (just T without
  via points), each segment cut into equal intervals; N intervals in all.
- States at the N + 1 nodes: end-effector point p_k [m] and velocity v_k [m/s] (base frame).
- Controls, two profiles (``PlanOptions.profile``):

  * "linear" (default): the acceleration a_k at every node, linear in between (continuous,
    piecewise linear); p_k+1 = p_k + h v_k + h^2 (2 a_k + a_k+1) / 6 and
    v_k+1 = v_k + h (a_k + a_k+1) / 2 are exact. Durations converge at second order in
    1/N (measured: the N -> 2N change drops about fourfold), so N = 24 is within 0.1-0.35 %
    of the converged duration on the benchmark problems without via points;
  * "constant": one acceleration per interval (p_k+1 = p_k + h v_k + h^2/2 a_k); first
    order: 0.2-2.6 % above the converged duration at N = 24 (the configuration before).

- Commands through the model's own inverse dynamics (``model.functions.inverse_dynamics``,
  the function the plant's forward dynamics inverts: closed-chain rigid body, motor model
  with its Kd term, friction and payload effects through ``eff``), bounded at points of
  every interval: for "constant" at *both ends* (the acceleration jumps at the nodes;
  imposing it at the nodes only lets the command overshoot by 10-19 % between them,
  PLANNING-NOTES); for "linear" at the nodes and :data:`POINTS_PER_INTERVAL` - 1 points
  inside every interval (the command is continuous; between the points it leaves their
  chord by O(h^2): < 1 % on the dense re-check). The bound (:mod:`.bound`) is a constant, |Tc| <= tc_max - reserve, or the
  device's speed-dependent limit, |Tc| <= L(w) - reserve with L the saturation rule the
  plant applies (:mod:`falcon_plan.model.saturation`); the device's limit dips to 2500
  where a leg reverses, so it is imposed at :data:`DEVICE_POINTS_PER_INTERVAL` points per
  interval.
- Workspace: ``model.functions.workspace_margins(p) >= NODE_MARGIN`` (2e-3) at every
  interior node; the small slack covers the position's short excursion between nodes (the
  dense re-check verifies it). The margins are half of the NLP's constraints and inactive
  in every benchmark problem, so :func:`.min_time.solve_min_time` first solves without them
  ("screening") and imposes them only when that solution leaves the workspace (exact either
  way: a solution of the relaxed problem that satisfies them is a solution of the full one);
  this halves the median solve time.
- Boundary values and via points are fixed through the variable bounds; the command limit
  is in the constraint bounds; the effect vector (payload) is an NLP parameter. So one NLP
  is built per (parameter set, limit kind, segments, profile, Hessian choice) and reused.

Why accelerations as controls and the commands as path constraints: the dynamics are then
linear in the states and the closed-chain expressions appear only in the path constraints,
evaluated point-wise; taking Tc as the control needs a mass-matrix solve inside the
integrator and was ~12x slower in the notes' measurement.

Solver: IPOPT (MUMPS) with a limited-memory (L-BFGS, 3 pairs) Hessian: it needs first
derivatives only, which are compiled; the exact Hessian took fewer iterations (14-20 against
20-35) but its second derivatives cost ~10x more per iteration (in the virtual machine; and
compiling them took 150 s and still ran 3x slower than L-BFGS overall). fatrop was slower
and less robust in the notes' prototype; CasADi 3.8's fatrop interface has no Hessian
approximation, so it would need those same second derivatives. Measured for issue 12 and not
adopted: a free (variable) grid of interval lengths (gap 1.35 -> 0.83 % on one problem at 3-4x
the iterations), IPOPT option changes (spral, no scaling, monotone mu, looser tolerances:
within +-10 % of the default), dropping the Python deadline callback (about 5 %).
Where a solve's time goes (issue 12, loaded 2-core machine, CPU time): about 18 iterations
whatever the guess (the bang-bang guess's acceleration scaled by 0.7-1.3, the N/2 solution
upsampled: 13), at ~0.7 ms per iteration for N = 4 (IPOPT's fixed cost) and ~2-2.7 ms for
N = 24, a third of it the compiled Jacobian kernels; only a start within ~1e-4 of the
optimum converges in 3 iterations. Two solves in two threads took longer than in turn (the
Python bindings hold the GIL). So one solve at N = 24 costs ~35 ms, and the refinement
sequence of :mod:`.api` about 1.5 solves.

Speed: the per-point functions are SX with common subexpressions merged once (``ca.cse``),
compiled to C with their Jacobians and cached on disk (:mod:`falcon_plan.compiled.external`, ~12x faster than
the virtual machine), and *mapped* over the points inside an MX graph, so CasADi
differentiates one small function instead of expanding the whole problem. CasADi's OpenBLAS
and OpenMP run on one thread (:func:`limit_solver_threads`). The initial guess is the
straight line (a polyline through the via points) with a bang-bang time scaling.
"""
from __future__ import annotations

import ctypes
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from falcon_plan.compiled import compile_with_jacobian
from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.bound import CommandBound, device_limit_rows
from falcon_plan.planning.problem import PROFILES, PlanOptions, PlanProblem, SolverSettings, Transcription
from falcon_plan.planning.report import WorkspaceHandling
from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)

COMMAND_SCALE = 2500.0
"""Commands enter the NLP divided by this [command units] (O(1) constraint rows)."""
STATE_SCALE = np.array([0.05, 0.05, 0.05, 1.0, 1.0, 1.0])
"""Scale of the node states (p [m], v [m/s]) as NLP variables."""
ACCEL_SCALE = 50.0
"""Scale of the interval accelerations [m/s^2] as NLP variables."""
TIME_SCALE = 0.1
"""Scale of the final time [s] as an NLP variable."""
T_BOUNDS_S = (1e-3, 10.0)
"""Range allowed for the final time [s]."""
POSITION_BOX_M = ((-0.12, -0.12, 0.0), (0.12, 0.12, 0.25))
"""A loose box around the workspace for the node positions [m] (the margins do the real work)."""
SPEED_BOUND_M_S = 5.0
"""Loose bound on every velocity component at the nodes [m/s] (keeps iterates sane)."""
ACCEL_BOUND_M_S2 = 3000.0
"""Loose bound on every acceleration component [m/s^2] (the command limit does the work)."""
MAX_ITERATIONS = 400
"""IPOPT's iteration limit of a solve with the workspace margins imposed (the screening and
coarse solves have their own, :data:`.min_time.SCREEN_MAX_ITER`, :data:`.min_time.IGNORED_MAX_ITER`)."""
DEFAULT_PROFILE = Transcription.profile
DEFAULT_HESSIAN = SolverSettings.hessian
"""The defaults of every level below the API: those of the planner's options
(:class:`~falcon_plan.planning.problem.Transcription`, :class:`~falcon_plan.planning.problem.SolverSettings`)."""
IPOPT_OPTIONS: dict[str, Any] = {
    "print_level": 0, "sb": "yes", "tol": 1e-7, "acceptable_tol": 1e-5, "acceptable_iter": 5,
    "max_iter": MAX_ITERATIONS, "mu_strategy": "adaptive", "limited_memory_max_history": 3,
    "limited_memory_aug_solver": "extended"}
"""IPOPT options of every NLP built from now on (the Hessian choice is added per NLP).

``limited_memory_aug_solver: extended`` puts the L-BFGS low-rank terms into the factorised
KKT matrix instead of applying them by Sherman-Morrison with several extra back-solves:
same iterates (durations equal to 1e-14), 12-18 % less CPU per solve over the benchmark
problems (issue 12). Measured and left: the MUMPS ordering and scaling options (no change),
the "probing" and "loqo" barrier oracles (1.5-2x the iterations), L-BFGS history 2 or 5
(within the noise), tolerances 1e-5 / 1e-6 (same iteration counts)."""
FAST_START_OPTIONS: dict[str, Any] = {
    "warm_start_init_point": "yes", "mu_init": 1e-4, "warm_start_bound_push": 1e-6,
    "warm_start_mult_bound_push": 1e-6}
"""Added for the screening solve: start from the guess as given (a consistent motion) with a
small barrier; 12 % fewer iterations over the benchmark problems. With active workspace
constraints the default start is more robust (105 against 227 iterations in one case), so
the full NLP keeps it."""
POINTS_PER_INTERVAL = 3
"""Points per interval at which a constant limit is imposed (linear profile): the node and
the thirds. Over the benchmark problems at N = 24 the dense re-check found at most 0.8 %
between them (with the node and the midpoint: 1.7 %, past the 1 % tolerance on two
problems, which then cost a re-solve at 2N; with the nodes only: 7 %)."""
DEVICE_POINTS_PER_INTERVAL = 6
"""Points per interval at which the device's speed-dependent limit is imposed (linear
profile): it dips to the static 2500 over ~2 ms where a leg's speed passes zero, and with
the midpoints only (2) the dense re-check found the command 6 % over it between them at
N = 24, with 4 points 1.2 %, with 6 points 0.5 % (the tolerance is 1 %)."""
GUESS_ACCEL_FRACTION = 0.7
"""Initial guess: this fraction of the acceleration the start's command room allows."""
WORKSPACE_MODES = ("screen", "impose", "ignore")
"""How :func:`.min_time.solve_min_time` handles the workspace margins."""
IPOPT_WALL_TIME_STATUS = "Maximum_WallTime_Exceeded"
"""IPOPT's return status when its own wall-time limit stopped it."""

NODE_MARGIN = 2e-3
"""Lower bound of the workspace margins at the nodes [rad, or sine / determinant units]."""


@dataclass(frozen=True)
class NodeMotion:
    """A motion at the transcription's N + 1 nodes (a solution, or a guess).

    duration_s : T [s]; p, v : (N+1, 3) [m], [m/s]; a : the acceleration [m/s^2], (N+1, 3)
    at the nodes for the "linear" profile, (N, 3) per interval for "constant";
    h : (N,) interval lengths [s] summing to T (None: equal, T / N).
    """

    duration_s: float
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    h: np.ndarray | None = None

    @property
    def intervals_s(self) -> np.ndarray:
        """Interval lengths [s], (N,)."""
        if self.h is None:
            return np.full(self.n_intervals, self.duration_s / self.n_intervals)
        return np.asarray(self.h, float)

    @property
    def n_intervals(self) -> int:
        """N."""
        return len(self.p) - 1

    @property
    def profile(self) -> str:
        """The acceleration profile: "linear" (values at the nodes) or "constant" (one per interval)."""
        return "linear" if len(self.a) == len(self.p) else "constant"

    @property
    def times_s(self) -> np.ndarray:
        """Node times [s], (N+1,), from 0."""
        return np.concatenate([[0.0], np.cumsum(self.intervals_s)])

    def midpoints(self) -> np.ndarray:
        """Positions [m] at the interval midpoints, (N, 3) (exact for the profile)."""
        h = self.intervals_s[:, None]
        p, v, a = np.asarray(self.p), np.asarray(self.v), np.asarray(self.a)
        if self.profile == "linear":
            return p[:-1] + 0.5 * h * v[:-1] + h * h * (5.0 * a[:-1] + a[1:]) / 48.0
        return p[:-1] + 0.5 * h * v[:-1] + 0.125 * h * h * a

    def as_profile(self, profile: str) -> "NodeMotion":
        """The same motion with the other acceleration profile (node values <-> interval means)."""
        if profile == self.profile:
            return self
        a = np.asarray(self.a, float)
        if profile == "constant":
            return NodeMotion(self.duration_s, self.p, self.v, 0.5 * (a[1:] + a[:-1]), self.h)
        nodes = np.vstack([a[:1], 0.5 * (a[1:] + a[:-1]), a[-1:]])
        return NodeMotion(self.duration_s, self.p, self.v, nodes, self.h)


@dataclass(frozen=True)
class SolveResult:
    """What one optimiser run produced (:func:`.min_time.solve_min_time` may combine two runs: the
    screening solve and the full one; times and iterations are then summed).

    Attributes
    ----------
    success : IPOPT converged (to its tolerance or the acceptable one) within the budget.
    solver_status : IPOPT's return status, or "time budget exhausted".
    iterations : IPOPT iterations (summed over the runs).
    solve_time_s, solve_cpu_s : wall and process CPU time of the solver calls [s].
    duration_s : the motion's duration T of the last iterate [s].
    n_intervals : N of the transcription.
    timed_out : the deadline callback stopped the solver.
    trajectory : the last iterate as a Trajectory whenever it is finite (None from
        :func:`solve_transcription`, and for an unusable iterate): check ``success`` first.
    nodes : the last iterate at the nodes (a :class:`NodeMotion`).
    workspace : how the workspace constraints were handled (a :class:`WorkspaceHandling`).
    """

    success: bool
    solver_status: str
    iterations: int
    solve_time_s: float
    """Wall time of the solver call [s]."""
    solve_cpu_s: float
    """CPU time of this process during the solver call [s] (steadier on a shared machine)."""
    duration_s: float
    n_intervals: int
    timed_out: bool
    trajectory: Trajectory | None
    nodes: NodeMotion = field(repr=False)
    """The last iterate at the nodes."""
    workspace: WorkspaceHandling = WorkspaceHandling.IMPOSED
    """How the workspace constraints were handled (see :func:`.min_time.solve_min_time`)."""


class _Deadline(ca.Callback):
    """IPOPT iteration callback that stops the solver once a wall-clock deadline passes."""

    def __init__(self, name: str, n_x: int, n_g: int, n_p: int) -> None:
        ca.Callback.__init__(self)
        self._sizes = {"x": n_x, "g": n_g, "p": n_p}
        self.deadline = math.inf
        self.expired = False
        self.construct(name, {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "ret"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        name = ca.nlpsol_out(i)
        n = {"f": 1, "x": self._sizes["x"], "lam_x": self._sizes["x"], "g": self._sizes["g"],
             "lam_g": self._sizes["g"], "lam_p": self._sizes["p"]}[name]
        return ca.Sparsity.dense(n, 1)

    def eval(self, arg: list[Any]) -> list[Any]:
        if time.perf_counter() > self.deadline:
            self.expired = True
            return [1]
        return [0]


_threads_limited = False


SINGLE_THREADED_LIBRARIES = (
    (Path(ca.__file__).parent, "libcasadi-tp-openblas.so*", ("openblas_set_num_threads",)),
    (Path(ca.__file__).parent, "libgomp*.so*", ("omp_set_num_threads",)),
    (Path(np.__file__).parent.parent / "numpy.libs", "libscipy_openblas*.so*",
     ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads", "openblas_set_num_threads")),
)
"""(folder, library file pattern, the thread-count setters it may export, first found used)
that :func:`limit_solver_threads` sets to one thread."""


def limit_solver_threads() -> None:
    """Run CasADi's bundled OpenBLAS and OpenMP (under IPOPT's MUMPS) and numpy's bundled
    OpenBLAS on one thread (:data:`SINGLE_THREADED_LIBRARIES`).

    On a loaded 2-core machine their worker threads spin and wait: one IPOPT solve measured
    0.09 s of CPU but 0.39 s of wall time; single-threaded, 0.15 s. numpy's are those of the
    switching-time solve's small Newton steps (``np.linalg.solve``, ``lstsq`` on 6-20 unknowns):
    a device-limit plan of short_z at load 5 on 2 cores took 3.2-4.0 s of wall time for
    0.6-0.7 s of CPU (the switching-time attempts 0.8-1.1 s each); single-threaded 1.1-1.4 s
    for 0.34-0.42 s (0.27-0.31 s each). One plan per core is the service's model anyway. Done
    once per process, at the first NLP build; it affects every CasADi and numpy user in the
    process (linear algebra on large matrices there runs on one core).
    """
    global _threads_limited
    if _threads_limited:
        return
    _threads_limited = True
    for folder, pattern, symbols in SINGLE_THREADED_LIBRARIES:
        for lib in sorted(folder.glob(pattern))[:1]:
            try:
                handle = ctypes.CDLL(str(lib))
                setter = next((getattr(handle, s) for s in symbols if hasattr(handle, s)), None)
                if setter is None:
                    raise AttributeError(f"none of {symbols}")
                setter(1)
            except (OSError, AttributeError) as exc:
                log.debug("could not limit threads through %s: %s", lib.name, exc)


@dataclass(frozen=True)
class PointConstraints:
    """What the transcription imposes at points of the motion (a problem's "physics").

    Attributes
    ----------
    key : hashable identity (the NLP cache key).
    rows : Function (p, v, a, eff) -> r, bounded per query at both ends of every interval.
    margins : Function (p, eff) -> m >= 0 at the interior nodes and interval midpoints, or None.
    n_eff : size of the parameter vector ``eff``.
    """

    key: tuple[Any, ...]
    rows: ca.Function
    margins: ca.Function | None
    n_eff: int


def falcon_constraints(model: FalconModel, *, compiled: bool = True, workspace: bool = True,
                       limit: str = "constant") -> PointConstraints:
    """The Falcon's constraints: the commands Tc(p, v, a) (the model's inverse dynamics,
    common subexpressions merged) and the workspace margins.

    ``limit`` "constant": rows Tc / COMMAND_SCALE (3), bounded by +-(tc_max - reserve);
    "device": rows (Tc - L(w)) / COMMAND_SCALE and (Tc + L(w)) / COMMAND_SCALE (6), with
    w = J(p) v and L the device's speed-dependent limit (:mod:`falcon_plan.model.saturation`),
    bounded by <= -reserve and >= +reserve, i.e. |Tc| <= L(w) - reserve.
    ``workspace`` False leaves the margins out (for the screening solve).
    With ``compiled`` both functions and their Jacobians are compiled to C once and cached
    on disk (:mod:`falcon_plan.compiled.external`): ~12x faster than CasADi's virtual machine.
    """
    fns = model.functions
    n_eff = fns.expressions.eff.numel()
    p, v, a = ca.SX.sym("p", 3), ca.SX.sym("v", 3), ca.SX.sym("a", 3)
    eff = ca.SX.sym("eff", n_eff)
    tc = fns.inverse_dynamics(p, v, a, eff)
    if limit == "device":
        lim = device_limit_rows(model, p, v, a, eff)
        rows = ca.Function("falcon_device_command", [p, v, a, eff],
                           [ca.cse(ca.vertcat(tc - lim, tc + lim) / COMMAND_SCALE)])
    else:
        rows = ca.Function("falcon_scaled_command", [p, v, a, eff], [ca.cse(tc / COMMAND_SCALE)])
    margins = ca.Function("falcon_margins", [p, eff], [ca.cse(fns.workspace_margins(p, eff))])
    if compiled:
        rows = compile_with_jacobian(rows)
        margins = compile_with_jacobian(margins)
    key = ("falcon", model.params, model.limits, rows.name(), n_eff)
    if not workspace:
        return PointConstraints((*key, "no-workspace"), rows, None, n_eff)
    return PointConstraints(key, rows, margins, n_eff)


def command_row_bounds(bound: CommandBound) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of the command rows of :func:`falcon_constraints` for ``bound``."""
    r = bound.reserve / COMMAND_SCALE
    if bound.kind == "device":
        return (np.concatenate([-np.inf * np.ones(3), r * np.ones(3)]),
                np.concatenate([-r * np.ones(3), np.inf * np.ones(3)]))
    lim = (bound.tc_max - bound.reserve) / COMMAND_SCALE * np.ones(3)
    return -lim, lim


def box_constraints() -> PointConstraints:
    """Per-axis velocity and acceleration rows (v, a) of a point mass (a 3-axis double
    integrator): the transcription without the Falcon, for the regression case."""
    p, v, a = ca.SX.sym("p", 3), ca.SX.sym("v", 3), ca.SX.sym("a", 3)
    eff = ca.SX.sym("eff", 1)
    rows = ca.Function("box_rows", [p, v, a, eff], [ca.vertcat(v, a)])
    return PointConstraints(("double-integrator",), rows, None, 1)


@dataclass(frozen=True)
class Stacked:
    """A vector stacked from matrix blocks in order, each stored column-major (as ``ca.vec``):
    the one definition of the NLP's variable and constraint layouts, used to build the
    symbolic vector and to pack, unpack and bound numeric ones (no hand-written slices).

    Attributes
    ----------
    shapes : (rows, columns) of each block, in order.
    """

    shapes: tuple[tuple[int, int], ...]

    @property
    def size(self) -> int:
        """Length of the stacked vector."""
        return sum(r * c for r, c in self.shapes)

    def join(self, *blocks: Any) -> Any:
        """The stacked vector of ``blocks`` (one per shape): CasADi matrices give a CasADi
        vector; numbers give a numpy one, where a 1-D block of the right size is read
        column-major and anything else is broadcast to the block's shape (a scalar fills it,
        a (rows, 1) column repeats in every column)."""
        if any(isinstance(b, (ca.MX, ca.SX)) for b in blocks):
            return ca.vertcat(*[ca.vec(b) for b in blocks])
        parts = []
        for block, shape in zip(blocks, self.shapes, strict=True):
            a = np.asarray(block, float)
            a = a.reshape(shape, order="F") if a.ndim <= 1 and a.size == shape[0] * shape[1] else np.broadcast_to(a, shape)
            parts.append(a.ravel(order="F"))
        return np.concatenate(parts)

    def split(self, vector: Any) -> list[np.ndarray]:
        """The blocks of a stacked numeric ``vector``, each with its (rows, columns) shape."""
        w = np.asarray(vector, float).ravel()
        ends = np.cumsum([0] + [r * c for r, c in self.shapes])
        return [w[a:b].reshape(shape, order="F") for a, b, shape in zip(ends[:-1], ends[1:], self.shapes)]


class MinTimeNlp:
    """The minimum-time NLP for one (point constraints, segments, profile, Hessian choice),
    built once.

    Parameters
    ----------
    constraints : the point constraints (rows bounded per query, margins >= 0).
    segments : interval counts of the segments between the via points (start -> via 1 ->
        ... -> goal), summing to N; each segment's duration is a variable of its own and its
        intervals are equal, so the times at which the via points are passed are optimised
        too (with one overall T they would be fixed fractions of it: a first-order error).
    hessian : "exact" or "limited-memory".
    max_iter : IPOPT's iteration limit.
    fast_start : add :data:`FAST_START_OPTIONS`.
    profile : "linear" or "constant" acceleration on each interval (:data:`PROFILES`).
    points_per_interval : "linear" profile: the command rows are imposed at the nodes and at
        this many evenly spaced points per interval (counting its start):
        :func:`.min_time.solve_min_time` uses :data:`POINTS_PER_INTERVAL` for a constant limit and
        :data:`DEVICE_POINTS_PER_INTERVAL` for the device's, which dips to its static value
        over ~2 ms wherever a leg reverses.
    wall_time_s : None: every solve stops at its own deadline (an IPOPT iteration callback,
        :attr:`deadline`). A number [s]: IPOPT's own wall-time limit, the same for every
        solve, and no callback (:attr:`deadline` None): CasADi hands every iterate to a
        Python callback as new objects, ~1 ms of a ~10 ms coarse solve (issue 12).
    """

    def __init__(self, constraints: PointConstraints, segments: tuple[int, ...], hessian: str = DEFAULT_HESSIAN,
                 max_iter: int = MAX_ITERATIONS, fast_start: bool = False, profile: str = DEFAULT_PROFILE,
                 points_per_interval: int = POINTS_PER_INTERVAL, wall_time_s: float | None = None) -> None:
        t0 = time.perf_counter()
        limit_solver_threads()
        self.segments = tuple(int(k) for k in segments)
        self.n = n = sum(self.segments)
        self.profile = profile
        n_eff = constraints.n_eff
        command, margins = constraints.rows, constraints.margins
        self.n_rows = command.size1_out(0)

        # --- variables: scaled segment durations (one per segment), node states (6, N+1),
        # accelerations (3, N+1) at the nodes ("linear") or (3, N) per interval ("constant")
        n_acc = n + 1 if profile == "linear" else n
        w_t = ca.MX.sym("T", len(self.segments))
        w_x = ca.MX.sym("X", 6, n + 1)
        w_a = ca.MX.sym("A", 3, n_acc)
        eff = ca.MX.sym("eff", n_eff)
        x = ca.DM(STATE_SCALE) * w_x          # physical (p; v), rows broadcast
        acc = ACCEL_SCALE * w_a
        p, v = x[:3, :], x[3:, :]
        if len(self.segments) == 1:
            h = TIME_SCALE * w_t / n
        else:  # interval lengths (1, N), equal within each segment
            h = ca.repmat(ca.horzcat(*[ca.repmat(TIME_SCALE * w_t[i] / k, 1, k)
                                       for i, k in enumerate(self.segments)]), 3, 1)

        # --- dynamics: exact steps of the acceleration profile (gap-closing constraints), and
        # the points where the command rows are imposed
        if profile == "linear":
            a0, a1 = acc[:, :-1], acc[:, 1:]
            p_next = p[:, :-1] + h * v[:, :-1] + h * h * (2.0 * a0 + a1) / 6.0
            v_next = v[:, :-1] + 0.5 * h * (a0 + a1)
            # at the nodes and ``points_per_interval - 1`` evenly spaced points inside every
            # interval (the command between two of them deviates from their chord by O(h^2))
            ps, vs, accs = [p], [v], [acc]
            for i in range(1, points_per_interval):
                tau = h * i / points_per_interval
                jerk_tau = (a1 - a0) * (i / points_per_interval)
                ps.append(p[:, :-1] + tau * v[:, :-1] + tau * tau * (0.5 * a0 + jerk_tau / 6.0))
                vs.append(v[:, :-1] + tau * (a0 + 0.5 * jerk_tau))
                accs.append(a0 + jerk_tau)
            points = (ca.horzcat(*ps), ca.horzcat(*vs), ca.horzcat(*accs))
        else:
            p_next = p[:, :-1] + h * v[:, :-1] + 0.5 * h * h * acc
            v_next = v[:, :-1] + h * acc
            # at both ends of every interval (the acceleration jumps at the nodes)
            points = (ca.horzcat(p[:, :-1], p[:, 1:]), ca.horzcat(v[:, :-1], v[:, 1:]), ca.horzcat(acc, acc))
        gap = ca.vertcat(p[:, 1:] - p_next, v[:, 1:] - v_next) / ca.DM(STATE_SCALE)
        n_points = points[0].shape[1]
        rows = command.map(n_points)(*points, ca.repmat(eff, 1, n_points))
        # --- workspace margins at the interior nodes
        if margins is not None:
            mg = margins.map(n - 1)(p[:, 1:-1], ca.repmat(eff, 1, n - 1))
        # the layouts of w and g: scaled segment durations, node states, accelerations; the
        # gap-closing rows, the command rows at every point, the margins at interior nodes
        self.variables = Stacked(((len(self.segments), 1), (6, n + 1), (3, n_acc)))
        self.constraints = Stacked(((6, n), (self.n_rows, n_points), (mg.shape if margins is not None else (0, 0))))
        w = self.variables.join(w_t, w_x, w_a)
        g = self.constraints.join(gap, rows, mg if margins is not None else ca.MX(0, 0))
        self.n_w = self.variables.size
        self.n_g = self.constraints.size
        self.n_points = n_points

        ipopt = dict(IPOPT_OPTIONS, **(FAST_START_OPTIONS if fast_start else {}), max_iter=int(max_iter),
                     hessian_approximation="exact" if hessian == "exact" else "limited-memory")
        # (NaN in an evaluation is IPOPT's to handle: it backs off; a warning per evaluation flooded a
        # service's log with thousands of lines for one unreachable goal speed)
        opts: dict[str, Any] = {"ipopt": ipopt, "print_time": False, "record_time": True, "error_on_fail": False,
                                "show_eval_warnings": False}
        self.deadline: _Deadline | None = None
        if wall_time_s is None:
            self.deadline = opts["iteration_callback"] = _Deadline(f"deadline_{id(self)}", self.n_w, self.n_g, n_eff)
        else:
            ipopt["max_wall_time"] = float(wall_time_s)
        self.solver = ca.nlpsol(f"falcon_min_time_{n}_{len(self.segments)}_{profile}", "ipopt",
                                {"x": w, "p": eff, "f": ca.sum1(w_t), "g": g}, opts)
        self.lock = threading.Lock()
        self.build_time_s = time.perf_counter() - t0
        log.info("built min-time NLP N=%d (%d vars, %d constraints) in %.2f s", n, self.n_w,
                 self.n_g, self.build_time_s)

    # --- packing ---------------------------------------------------------------------------
    def pack(self, motion: NodeMotion) -> np.ndarray:
        """A node ``motion`` -> the NLP's scaled variable vector (:attr:`variables`)."""
        xs = np.vstack([np.asarray(motion.p, float).T, np.asarray(motion.v, float).T]) / STATE_SCALE[:, None]
        acc = np.asarray(motion.as_profile(self.profile).a, float)
        segment_t = np.diff(motion.times_s[np.cumsum((0,) + self.segments)])
        return self.variables.join(segment_t / TIME_SCALE, xs, acc.T / ACCEL_SCALE)

    def unpack(self, w: np.ndarray) -> NodeMotion:
        """The NLP's scaled variable vector ``w`` (n_w,) -> the node motion."""
        scaled_t, scaled_x, scaled_a = self.variables.split(w)
        segment_t = scaled_t[:, 0] * TIME_SCALE
        xs = scaled_x * STATE_SCALE[:, None]
        acc = scaled_a * ACCEL_SCALE
        m = len(self.segments)
        h = np.repeat(segment_t / np.array(self.segments), self.segments) if m > 1 else None
        return NodeMotion(float(segment_t.sum()), xs[:3].T.copy(), xs[3:].T.copy(), acc.T.copy(), h)

    def bounds(self, problem: PlanProblem, row_lower: np.ndarray,
               row_upper: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(lbx, ubx, lbg, ubg) for one query: ``problem``'s start and goal states are fixed at
        the first and last node, its via points at the segments' ends; ``row_lower`` /
        ``row_upper`` bound the point rows (one value per row, the same at every point)."""
        n, m = self.n, len(self.segments)
        via_nodes = np.cumsum(self.segments)[:-1]
        lo_p, hi_p = np.array(POSITION_BOX_M[0]), np.array(POSITION_BOX_M[1])
        lo_x = np.tile(np.concatenate([lo_p, -SPEED_BOUND_M_S * np.ones(3)])[:, None], (1, n + 1))
        hi_x = np.tile(np.concatenate([hi_p, SPEED_BOUND_M_S * np.ones(3)])[:, None], (1, n + 1))
        fixed = {0: (problem.start_m, problem.start_velocity_m_s),
                 n: (problem.goal_m, problem.goal_velocity_m_s)}
        for k, node in enumerate(via_nodes):
            lo_x[:3, node] = hi_x[:3, node] = problem.via_m[k]
        for node, (pos, vel) in fixed.items():
            lo_x[:, node] = hi_x[:, node] = np.concatenate([pos, vel])
        lo_a = -ACCEL_BOUND_M_S2 * np.ones((3, n + 1 if self.profile == "linear" else n))
        lbx = self.variables.join(T_BOUNDS_S[0] / m / TIME_SCALE, lo_x / STATE_SCALE[:, None], lo_a / ACCEL_SCALE)
        ubx = self.variables.join(T_BOUNDS_S[1] / TIME_SCALE, hi_x / STATE_SCALE[:, None], -lo_a / ACCEL_SCALE)
        column = (self.n_rows, 1)  # one value per row, the same at every point
        lbg = self.constraints.join(0.0, np.broadcast_to(row_lower, (self.n_rows,)).reshape(column), NODE_MARGIN)
        ubg = self.constraints.join(0.0, np.broadcast_to(row_upper, (self.n_rows,)).reshape(column), np.inf)
        return lbx, ubx, lbg, ubg


_nlp_cache: dict[tuple[Any, ...], MinTimeNlp] = {}
_nlp_cache_lock = threading.Lock()


def get_nlp(constraints: PointConstraints, segments: tuple[int, ...], hessian: str = DEFAULT_HESSIAN,
            max_iter: int = MAX_ITERATIONS, fast_start: bool = False, profile: str = DEFAULT_PROFILE,
            points_per_interval: int = POINTS_PER_INTERVAL, wall_time_s: float | None = None) -> MinTimeNlp:
    """The :class:`MinTimeNlp` for ``constraints``, the interval counts per segment
    ``segments``, ``hessian`` ("exact" or "limited-memory"), IPOPT's iteration limit
    ``max_iter``, ``fast_start`` (:data:`FAST_START_OPTIONS`), the acceleration ``profile``,
    the command rows' ``points_per_interval`` and the deadline (``wall_time_s``, as there):
    built once, cached (thread-safe)."""
    key = (constraints.key, tuple(segments), hessian, int(max_iter), fast_start, profile, points_per_interval,
           wall_time_s)
    with _nlp_cache_lock:
        nlp = _nlp_cache.get(key)
        if nlp is None:
            nlp = _nlp_cache[key] = MinTimeNlp(constraints, segments, hessian, max_iter, fast_start,
                                               profile, points_per_interval, wall_time_s)
    return nlp


_constraint_cache: dict[tuple[Any, ...], PointConstraints] = {}


def model_constraints(model: FalconModel, hessian: str, workspace: bool = True,
                      limit: str = "constant") -> PointConstraints:
    """The Falcon constraints of ``model`` (compiled when ``hessian`` is "limited-memory",
    whose solver needs first derivatives only; "exact" uses CasADi's virtual machine), with
    or without the workspace margins (``workspace``), for a ``limit`` "constant" or
    "device"; cached."""
    key = (model.params, model.limits, model.functions.expressions.eff.numel(), hessian, workspace, limit)
    with _nlp_cache_lock:
        if key not in _constraint_cache:
            _constraint_cache[key] = falcon_constraints(model, compiled=hessian != "exact",
                                                        workspace=workspace, limit=limit)
        return _constraint_cache[key]


def points_per_interval(limit: str) -> int:
    """Points per interval at which the command rows are imposed ("linear" profile) for a
    ``limit`` kind: :data:`DEVICE_POINTS_PER_INTERVAL` for the device's, else
    :data:`POINTS_PER_INTERVAL`."""
    return DEVICE_POINTS_PER_INTERVAL if limit == "device" else POINTS_PER_INTERVAL

def via_nodes(problem: PlanProblem, n_intervals: int) -> list[int]:
    """Nodes at which ``problem``'s via points are imposed on a grid of ``n_intervals``
    intervals: spread in proportion to the straight-line distance along start -> via ... ->
    goal, distinct, strictly inside (1 .. N-1); InvalidProblemError when N is too small."""
    if not problem.via_m:
        return []
    pts = problem.waypoints_m
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    frac = np.cumsum(seg)[:-1] / max(float(seg.sum()), 1e-12)
    nodes: list[int] = []
    for i, f in enumerate(frac):
        lo = (nodes[-1] + 1) if nodes else 1
        hi = n_intervals - 1 - (len(frac) - 1 - i)
        if lo > hi:
            raise InvalidProblemError(
                f"{len(frac)} via points need more than {n_intervals} intervals; raise n_intervals")
        nodes.append(int(min(max(round(f * n_intervals), lo), hi)))
    return nodes


def segment_counts(problem: PlanProblem, n_intervals: int) -> tuple[int, ...]:
    """Interval counts of ``problem``'s segments start -> via ... -> goal for
    ``n_intervals`` in all (:func:`via_nodes`): (N,) without via points."""
    return tuple(int(k) for k in np.diff([0, *via_nodes(problem, n_intervals), n_intervals]))


def initial_guess(model: FalconModel, problem: PlanProblem, n: int, tc_max: float,
                  nodes: list[int], accel_fraction: float = GUESS_ACCEL_FRACTION,
                  carry_speeds: bool = True) -> NodeMotion:
    """A straight-line (polyline through ``problem``'s via points) guess on ``n`` equal
    intervals with a bang-bang time scaling, the via points on the nodes ``nodes``. With
    ``carry_speeds``, a moving end's speed is carried on from the start (brought to the goal's)
    within the motion, which takes as much longer as stopping (reaching) it takes; without,
    only the end nodes' velocities are the ends' (a fast moving start's line then runs against
    its speed: IPOPT ran out of iterations from it at every N on bench_replan case 66).

    The acceleration magnitude comes from the ``model``: the command per unit acceleration
    along the start-goal direction at the start, against what is left of ``tc_max`` (the
    bound at rest [command units]) after holding gravity, times ``accel_fraction``.
    """
    pts = problem.waypoints_m
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    length = max(float(seg.sum()), 1e-6)
    direction = (pts[1] - pts[0]) / max(seg[0], 1e-9)
    start = np.asarray(problem.start_m)
    hold = model.inverse_dynamics(start, np.zeros(3), np.zeros(3))
    per_accel = np.abs(model.inverse_dynamics(start, np.zeros(3), direction) - hold)
    room = np.maximum(tc_max - np.abs(hold), 0.1 * tc_max)
    a_max = accel_fraction * float(np.min(room / np.maximum(per_accel, 1e-9)))
    v0, vf = np.asarray(problem.start_velocity_m_s, float), np.asarray(problem.goal_velocity_m_s, float)
    carried = (v0, vf) if carry_speeds else (np.zeros(3), np.zeros(3))
    line_s = 2.0 * math.sqrt(length / a_max)
    # a moving end needs about the time to stop (or reach) its speed on top of the line's
    t_total = line_s + (float(np.linalg.norm(carried[0])) + float(np.linalg.norm(carried[1]))) / a_max
    # bang-bang arc-length profile sampled at the nodes (a_k constant per interval)
    tk = np.linspace(0.0, t_total, n + 1)
    half = t_total / 2
    s = np.where(tk <= half, 2.0 * length * (tk / t_total) ** 2, length - 2.0 * length * (1.0 - tk / t_total) ** 2)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    p = np.stack([np.interp(s, cum, pts[:, i]) for i in range(3)], axis=1)
    # the end speeds, carried on and brought to zero within the motion (each term is zero at
    # both ends, its slope the end's speed at its own end and zero at the other)
    tau = (tk / t_total)[:, None]
    p = p + t_total * (carried[0] * tau * (1.0 - tau) ** 2 + carried[1] * (tau - 1.0) * tau ** 2)
    # via nodes exactly on their points
    for k, node in enumerate(nodes):
        p[node] = problem.via_m[k]
    h = t_total / n
    v = np.gradient(p, h, axis=0)
    v[0], v[-1] = v0, vf
    a = np.diff(v, axis=0) / h
    return NodeMotion(t_total, p, v, a)


@dataclass(frozen=True)
class MinTimeSettings:
    """How one minimum-time transcription is solved (:func:`.min_time.solve_min_time`,
    :func:`solve_transcription`): the planner's stages build it from its
    :class:`~falcon_plan.planning.problem.PlanOptions` (:meth:`of`), so every level has the
    options' defaults.

    Attributes
    ----------
    n_intervals : N.
    segments : interval counts per segment between via points (default
        :func:`segment_counts`; a refinement passes the coarse solve's counts doubled, so that
        the grids are nested).
    hessian : "exact" or "limited-memory" (default: the options').
    profile : the acceleration profile on each interval, :data:`PROFILES` (default: the options').
    time_budget_s : wall-clock budget [s]; the optimiser stops when it is used up.
    workspace : how the workspace margins are handled, :data:`WORKSPACE_MODES`: "screen":
        first solve without them (at most :data:`.min_time.SCREEN_MAX_ITER` iterations) and impose them
        only if that solution leaves the workspace (or the screening solve fails): about 2x
        faster when they are inactive; "impose": solve with them; "ignore": solve without
        them (at most :data:`.min_time.IGNORED_MAX_ITER` iterations) and do not check (a coarse solve
        that only has to show the command pattern, the caller checking the motion it leads to).
        (:func:`.min_time.solve_min_time` only.)
    command_points : "linear" profile: the points per interval where the command rows are
        imposed (default: :func:`points_per_interval` of the bound's kind in
        :func:`.min_time.solve_min_time`, :data:`POINTS_PER_INTERVAL` in :func:`solve_transcription`; 1:
        at the nodes only, for a coarse solve that only has to show the command pattern).
    wall_time_s : None: ``time_budget_s`` is kept by the deadline callback; a number [s]: by
        IPOPT's own wall-time limit of that value instead (:class:`MinTimeNlp`; the smaller of
        the two is not taken: the caller picks).
    """

    n_intervals: int
    segments: tuple[int, ...] | None = None
    hessian: str = DEFAULT_HESSIAN
    profile: str = DEFAULT_PROFILE
    time_budget_s: float = math.inf
    workspace: str = "screen"
    command_points: int | None = None
    wall_time_s: float | None = None

    def __post_init__(self) -> None:
        if self.workspace not in WORKSPACE_MODES:
            raise ValueError(f"workspace {self.workspace!r}: allowed {WORKSPACE_MODES}")
        if self.segments is not None:
            object.__setattr__(self, "segments", tuple(self.segments))

    @classmethod
    def of(cls, options: PlanOptions, n_intervals: int, **changes: Any) -> "MinTimeSettings":
        """Settings for ``n_intervals`` with the Hessian, profile and time budget of
        ``options``, then ``changes`` (field names, e.g. the budget left, the segments)."""
        return cls(n_intervals, **{"hessian": options.solver.hessian, "profile": options.transcription.profile,
                                   "time_budget_s": options.solver.time_budget_s, **changes})

def solve_transcription(constraints: PointConstraints, problem: PlanProblem, settings: MinTimeSettings, *,
                        row_lower: np.ndarray, row_upper: np.ndarray, eff: np.ndarray,
                        guess: NodeMotion, max_iter: int = MAX_ITERATIONS, fast_start: bool = False) -> SolveResult:
    """Solve the minimum-time transcription with any point ``constraints`` (the machinery
    under :func:`.min_time.solve_min_time`; the trajectory is left None). Never raises for solver
    failure.

    ``problem`` gives the fixed ends and via points; ``settings`` the grid, the budget and
    the NLP's choices (its ``workspace`` is not used: ``constraints`` say what is imposed);
    ``row_lower`` / ``row_upper`` bound the point rows (:func:`command_row_bounds`); ``eff``
    is the effect vector (the NLP parameter); ``guess`` the starting point (a
    :class:`NodeMotion` on this grid); ``max_iter`` and ``fast_start`` select the NLP as in
    :func:`get_nlp`.
    """
    n_intervals, time_budget_s = settings.n_intervals, settings.time_budget_s
    segments = segment_counts(problem, n_intervals) if settings.segments is None else settings.segments
    points = POINTS_PER_INTERVAL if settings.command_points is None else int(settings.command_points)
    nlp = get_nlp(constraints, segments, settings.hessian, max_iter, fast_start, settings.profile, points,
                  settings.wall_time_s)
    lbx, ubx, lbg, ubg = nlp.bounds(problem, row_lower, row_upper)
    x0 = np.clip(nlp.pack(guess), lbx, ubx)
    with nlp.lock:
        if nlp.deadline is not None:
            nlp.deadline.deadline = time.perf_counter() + time_budget_s
            nlp.deadline.expired = False
        t0, c0 = time.perf_counter(), time.process_time()
        sol = nlp.solver(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg, p=eff)
        solve_time, solve_cpu = time.perf_counter() - t0, time.process_time() - c0
        stats = nlp.solver.stats()
        status = str(stats.get("return_status", "unknown"))
        timed_out = nlp.deadline.expired if nlp.deadline is not None else status == IPOPT_WALL_TIME_STATUS
    success = bool(stats.get("success", False)) and not timed_out
    motion = nlp.unpack(np.asarray(sol["x"]))
    return SolveResult(success=success, solver_status="time budget exhausted" if timed_out else status,
                       iterations=int(stats.get("iter_count", -1)), solve_time_s=solve_time,
                       solve_cpu_s=solve_cpu,
                       duration_s=motion.duration_s, n_intervals=n_intervals, timed_out=timed_out,
                       trajectory=None, nodes=motion)


def nodes_to_trajectory(model: FalconModel, problem: PlanProblem, motion: NodeMotion, *, source: str,
                        meta: dict[str, Any] | None = None) -> Trajectory:
    """A :class:`Trajectory` from ``motion``, node values of the transcription, labelled with
    ``source`` and carrying ``meta`` (JSON-ready details).

    "linear" profile: the accelerations are the node values (linear in between). "constant":
    the last sample's acceleration is zero when the goal is at rest (the device then holds
    still), else the last interval's. Commands are the model's inverse dynamics at each
    sample (for "constant", right limits: the acceleration of the interval that starts
    there), with the problem's payload.
    """
    t = motion.times_s
    if motion.profile == "linear":
        acc = motion.a
    else:
        a_last = np.zeros(3) if not any(problem.goal_velocity_m_s) else motion.a[-1]
        acc = np.vstack([motion.a, a_last])
    cmd = payload_model(model, problem).inverse_dynamics(motion.p, motion.v, acc)
    return Trajectory(t, motion.p, motion.v, acc, cmd, model.params.name, source, dict(meta or {}),
                      interpolation=motion.profile)


def payload_model(model: FalconModel, problem: PlanProblem) -> FalconModel:
    """``model`` with the problem's payload added to its effects' payload."""
    if problem.payload_kg == 0.0:
        return model
    return model.with_effects(model.effects.replace(payload_kg=model.effects.payload_kg + problem.payload_kg))


__all__ = ["MinTimeNlp", "Stacked", "NodeMotion", "PointConstraints", "falcon_constraints", "box_constraints",
           "command_row_bounds", "solve_transcription", "model_constraints", "SolveResult", "get_nlp",
           "MinTimeSettings", "initial_guess", "via_nodes", "points_per_interval", "segment_counts",
           "nodes_to_trajectory", "payload_model", "COMMAND_SCALE", "PROFILES"]
