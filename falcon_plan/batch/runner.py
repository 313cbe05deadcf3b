"""The batch runner: plan every problem, read the cross-check references, execute on the plant.

For each :class:`~falcon_plan.batch.loader.Problem`, one task (in a worker process):

1. :func:`falcon_plan.planning.api.plan` with the problem's command limit, grid, end
   velocities, via points and payload (:func:`plan_options`); a refusal (``WorkspaceError``,
   ``InvalidProblemError``, ``PlanningFailed``) is classified into one of
   :data:`~falcon_plan.batch.loader.REFUSAL_REASONS` (:func:`classify_refusal`);
2. the reference durations (toppra on the same path, toppra on the straight line, ruckig)
   and their run times come from the planner's report;
3. the planned trajectory is executed by the :class:`~falcon_plan.execution.executor.Executor`
   on a :class:`~falcon_plan.devices.sim_device.SimDevice` (simulated plant with the
   problem's payload, as fast as possible), seeded from the global seed and the problem name,
   and the tracking error is recorded.

A reference whose report entry is missing is ``unavailable`` (with a note) instead of failing
the run; an exception inside a task becomes an ``error`` row. Each task returns one :class:`ResultRow` per method in :data:`METHODS`. Rows
are a function of the problems and the seed, except the columns in :data:`TIMING_COLUMNS`.
"""
from __future__ import annotations

import concurrent.futures as futures
import contextlib
import dataclasses
import logging
import math
import multiprocessing
import os
import re
import signal
import threading
import time
import zlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import numpy as np

from falcon_plan.batch.loader import Expectation, Problem
from falcon_plan.planning.problem import PlanProblem

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.planning.problem import PlanOptions
    from falcon_plan.planning.report import Plan
    from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)

PLANNER = "casadi"
"""The method every other one is compared against."""
CROSSCHECKS = {
    "toppra_same_path": ("toppra_same_path_s", "toppra"),
    "toppra_straight": ("toppra_straight_s", "toppra"),
    "ruckig": ("ruckig_s", "ruckig"),
}
"""Reference methods: (report key of the duration [s], key of its run time in the report's
``timings_s``). The planner times its two toppra runs together, so both toppra rows show that
combined time."""
METHODS = (PLANNER, *CROSSCHECKS)
"""Every method, in table order."""

STATUSES = ("solved", "refused", "failed", "skipped", "error", "unavailable")
"""Row statuses: ``solved``; ``refused`` (the planner declined the problem, ``reason`` says
why); ``failed`` (a reference gave no duration, see ``note``); ``skipped`` (the method does
not apply: see :func:`reference_not_applicable`, or the planner did not solve); ``error``
(an unexpected exception, in ``note``); ``unavailable`` (the planner's report has no duration for this reference)."""

QUICK_INTERVALS = 20
"""Planner grid of ``quick`` runs [intervals] (quick runs also skip the 2N refinement)."""

TIMING_COLUMNS = ("solve_time_s", "wall_time_s")
"""Columns that measure time on this machine, so differ between identical runs."""

_VIA_PATTERN = re.compile(r"\bvia point")


@dataclass(frozen=True)
class RunOptions:
    """How to run a batch.

    Attributes
    ----------
    seed : global seed; each problem's seed is :func:`task_seed` of it and the name.
    jobs : worker processes (``None``: ``os.cpu_count()``); 1 runs in this process.
    quick : plan on a :data:`QUICK_INTERVALS` grid without refinement (a smoke run).
    execute : run each planned trajectory on the simulated plant.
    warm_up : plan :data:`WARM_UP` once per worker before its tasks (see :func:`warm_up`).
    model_path : a model file (:mod:`falcon_plan.model.modelfile`) to plan and execute with
        (and the simulated device's world); ``None``: the nominal model.
    """

    seed: int = 0
    jobs: int | None = None
    quick: bool = False
    execute: bool = True
    warm_up: bool = True
    model_path: str | None = None

    def __post_init__(self) -> None:
        if self.jobs is not None and (isinstance(self.jobs, bool) or self.jobs < 1):
            from falcon_plan.errors import InvalidParameterError

            raise InvalidParameterError(f"jobs must be a whole number >= 1, got {self.jobs!r}")

    @property
    def workers(self) -> int:
        """Number of worker processes to use."""
        return self.jobs if self.jobs is not None else (os.cpu_count() or 1)


