"""Minimum-time point-to-point motion of the Falcon as a CasADi NLP solved by IPOPT.

Transcription (multiple shooting, exact for :class:`Trajectory`'s interpolation)
--------------------------------------------------------------------------------
- Free final time T [s]; N equal intervals of length h = T / N.
- States at the N + 1 nodes: end-effector point p_k [m] and velocity v_k [m/s] (base frame).
- Controls: one acceleration a_k [m/s^2] per interval, held constant on [t_k, t_k+1), so
  p_k+1 = p_k + h v_k + h^2/2 a_k and v_k+1 = v_k + h a_k are exact (no integration error).
- Commands through the model's own inverse dynamics (``model.functions.inverse_dynamics``,
  the function the plant's forward dynamics inverts: closed-chain rigid body, motor model
  with its Kd term, friction and payload effects through ``eff``): Tc(p, v, a) is bounded by
  +-tc_max at *both ends* of every interval, (p_k, v_k, a_k) and (p_k+1, v_k+1, a_k). Imposing
  it at the nodes only lets the command overshoot by 10-19 % between them (PLANNING-NOTES);
  with both ends the dense re-check finds < 0.1 %.
- Workspace: ``model.functions.workspace_margins(p) >= NODE_MARGIN`` (2e-3) at every
  interior node; the small slack covers the position's short quadratic excursion between
  nodes (the dense re-check verifies it; ``MIDPOINT_MARGINS`` adds the interval midpoints,
  at +50 % solve time, for no change on the benchmark problems). The margins are half of
  the NLP's constraints and inactive in every benchmark problem, so :func:`solve_min_time`
  first solves without them ("screening") and imposes them only when that solution leaves
  the workspace (exact either way: a solution of the relaxed problem that satisfies them is
  a solution of the full one); this halves the median solve time.
- Boundary values and via points are fixed through the variable bounds; the command limit
  is in the constraint bounds; the effect vector (payload) is an NLP parameter. So one NLP
  is built per (parameter set, limits, N, Hessian choice) and reused for every query.

Why accelerations as controls and the commands as path constraints: the dynamics are then
linear in the states and the closed-chain expressions appear only in the path constraints,
evaluated point-wise; taking Tc as the control needs a mass-matrix solve inside the
integrator and was ~12x slower in the notes' measurement.

Solver: IPOPT (MUMPS) with a limited-memory (L-BFGS, 3 pairs) Hessian: it needs first
derivatives only, which are compiled; the exact Hessian took fewer iterations (14-20 against
20-35) but its second derivatives cost ~10x more per iteration (in the virtual machine; and
compiling them took 150 s and still ran 3x slower than L-BFGS overall). fatrop was slower
and less robust in the notes' prototype and was not adopted.

Speed: the per-point functions are SX with common subexpressions merged once (``ca.cse``),
compiled to C with their Jacobians and cached on disk (:mod:`.kernels`, ~12x faster than
the virtual machine), and *mapped* over the 2N points inside an MX graph, so CasADi
differentiates one small function instead of expanding the whole problem. CasADi's OpenBLAS
and OpenMP run on one thread (:func:`limit_solver_threads`). The initial guess is the
straight line (a polyline through the via points) with a bang-bang time scaling.
"""
from __future__ import annotations

import ctypes
import dataclasses
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.kernels import compile_with_jacobian
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.planning.trajectory import Trajectory

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
IPOPT_OPTIONS: dict[str, Any] = {
    "print_level": 0, "sb": "yes", "tol": 1e-7, "acceptable_tol": 1e-5, "acceptable_iter": 5,
    "max_iter": 400, "mu_strategy": "adaptive", "limited_memory_max_history": 3}
"""IPOPT options of every NLP built from now on (the Hessian choice is added per NLP)."""
FAST_START_OPTIONS: dict[str, Any] = {
    "warm_start_init_point": "yes", "mu_init": 1e-4, "warm_start_bound_push": 1e-6,
    "warm_start_mult_bound_push": 1e-6}
"""Added for the screening solve: start from the guess as given (a consistent motion) with a
small barrier; 12 % fewer iterations over the benchmark problems. With active workspace
constraints the default start is more robust (105 against 227 iterations in one case), so
the full NLP keeps it."""
GUESS_ACCEL_FRACTION = 0.7
"""Initial guess: this fraction of the acceleration the start's command room allows."""
MIDPOINT_MARGINS = False
"""Impose the workspace margins at interval midpoints too. Off: at the nodes only, with
:data:`NODE_MARGIN` of slack for the short excursion in between (the dense re-check
verifies it); it halves the constraint count and the cost per iteration."""
SCREEN_MAX_ITER = 60
"""Iteration limit of the screening solve without workspace margins (then the full NLP)."""
NODE_MARGIN = 2e-3
"""Lower bound of the workspace margins at the nodes [rad, or sine / determinant units]."""


@dataclass(frozen=True)
class SolveResult:
    """What one optimiser run produced (:func:`solve_min_time` may combine two runs: the
    screening solve and the full one; times and iterations are then summed).

    ``trajectory`` is the last iterate as a Trajectory whenever it is finite (None from
    :func:`solve_transcription`, and for an unusable iterate): check ``success`` first.
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
    nodes: dict[str, np.ndarray] = field(repr=False)
    """``p`` (N+1, 3) [m], ``v`` (N+1, 3) [m/s], ``a`` (N, 3) [m/s^2] of the last iterate."""
    workspace: str = "imposed"
    """How the workspace constraints were handled: "imposed", or "inactive (screened)" when
    the solve without them already stayed inside (see :func:`solve_min_time`)."""


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


def limit_solver_threads() -> None:
    """Run CasADi's bundled OpenBLAS and OpenMP (under IPOPT's MUMPS) on one thread.

    On a loaded 2-core machine their worker threads spin and wait: one IPOPT solve measured
    0.09 s of CPU but 0.39 s of wall time; single-threaded, 0.15 s. One plan per core is the
    service's model anyway. Done once per process, at the first NLP build; it affects every
    CasADi user in the process (they run small problems too).
    """
    global _threads_limited
    if _threads_limited:
        return
    _threads_limited = True
    folder = Path(ca.__file__).parent
    for pattern, symbol in (("libcasadi-tp-openblas.so*", "openblas_set_num_threads"),
                            ("libgomp*.so*", "omp_set_num_threads")):
        for lib in sorted(folder.glob(pattern))[:1]:
            try:
                getattr(ctypes.CDLL(str(lib)), symbol)(1)
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


def falcon_constraints(model: FalconModel, *, compiled: bool = True, workspace: bool = True) -> PointConstraints:
    """The Falcon's constraints: commands Tc(p, v, a) / COMMAND_SCALE (the model's inverse
    dynamics, common subexpressions merged) and the workspace margins.

    ``workspace`` False leaves the margins out (for the screening solve).
    With ``compiled`` both functions and their Jacobians are compiled to C once and cached
    on disk (:mod:`falcon_plan.planning.kernels`): ~12x faster than CasADi's virtual machine.
    """
    fns = model.functions
    n_eff = fns.expressions.eff.numel()
    p, v, a = ca.SX.sym("p", 3), ca.SX.sym("v", 3), ca.SX.sym("a", 3)
    eff = ca.SX.sym("eff", n_eff)
    tc = ca.cse(fns.inverse_dynamics(p, v, a, eff) / COMMAND_SCALE)
    rows = ca.Function("falcon_scaled_command", [p, v, a, eff], [tc])
    margins = ca.Function("falcon_margins", [p, eff], [ca.cse(fns.workspace_margins(p, eff))])
    if compiled:
        rows = compile_with_jacobian(rows)
        margins = compile_with_jacobian(margins)
    if not workspace:
        return PointConstraints(("falcon", model.params, model.limits, rows.name(), "no-workspace"),
                                rows, None, n_eff)
    return PointConstraints(("falcon", model.params, model.limits, rows.name()), rows, margins, n_eff)


def box_constraints() -> PointConstraints:
    """Per-axis velocity and acceleration rows (v, a) of a point mass (a 3-axis double
    integrator): the transcription without the Falcon, for the regression case."""
    p, v, a = ca.SX.sym("p", 3), ca.SX.sym("v", 3), ca.SX.sym("a", 3)
    eff = ca.SX.sym("eff", 1)
    rows = ca.Function("box_rows", [p, v, a, eff], [ca.vertcat(v, a)])
    return PointConstraints(("double-integrator",), rows, None, 1)


class MinTimeNlp:
    """The minimum-time NLP for one (model parameters, limits, N, Hessian choice), built once.

    Parameters
    ----------
    constraints : the point constraints (rows bounded per query, margins >= 0).
    n_intervals : N, the number of equal intervals.
    hessian : "exact" or "limited-memory".
    max_iter : IPOPT's iteration limit.
    fast_start : add :data:`FAST_START_OPTIONS`.
    """

    def __init__(self, constraints: PointConstraints, n_intervals: int, hessian: str = "limited-memory",
                 max_iter: int = 400, fast_start: bool = False) -> None:
        t0 = time.perf_counter()
        limit_solver_threads()
        self.n = n = int(n_intervals)
        n_eff = constraints.n_eff
        command, margins = constraints.rows, constraints.margins
        self.n_rows = command.size1_out(0)

        # --- variables: scaled final time, node states (6, N+1), interval accelerations (3, N)
        w_t = ca.MX.sym("T", 1)
        w_x = ca.MX.sym("X", 6, n + 1)
        w_a = ca.MX.sym("A", 3, n)
        eff = ca.MX.sym("eff", n_eff)
        big_t = TIME_SCALE * w_t
        x = ca.DM(STATE_SCALE) * w_x          # physical (p; v), rows broadcast
        acc = ACCEL_SCALE * w_a
        p, v = x[:3, :], x[3:, :]
        h = big_t / n

        # --- dynamics: exact piecewise-constant-acceleration steps (gap-closing constraints)
        p_next = p[:, :-1] + h * v[:, :-1] + 0.5 * h * h * acc
        v_next = v[:, :-1] + h * acc
        gap = ca.vertcat(p[:, 1:] - p_next, v[:, 1:] - v_next) / ca.DM(STATE_SCALE)

        # --- point rows (commands) at both ends of every interval, one mapped call over 2N points
        rows = command.map(2 * n)(ca.horzcat(p[:, :-1], p[:, 1:]), ca.horzcat(v[:, :-1], v[:, 1:]),
                                  ca.horzcat(acc, acc), ca.repmat(eff, 1, 2 * n))
        parts = [ca.vec(gap), ca.vec(rows)]
        # --- workspace margins at interior nodes and interval midpoints
        if margins is not None and MIDPOINT_MARGINS:
            p_mid = p[:, :-1] + 0.5 * h * v[:, :-1] + 0.125 * h * h * acc
            n_margin_points = 2 * n - 1
            mg = margins.map(n_margin_points)(ca.horzcat(p[:, 1:-1], p_mid),
                                              ca.repmat(eff, 1, n_margin_points))
            parts.append(ca.vec(mg))
        elif margins is not None:
            mg = margins.map(n - 1)(p[:, 1:-1], ca.repmat(eff, 1, n - 1))
            parts.append(ca.vec(mg))
        g = ca.vertcat(*parts)
        w = ca.vertcat(w_t, ca.vec(w_x), ca.vec(w_a))
        self.n_w = w.numel()
        self.n_g = g.numel()
        n_row_entries = 2 * n * self.n_rows
        self._slices = {"gap": slice(0, 6 * n), "rows": slice(6 * n, 6 * n + n_row_entries),
                        "margins": slice(6 * n + n_row_entries, self.n_g)}

        self.deadline = _Deadline(f"deadline_{id(self)}", self.n_w, self.n_g, n_eff)
        ipopt = dict(IPOPT_OPTIONS, **(FAST_START_OPTIONS if fast_start else {}), max_iter=int(max_iter),
                     hessian_approximation="exact" if hessian == "exact" else "limited-memory")
        opts = {"ipopt": ipopt, "print_time": False, "record_time": True,
                "iteration_callback": self.deadline, "error_on_fail": False}
        self.solver = ca.nlpsol(f"falcon_min_time_{n}", "ipopt",
                                {"x": w, "p": eff, "f": w_t, "g": g}, opts)
        self.lock = threading.Lock()
        self.build_time_s = time.perf_counter() - t0
        log.info("built min-time NLP N=%d (%d vars, %d constraints) in %.2f s", n, self.n_w,
                 self.n_g, self.build_time_s)

    # --- packing ---------------------------------------------------------------------------
    def pack(self, t_s: float, p: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Physical values -> the NLP's scaled variable vector (column-major like ca.vec)."""
        xs = np.vstack([np.asarray(p, float).T, np.asarray(v, float).T]) / STATE_SCALE[:, None]
        return np.concatenate([[t_s / TIME_SCALE], xs.ravel(order="F"),
                               (np.asarray(a, float).T / ACCEL_SCALE).ravel(order="F")])

    def unpack(self, w: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """The NLP's variable vector -> (T [s], p (N+1,3), v (N+1,3), a (N,3))."""
        w = np.asarray(w, float).ravel()
        n = self.n
        xs = w[1:1 + 6 * (n + 1)].reshape((6, n + 1), order="F") * STATE_SCALE[:, None]
        acc = w[1 + 6 * (n + 1):].reshape((3, n), order="F") * ACCEL_SCALE
        return float(w[0] * TIME_SCALE), xs[:3].T.copy(), xs[3:].T.copy(), acc.T.copy()

    def bounds(self, problem: PlanProblem, via_nodes: list[int], row_lower: np.ndarray,
               row_upper: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(lbx, ubx, lbg, ubg) for one query; ``row_lower``/``row_upper`` bound the point
        rows (one value per row, the same at every point)."""
        n = self.n
        lo_p, hi_p = np.array(POSITION_BOX_M[0]), np.array(POSITION_BOX_M[1])
        lo_x = np.tile(np.concatenate([lo_p, -SPEED_BOUND_M_S * np.ones(3)])[:, None], (1, n + 1))
        hi_x = np.tile(np.concatenate([hi_p, SPEED_BOUND_M_S * np.ones(3)])[:, None], (1, n + 1))
        fixed = {0: (problem.start_m, problem.start_velocity_m_s),
                 n: (problem.goal_m, problem.goal_velocity_m_s)}
        for k, node in enumerate(via_nodes):
            lo_x[:3, node] = hi_x[:3, node] = problem.via_m[k]
        for node, (pos, vel) in fixed.items():
            lo_x[:, node] = hi_x[:, node] = np.concatenate([pos, vel])
        lo_a = -ACCEL_BOUND_M_S2 * np.ones((3, n))
        lbx = np.concatenate([[T_BOUNDS_S[0] / TIME_SCALE], (lo_x / STATE_SCALE[:, None]).ravel(order="F"),
                              (lo_a / ACCEL_SCALE).ravel(order="F")])
        ubx = np.concatenate([[T_BOUNDS_S[1] / TIME_SCALE], (hi_x / STATE_SCALE[:, None]).ravel(order="F"),
                              (-lo_a / ACCEL_SCALE).ravel(order="F")])
        lbg, ubg = np.zeros(self.n_g), np.zeros(self.n_g)
        lbg[self._slices["rows"]] = np.tile(np.broadcast_to(row_lower, (self.n_rows,)), 2 * self.n)
        ubg[self._slices["rows"]] = np.tile(np.broadcast_to(row_upper, (self.n_rows,)), 2 * self.n)
        lbg[self._slices["margins"]] = 0.0 if MIDPOINT_MARGINS else NODE_MARGIN
        ubg[self._slices["margins"]] = np.inf
        return lbx, ubx, lbg, ubg


_nlp_cache: dict[tuple[Any, ...], MinTimeNlp] = {}
_nlp_cache_lock = threading.Lock()


def get_nlp(constraints: PointConstraints, n_intervals: int, hessian: str = "limited-memory",
            max_iter: int = 400, fast_start: bool = False) -> MinTimeNlp:
    """The NLP for these constraints, N, Hessian choice and IPOPT settings: built once, cached."""
    key = (constraints.key, int(n_intervals), hessian, int(max_iter), fast_start)
    with _nlp_cache_lock:
        nlp = _nlp_cache.get(key)
        if nlp is None:
            nlp = _nlp_cache[key] = MinTimeNlp(constraints, n_intervals, hessian, max_iter, fast_start)
    return nlp


_constraint_cache: dict[tuple[Any, ...], PointConstraints] = {}


def model_constraints(model: FalconModel, hessian: str, workspace: bool = True) -> PointConstraints:
    """The Falcon constraints of ``model`` (compiled for the limited-memory Hessian, whose
    solver needs first derivatives only; the exact Hessian uses CasADi's virtual machine),
    with or without the workspace margins."""
    key = (model.params, model.limits, hessian, workspace)
    with _nlp_cache_lock:
        if key not in _constraint_cache:
            _constraint_cache[key] = falcon_constraints(model, compiled=hessian != "exact", workspace=workspace)
        return _constraint_cache[key]


def workspace_respected(model: FalconModel, nodes: dict[str, np.ndarray], t_final: float) -> bool:
    """True when a solution of the screening solve satisfies what the full NLP imposes:
    margins >= NODE_MARGIN at the interior nodes, and >= 0 at the interval midpoints."""
    p, v, a = nodes["p"], nodes["v"], nodes["a"]
    h = t_final / len(a)
    mid = p[:-1] + 0.5 * h * v[:-1] + 0.125 * h * h * a
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(mid))):
        return False
    inner = model.workspace_margins(p[1:-1]) if len(p) > 2 else np.zeros((0, 1))
    return bool(np.all(inner >= NODE_MARGIN) and np.all(model.workspace_margins(mid) >= 0.0))


def via_nodes(problem: PlanProblem, n_intervals: int) -> list[int]:
    """Nodes at which the via points are imposed: spread in proportion to the straight-line
    distance along start -> via ... -> goal, distinct, strictly inside (1 .. N-1)."""
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


def initial_guess(model: FalconModel, problem: PlanProblem, n: int, tc_max: float,
                  nodes: list[int]) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """A straight-line (polyline through the via points) guess with a bang-bang time scaling.

    The acceleration magnitude comes from the model: the command per unit acceleration along
    the start-goal direction at the start, against what is left of tc_max after holding
    gravity, times :data:`GUESS_ACCEL_FRACTION`. Returns (T [s], p, v, a) at the nodes.
    """
    pts = problem.waypoints_m
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    length = max(float(seg.sum()), 1e-6)
    direction = (pts[1] - pts[0]) / max(seg[0], 1e-9)
    start = np.asarray(problem.start_m)
    hold = model.inverse_dynamics(start, np.zeros(3), np.zeros(3))
    per_accel = np.abs(model.inverse_dynamics(start, np.zeros(3), direction) - hold)
    room = np.maximum(tc_max - np.abs(hold), 0.1 * tc_max)
    a_max = GUESS_ACCEL_FRACTION * float(np.min(room / np.maximum(per_accel, 1e-9)))
    t_total = 2.0 * math.sqrt(length / a_max)
    # bang-bang arc-length profile sampled at the nodes (a_k constant per interval)
    tk = np.linspace(0.0, t_total, n + 1)
    half = t_total / 2
    s = np.where(tk <= half, 0.5 * a_max * tk**2, length - 0.5 * a_max * (t_total - tk) ** 2)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    p = np.stack([np.interp(s, cum, pts[:, i]) for i in range(3)], axis=1)
    # via nodes exactly on their points
    for k, node in enumerate(nodes):
        p[node] = problem.via_m[k]
    h = t_total / n
    v = np.gradient(p, h, axis=0)
    v[0], v[-1] = problem.start_velocity_m_s, problem.goal_velocity_m_s
    a = np.diff(v, axis=0) / h
    return t_total, p, v, a


def solve_min_time(model: FalconModel, problem: PlanProblem, *, n_intervals: int, tc_max: float,
                   time_budget_s: float = math.inf, hessian: str = "limited-memory",
                   guess: tuple[float, np.ndarray, np.ndarray, np.ndarray] | None = None,
                   screen_workspace: bool = True) -> SolveResult:
    """Solve the minimum-time problem; never raises for solver failure (see ``success``).

    Parameters
    ----------
    model : the dynamics; its effects (plus ``problem.payload_kg``) are the NLP parameter.
    problem : start, goal, end velocities, via points, payload.
    n_intervals : N.
    tc_max : command limit [command units].
    time_budget_s : wall-clock budget [s]; the optimiser stops when it is used up.
    hessian : "exact" or "limited-memory".
    guess : (T, p (N+1,3), v (N+1,3), a (N,3)) initial guess; default :func:`initial_guess`.
    screen_workspace : first solve without the workspace margins (at most
        :data:`SCREEN_MAX_ITER` iterations) and impose them only if that solution leaves the
        workspace (or the screening solve fails): about 2x faster when they are inactive.
    """
    nodes = via_nodes(problem, n_intervals)
    if guess is None:
        guess = initial_guess(model, problem, n_intervals, tc_max, nodes)
    limit = tc_max / COMMAND_SCALE * np.ones(3)
    eff = payload_model(model, problem).effect_vector
    # Build (and, the first time on a machine, compile) the NLPs before the clock starts:
    # the time budget is for solving, not for a one-off compilation.
    for workspace, max_iter in ((False, SCREEN_MAX_ITER), (True, 400))[0 if screen_workspace else 1:]:
        get_nlp(model_constraints(model, hessian, workspace), n_intervals, hessian, max_iter, not workspace)
    t_start = time.perf_counter()

    def solve(workspace: bool, max_iter: int) -> SolveResult:
        return solve_transcription(model_constraints(model, hessian, workspace), problem,
                                   n_intervals=n_intervals, row_lower=-limit, row_upper=limit, eff=eff,
                                   guess=guess, time_budget_s=time_budget_s - (time.perf_counter() - t_start),
                                   hessian=hessian, max_iter=max_iter, fast_start=not workspace)

    if not screen_workspace:
        result = solve(True, 400)
    else:
        # The workspace margins are half the NLP's constraints and are inactive in every
        # benchmark problem (minimum-time paths stay away from the boundary): solve without
        # them first; keep that solution if it stays inside (then it is also optimal with
        # them), else solve with them, from the same guess.
        first = solve(False, SCREEN_MAX_ITER)
        if first.success and workspace_respected(model, first.nodes, first.duration_s):
            result = dataclasses.replace(first, workspace="inactive (screened)")
        elif first.timed_out:
            result = first
        else:
            second = solve(True, 400)
            result = dataclasses.replace(
                second, iterations=first.iterations + second.iterations,
                solve_time_s=first.solve_time_s + second.solve_time_s,
                solve_cpu_s=first.solve_cpu_s + second.solve_cpu_s,
                workspace="imposed (active)" if first.success else f"imposed (screening: {first.solver_status})")
    t_final, p, v, a = result.duration_s, result.nodes["p"], result.nodes["v"], result.nodes["a"]
    traj = None
    if np.all(np.isfinite(p)) and np.all(np.isfinite(a)) and t_final > 0:
        traj = nodes_to_trajectory(model, problem, t_final, p, v, a, source="casadi",
                                   meta={"n_intervals": n_intervals, "solver_status": result.solver_status})
    return dataclasses.replace(result, trajectory=traj)


def solve_transcription(constraints: PointConstraints, problem: PlanProblem, *, n_intervals: int,
                        row_lower: np.ndarray, row_upper: np.ndarray, eff: np.ndarray,
                        guess: tuple[float, np.ndarray, np.ndarray, np.ndarray],
                        time_budget_s: float = math.inf, hessian: str = "limited-memory",
                        max_iter: int = 400, fast_start: bool = False) -> SolveResult:
    """Solve the minimum-time transcription with any point constraints (the machinery under
    :func:`solve_min_time`; the trajectory is left None). Never raises for solver failure."""
    nlp = get_nlp(constraints, n_intervals, hessian, max_iter, fast_start)
    nodes = via_nodes(problem, n_intervals)
    lbx, ubx, lbg, ubg = nlp.bounds(problem, nodes, row_lower, row_upper)
    x0 = np.clip(nlp.pack(*guess), lbx, ubx)
    with nlp.lock:
        nlp.deadline.deadline = time.perf_counter() + time_budget_s
        nlp.deadline.expired = False
        t0, c0 = time.perf_counter(), time.process_time()
        sol = nlp.solver(x0=x0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg, p=eff)
        solve_time, solve_cpu = time.perf_counter() - t0, time.process_time() - c0
        stats = nlp.solver.stats()
        timed_out = nlp.deadline.expired
    status = str(stats.get("return_status", "unknown"))
    success = bool(stats.get("success", False)) and not timed_out
    t_final, p, v, a = nlp.unpack(np.asarray(sol["x"]))
    return SolveResult(success=success, solver_status="time budget exhausted" if timed_out else status,
                       iterations=int(stats.get("iter_count", -1)), solve_time_s=solve_time,
                       solve_cpu_s=solve_cpu,
                       duration_s=t_final, n_intervals=n_intervals, timed_out=timed_out,
                       trajectory=None, nodes={"p": p, "v": v, "a": a})


def nodes_to_trajectory(model: FalconModel, problem: PlanProblem, t_final: float, p: np.ndarray,
                        v: np.ndarray, a: np.ndarray, *, source: str,
                        meta: dict[str, Any] | None = None) -> Trajectory:
    """A :class:`Trajectory` from node values of the transcription.

    The last sample's acceleration is zero when the goal is at rest (the device then holds
    still), else the last interval's; commands are the model's inverse dynamics at each
    sample (right limits: the acceleration of the interval that starts there), with the
    problem's payload.
    """
    n = len(a)
    t = np.linspace(0.0, t_final, n + 1)
    a_last = np.zeros(3) if not any(problem.goal_velocity_m_s) else a[-1]
    acc = np.vstack([a, a_last])
    cmd = payload_model(model, problem).inverse_dynamics(p, v, acc)
    return Trajectory(t, p, v, acc, cmd, model.params.name, source, dict(meta or {}))


def payload_model(model: FalconModel, problem: PlanProblem) -> FalconModel:
    """``model`` with the problem's payload added to its effects' payload."""
    if problem.payload_kg == 0.0:
        return model
    return model.with_effects(model.effects.replace(payload_kg=model.effects.payload_kg + problem.payload_kg))


__all__ = ["MinTimeNlp", "PointConstraints", "falcon_constraints", "box_constraints", "solve_transcription", "model_constraints", "SolveResult", "get_nlp", "solve_min_time", "initial_guess", "via_nodes",
           "nodes_to_trajectory", "payload_model", "COMMAND_SCALE"]