@dataclass
class ResultRow:
    """One problem under one method: a row of the results table (``None``: empty cell).

    Tracking errors are those of the planner's trajectory executed on the plant, so they are
    on planner rows only; margins are the planner's dense re-check of its own plan.

    Attributes
    ----------
    problem : the problem's name.
    method : one of :data:`METHODS`.
    expected : the problem's expectation, ``solved`` or ``refused:<reason>``.
    status : one of :data:`STATUSES`.
    reason : refusal reason (one of ``REFUSAL_REASONS``) when refused, else ''.
    met : the outcome is what the problem expects (solved, or refused for the stated
        reason); ``None`` when the method does not apply to the problem (status ``skipped``).
    duration_s : duration of the motion [s].
    duration_ratio : this method's duration over the planner's (1 on the planner row).
    solve_time_s : run time of the method [s]: the optimiser (+ fallback) for the planner,
        the report's timing for the references.
    wall_time_s : wall time of the whole task (plan, references, refinement, execution)
        [s], planner rows only.
    command_margin : 1 - max |Tc| / tc_max on the planner's dense re-check (>= 0: within
        the limit).
    workspace_margin : smallest workspace constraint value on the dense re-check (>= 0:
        inside).
    track_rms_counts : worst leg's RMS tracking error [counts].
    track_max_counts : worst leg's largest tracking error [counts].
    track_rms_mm : RMS of the Cartesian tracking error norm [mm].
    track_max_mm : largest Cartesian tracking error norm [mm].
    tags : the problem's tags, separated by spaces.
    note : free text: a fallback, a skip or failure reason, an execution problem.
    """

    problem: str
    method: str
    expected: str
    status: str
    reason: str = ""
    met: bool | None = None
    duration_s: float | None = None
    duration_ratio: float | None = None
    solve_time_s: float | None = None
    wall_time_s: float | None = None
    command_margin: float | None = None
    workspace_margin: float | None = None
    track_rms_counts: float | None = None
    track_max_counts: float | None = None
    track_rms_mm: float | None = None
    track_max_mm: float | None = None
    tags: str = ""
    note: str = ""

    def to_dict(self) -> dict[str, Any]:
        """Plain dict in column order."""
        return dataclasses.asdict(self)


COLUMNS = tuple(f.name for f in dataclasses.fields(ResultRow))
"""Column order of the results table."""


def task_seed(seed: int, name: str) -> int:
    """Deterministic per-problem seed from the global ``seed`` and the problem ``name``
    (independent of process, order and Python's hash randomisation)."""
    entropy = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode("utf-8"))])
    return int(entropy.generate_state(1)[0])


# --- inputs of the planner -----------------------------------------------------------------
_MODELS: dict[tuple[float, str | None], FalconModel] = {}


def problem_model(payload_kg: float = 0.0, model_path: str | None = None) -> FalconModel:
    """The nominal FalconModel, or the one in the model file ``model_path`` (``None``:
    nominal), with ``payload_kg`` [kg] added as an effect when nonzero (cached per process)."""
    key = (payload_kg, model_path)
    if key not in _MODELS:
        from falcon_plan.model.modelfile import load_model

        base = load_model(model_path)
        _MODELS[key] = base.with_effects(base.effects.replace(payload_kg=base.effects.payload_kg + payload_kg)) \
            if payload_kg else base
    return _MODELS[key]


def plan_options(problem: Problem, quick: bool) -> PlanOptions:
    """The planner's ``PlanOptions`` for ``problem``: its command limit and grid (capped at
    :data:`QUICK_INTERVALS` and without refinement when ``quick``), cross-checks on, the
    planner's own plant check off (the runner executes the plan itself), no warm start;
    everything else at the planner's defaults."""
    from falcon_plan.planning.problem import PlanOptions

    # cold starts only: a warm-start cache of solved neighbours would make results depend on
    # the order the tasks ran in
    changes: dict[str, Any] = {"tc_max": problem.tc_max, "crosscheck": True, "plant_check": False,
                               "warm_start": "none"}
    if problem.n_intervals is not None:
        changes["n_intervals"] = problem.n_intervals
    if quick:
        changes["n_intervals"] = min(changes.get("n_intervals", QUICK_INTERVALS), QUICK_INTERVALS)
        changes["refine"] = False
    return PlanOptions.of(**changes)


def classify_refusal(exc: BaseException) -> str:
    """Which of :data:`~falcon_plan.batch.loader.REFUSAL_REASONS` the planner exception
    ``exc`` means.

    ``WorkspaceError``: ``via_unreachable`` when it names a via point, else
    ``outside_workspace``; an ``InvalidProblemError`` about holding against gravity or
    tc_max: ``tc_max_too_small``; anything else declined (``PlanningFailed``, other invalid
    problems): ``infeasible``.
    """
    from falcon_plan.errors import WorkspaceError

    text = str(exc)
    if isinstance(exc, WorkspaceError):
        return "via_unreachable" if _VIA_PATTERN.search(text) else "outside_workspace"
    if "tc_max_too_small" in text or "against gravity" in text:
        return "tc_max_too_small"
    return "infeasible"


# --- one task ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Tracking:
    """Tracking error of one execution (``None`` where not measured) and a note.

    Attributes
    ----------
    rms_counts, max_counts : worst leg's RMS and largest tracking error [counts].
    rms_mm, max_mm : RMS and largest Cartesian tracking error norm [mm].
    note : why the execution did not complete, or ''.
    """

    rms_counts: float | None = None
    max_counts: float | None = None
    rms_mm: float | None = None
    max_mm: float | None = None
    note: str = ""


def execute_on_plant(trajectory: Trajectory, problem: Problem, seed: int, model_path: str | None = None) -> Tracking:
    """Run ``trajectory`` with the Executor on a ``SimDevice`` seeded with ``seed`` (as fast
    as possible) opened at the problem's start point with the problem's payload, in the world
    of the model file ``model_path`` (``None``: nominal).

    Returns the worst leg's RMS and max error [counts] and the RMS and max of the Cartesian
    error norm [mm], over the motion and after it (the executor's pre-roll, which holds the
    start at rest, is excluded; a problem that starts moving therefore starts with a jump).
    """
    from falcon_plan.devices.sim_device import SimDevice
    from falcon_plan.execution.executor import ExecutionStatus, Executor

    model = problem_model(problem.motion.payload_kg, model_path)
    with SimDevice(model=model, seed=seed, start_position_m=np.asarray(problem.motion.start_m)) as device:
        device.home()
        report = Executor(device, model).run(trajectory)
    note = "" if report.status == ExecutionStatus.COMPLETED else f"execution {report.status}: {report.reason}"
    tr = report.tracking
    if tr is None:
        return Tracking(note=note or "execution sent no samples")
    return Tracking(max(tr.counts_rms), max(tr.counts_max), tr.norm_rms_mm, tr.norm_max_mm, note)


def _number(value: Any) -> float | None:
    """``value`` as a float if it is a finite real number, else None."""
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return None


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300]


def outcome_met(problem: Problem, row: ResultRow) -> bool | None:
    """True when the row's outcome is what the problem expects (solved, or refused for the
    stated reason), False when not, None when the method did not apply (``skipped``)."""
    if row.status == "skipped":
        return None
    if problem.expect.status == "solved":
        return row.status == "solved"
    return row.status == "refused" and row.reason == problem.expect.reason


def reference_not_applicable(method: str, problem: Problem, report: dict[str, Any]) -> str:
    """Why reference ``method`` does not answer ``problem`` ('' when it does), from the
    references' documented scope: toppra on the same path needs the optimiser's path (not a
    fallback plan, as the planner's ``report`` dict says in its ``method``); toppra on the
    straight line needs rest at both ends; ruckig's Community edition ignores via points."""
    if method == "toppra_same_path" and report.get("method") != PLANNER:
        return "no optimiser path (the plan is the fallback)"
    if method == "toppra_straight" and not problem.from_rest:
        return "straight-line reference needs rest at both ends"
    if method == "ruckig" and problem.motion.via_m:
        return "ruckig reference ignores via points (Community edition)"
    return ""


def _fill_planner_row(row: ResultRow, plan_result: Plan, report: dict[str, Any]) -> None:
    row.status = "solved"
    row.duration_s = float(plan_result.trajectory.duration_s)
    row.duration_ratio = 1.0
    ratio = _number(report.get("worst_command_ratio"))
    row.command_margin = None if ratio is None else 1.0 - ratio
    row.workspace_margin = _number(report.get("worst_workspace_margin"))
    if report.get("method", PLANNER) != PLANNER:
        row.note = f"{report.get('method')}: {report.get('fallback_reason', '')}"


_NOTE_PREFIX = {"toppra_same_path": "toppra same path", "toppra_straight": "toppra straight",
                "ruckig": "ruckig"}
"""How the planner's report notes name each reference."""


def _fill_reference_row(row: ResultRow, planner: ResultRow, problem: Problem, report: dict[str, Any]) -> None:
    duration_key, timing_key = CROSSCHECKS[row.method]
    if planner.status != "solved":
        row.status = "skipped"
        row.note = f"planner {planner.status}"
        return
    why_not = reference_not_applicable(row.method, problem, report)
    if why_not:
        row.status, row.note = "skipped", why_not
        return
    row.solve_time_s = _number(report.get("timings_s", {}).get(timing_key))
    row.duration_s = _number(report.get(duration_key))
    if row.duration_s is not None:
        row.status = "solved"
        row.duration_ratio = row.duration_s / planner.duration_s if planner.duration_s else None
    elif duration_key not in report:
        row.status, row.note = "unavailable", f"the planner's report has no {duration_key}"
    else:
        row.status = "failed"
        row.note = "; ".join(n for n in report.get("notes", []) if n.startswith(_NOTE_PREFIX[row.method])) \
            or "no duration reported"


def run_problem(problem: Problem, seed: int = 0, quick: bool = False, execute: bool = True,
                model_path: str | None = None) -> list[ResultRow]:
    """Plan, cross-check and execute one problem: one :class:`ResultRow` per method.
    ``model_path``: plan and execute with that model file (:attr:`RunOptions.model_path`).

    ``seed`` seeds the simulated device (the batch passes :func:`task_seed`); ``quick``
    plans on the :data:`QUICK_INTERVALS` grid without refinement (:func:`plan_options`);
    ``execute`` runs the plan on the simulated plant. Never raises for a planner or execution
    problem: those become statuses and notes.
    """
    started = time.perf_counter()
    rows = {m: ResultRow(problem.name, m, problem.expect.label(), "skipped", tags=" ".join(problem.tags))
            for m in METHODS}
    main = rows[PLANNER]
    report: dict[str, Any] = {}
    plan_result = None
    from falcon_plan.errors import InvalidProblemError, PlanningFailed, WorkspaceError
    from falcon_plan.planning.api import plan_problem

    try:
        plan_result = plan_problem(problem.motion, plan_options(problem, quick), problem_model(model_path=model_path))
    except (WorkspaceError, InvalidProblemError, PlanningFailed) as exc:
        main.status, main.reason, main.note = "refused", classify_refusal(exc), _one_line(exc)
        failed_report = getattr(exc, "report", None)
        report = failed_report.to_dict() if failed_report is not None else {}
    except Exception as exc:  # a bug in the planner must not end the batch
        log.exception("the planner raised on %s", problem.name)
        main.status, main.note = "error", f"{type(exc).__name__}: {_one_line(exc)}"
    if plan_result is not None:
        report = plan_result.report.to_dict()
        _fill_planner_row(main, plan_result, report)
        if execute:
            try:
                tracking = execute_on_plant(plan_result.trajectory, problem, seed, model_path)
            except Exception as exc:  # an execution failure is a result, not a crash
                log.exception("execution failed on %s", problem.name)
                tracking = Tracking(note=f"execution error {type(exc).__name__}: {_one_line(exc)}")
            main.track_rms_counts, main.track_max_counts = tracking.rms_counts, tracking.max_counts
            main.track_rms_mm, main.track_max_mm = tracking.rms_mm, tracking.max_mm
            main.note = "; ".join(filter(None, [main.note, tracking.note]))
    main.solve_time_s = _number(report.get("solve_time_s"))
    for method in CROSSCHECKS:
        _fill_reference_row(rows[method], main, problem, report)
    for row in rows.values():
        row.met = outcome_met(problem, row)
    main.wall_time_s = time.perf_counter() - started
    return [rows[m] for m in METHODS]


# --- the batch -----------------------------------------------------------------------------
ProgressCallback = Callable[[int, int, str, float], None]
"""``progress(done, total, problem_name, elapsed_s)``, called as each problem finishes."""


@dataclass
class BatchResult:
    """Every row of a batch and how it was run.

    Attributes
    ----------
    rows : the result rows, in problem order, then :data:`METHODS` order.
    options : the options the batch ran with.
    wall_time_s : wall time of the whole batch, warm-up included [s].
    problems : the problems run, in order.
    """

    rows: list[ResultRow]
    options: RunOptions
    wall_time_s: float
    problems: list[Problem] = field(default_factory=list)


WARM_UP = Problem(name="warm-up", description="10 mm move at the centre, run once per worker and discarded",
                  motion=PlanProblem((0.0, 0.0, 0.125), (0.01, 0.0, 0.125)), tc_max=2500.0,
                  expect=Expectation("solved"))
"""Planned once per worker before its tasks, so that one-time costs (building the NLP and
the references' CasADi functions) do not land in the first problem's solve times."""


def warm_up(quick: bool) -> None:
    """Plan :data:`WARM_UP` with the batch's options (``quick``: as :attr:`RunOptions.quick`)
    and discard the result (never raises: a failure here shows up again, and is reported, in
    the real tasks)."""
    try:
        from falcon_plan.planning.api import plan_problem

        plan_problem(WARM_UP.motion, plan_options(WARM_UP, quick), problem_model())
    except Exception as exc:  # noqa: BLE001 - the tasks report real failures
        log.info("warm-up plan failed: %s", exc)


def _start_worker(warm: bool, quick: bool) -> None:
    """A batch worker's initializer: its signals belong to the parent (it ignores SIGINT from
    birth and keeps SIGTERM's default, see :func:`leave_signals_to_parent`), then
    :func:`warm_up` if ``warm``."""
    from falcon_plan.devices.base import leave_signals_to_parent

    leave_signals_to_parent()
    if warm:
        warm_up(quick)


def _error_rows(problem: Problem, exc: BaseException) -> list[ResultRow]:
    """Rows for a task whose worker process failed (e.g. a solver crash)."""
    return [ResultRow(problem.name, m, problem.expect.label(), "error", tags=" ".join(problem.tags),
                      note=f"worker failed: {type(exc).__name__}: {_one_line(exc)}") for m in METHODS]


@contextlib.contextmanager
def _children_ignore_sigint() -> Iterator[None]:
    """Processes started inside the block ignore SIGINT from birth (the disposition is
    inherited, and Python then installs no KeyboardInterrupt handler): a Ctrl-C reaches the
    whole process group, and only the parent should answer it (it ends the workers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def run_batch(problems: Sequence[Problem], options: RunOptions = RunOptions(),
              progress: ProgressCallback | None = None) -> BatchResult:
    """Run every problem, one task per problem on ``options.workers`` processes ("spawn"
    start method: no state inherited from the caller; each warmed up by :func:`warm_up`),
    and collect the rows in the problems' order, whatever order the tasks finish in.
    ``workers == 1`` runs in this process. ``wall_time_s`` includes the warm-up.
    ``progress``, if given, is called as each problem finishes (:data:`ProgressCallback`)."""
    started = time.perf_counter()
    results: dict[str, list[ResultRow]] = {}
    total = len(problems)

    def finished(name: str, rows: list[ResultRow]) -> None:
        results[name] = rows
        if progress is not None:
            progress(len(results), total, name, time.perf_counter() - started)

    def args(p: Problem) -> tuple[Problem, int, bool, bool, str | None]:
        return p, task_seed(options.seed, p.name), options.quick, options.execute, options.model_path

    if options.workers == 1 or total <= 1:
        if options.warm_up:
            warm_up(options.quick)
        for p in problems:
            finished(p.name, run_problem(*args(p)))
    else:
        context = multiprocessing.get_context("spawn")
        with futures.ProcessPoolExecutor(max_workers=min(options.workers, total), mp_context=context,
                                         initializer=_start_worker,
                                         initargs=(options.warm_up, options.quick)) as pool:
            with _children_ignore_sigint():  # the workers start on the first submits
                pending = {pool.submit(run_problem, *args(p)): p for p in problems}
            try:
                for future in futures.as_completed(pending):
                    p = pending[future]
                    try:
                        rows = future.result()
                    except Exception as exc:  # the worker died (e.g. a solver crash)
                        log.error("task %s failed: %s", p.name, exc)
                        rows = _error_rows(p, exc)
                    finished(p.name, rows)
            except KeyboardInterrupt:
                pool.shutdown(wait=False, cancel_futures=True)  # do not wait for queued tasks
                for child in multiprocessing.active_children():  # nor for running ones
                    child.terminate()
                raise
    ordered = [row for p in problems for row in results[p.name]]
    return BatchResult(ordered, options, time.perf_counter() - started, list(problems))
