"""Benchmark problem files: the :class:`Problem` value type, its JSON format and the loader.

A :class:`Problem` embeds the planner's :class:`~falcon_plan.planning.problem.PlanProblem`
(its ``motion``); the files keep the motion's keys flat beside the benchmark's own.

One JSON object per file (``problems/<name>.json``); ``problems/README.md`` documents every
key. Reading is strict: unknown keys, missing keys, wrong types, non-finite numbers and
out-of-range values are all errors that name the file and the key. Coordinates are metres in
the base frame of MODEL-CONVENTIONS; velocities metres per second.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

from falcon_plan.errors import InvalidProblemError
from falcon_plan.model.params import ACRA2009
from falcon_plan.planning.problem import PlanProblem
from falcon_plan.validation import require_number, require_whole_number

Point = tuple[float, float, float]


EXPECTED_STATUSES = ("solved", "refused")
"""Values of ``expect.status``."""

REFUSAL_REASONS = ("outside_workspace", "via_unreachable", "tc_max_too_small", "infeasible")
"""Values of ``expect.reason`` when ``expect.status`` is ``"refused"``:

- ``outside_workspace``: the start or goal point is outside the usable workspace;
- ``via_unreachable``: a via point is outside the usable workspace (start and goal inside);
- ``tc_max_too_small``: the commands that hold the device still at the start against gravity
  (with the payload) exceed ``tc_max``;
- ``infeasible``: the points are valid but no motion satisfies the limits (the planner
  reports the problem as infeasible).
"""

NAME_PATTERN = re.compile(r"^[a-z0-9][a-z0-9_\-]*$")
"""Problem names: lower-case letters, digits, '_' and '-'; also the file's stem."""

REQUIRED_KEYS = ("name", "description", "start_m", "goal_m", "tc_max", "tags", "expect")
OPTIONAL_KEYS = ("via_m", "start_velocity_m_s", "goal_velocity_m_s", "payload_kg", "n_intervals")
ALLOWED_KEYS = REQUIRED_KEYS + OPTIONAL_KEYS


class ProblemFileError(InvalidProblemError):
    """A benchmark problem file is unreadable or does not follow the format of
    ``problems/README.md``; the message names the file and the key."""


@dataclass(frozen=True)
class Expectation:
    """What the planner is expected to do with a problem.

    Attributes
    ----------
    status : ``"solved"`` or ``"refused"``.
    reason : one of :data:`REFUSAL_REASONS` when refused, else ``None``.
    """

    status: str
    reason: str | None = None

    def __post_init__(self) -> None:
        if self.status not in EXPECTED_STATUSES:
            raise ProblemFileError(f"expect.status must be one of {list(EXPECTED_STATUSES)}, got {self.status!r}")
        if self.status == "refused" and self.reason not in REFUSAL_REASONS:
            raise ProblemFileError(f"expect.reason must be one of {list(REFUSAL_REASONS)} for a refusal, "
                                   f"got {self.reason!r}")
        if self.status == "solved" and self.reason is not None:
            raise ProblemFileError("expect.reason is only allowed with status 'refused'")

    def label(self) -> str:
        """Short text for tables: ``solved`` or ``refused:<reason>``."""
        return self.status if self.reason is None else f"{self.status}:{self.reason}"

    def to_dict(self) -> dict[str, str]:
        """JSON form, as in the problem files."""
        return {"status": self.status} if self.reason is None else {"status": self.status, "reason": self.reason}


@dataclass(frozen=True)
class Problem:
    """One named benchmark problem: a :class:`~falcon_plan.planning.problem.PlanProblem` (the
    motion) plus what the benchmark needs around it.

    Attributes
    ----------
    name : unique name, also the file's stem.
    description : one line of plain text.
    motion : the motion to plan (start, goal and via points [m], end velocities [m/s],
        payload [kg]), the planner's own problem type; its fields are flat keys in the file.
    tc_max : command limit |Tc| <= tc_max [command units], 1..4096.
    expect : what the planner should do (:class:`Expectation`).
    n_intervals : the planner's number of time intervals, or ``None`` for its default.
    tags : free labels for selecting and grouping (e.g. ``"short"``, ``"payload"``).
    source : the file it was read from ('' when built in code).
    """

    name: str
    description: str
    motion: PlanProblem
    tc_max: float
    expect: Expectation
    n_intervals: int | None = None
    tags: tuple[str, ...] = ()
    source: str = field(default="", compare=False)

    @property
    def from_rest(self) -> bool:
        """True when the move starts and ends at rest."""
        return self.motion.is_rest_to_rest

    def to_dict(self) -> dict[str, Any]:
        """JSON form with the keys in the documented order (the motion's fields flat, beside
        the others); optional keys at their default are left out."""
        motion = self.motion
        out: dict[str, Any] = {"name": self.name, "description": self.description,
                               "start_m": list(motion.start_m), "goal_m": list(motion.goal_m)}
        if motion.via_m:
            out["via_m"] = [list(p) for p in motion.via_m]
        if any(motion.start_velocity_m_s):
            out["start_velocity_m_s"] = list(motion.start_velocity_m_s)
        if any(motion.goal_velocity_m_s):
            out["goal_velocity_m_s"] = list(motion.goal_velocity_m_s)
        out["tc_max"] = int(self.tc_max) if float(self.tc_max).is_integer() else self.tc_max
        if motion.payload_kg:
            out["payload_kg"] = motion.payload_kg
        if self.n_intervals is not None:
            out["n_intervals"] = self.n_intervals
        out["tags"] = list(self.tags)
        out["expect"] = self.expect.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: Any, source: str = "") -> "Problem":
        """Validate ``data``, a parsed JSON object with the keys of ``problems/README.md``;
        raises :class:`ProblemFileError` naming ``source`` (the file, '' when built in code)
        and the offending key. The motion's keys are checked as JSON (numbers, lists) here
        and for meaning (ranges, speeds) by :class:`PlanProblem`."""
        where = source or "problem"
        if not isinstance(data, dict):
            raise ProblemFileError(f"{where}: the file must hold one JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - set(ALLOWED_KEYS))
        if unknown:
            raise ProblemFileError(f"{where}: unknown key(s) {unknown}; allowed: {list(ALLOWED_KEYS)}")
        missing = [k for k in REQUIRED_KEYS if k not in data]
        if missing:
            raise ProblemFileError(f"{where}: missing required key(s) {missing}")
        try:
            return cls(
                name=_name(data["name"]),
                description=_text(data["description"], "description"),
                motion=_motion(data),
                tc_max=_tc_max(data["tc_max"]),
                n_intervals=_n_intervals(data.get("n_intervals")),
                tags=_tags(data["tags"]),
                expect=_expect(data["expect"]),
                source=source,
            )
        except InvalidProblemError as exc:
            raise ProblemFileError(f"{where}: {exc}") from None


# --- field validators (each raises ProblemFileError naming the key) --------------------------
def _number(value: Any, key: str) -> float:
    return require_number(key, value, ProblemFileError)


def _list(value: Any, key: str) -> list[Any]:
    if not isinstance(value, list):
        raise ProblemFileError(f"{key} must be a JSON list, got {value!r}")
    return value


def _point(value: Any, key: str) -> Point:
    items = _list(value, key)
    if len(items) != 3:
        raise ProblemFileError(f"{key} must have 3 coordinates (x, y, z), got {len(items)}")
    x, y, z = (_number(v, f"{key}[{i}]") for i, v in enumerate(items))
    return (x, y, z)


def _motion(data: dict[str, Any]) -> PlanProblem:
    """The :class:`PlanProblem` of the motion keys of ``data`` (JSON types checked here, the
    rest by PlanProblem, whose messages name the key)."""
    fields: dict[str, Any] = {key: _point(data[key], key)
                              for key in ("start_m", "goal_m", "start_velocity_m_s", "goal_velocity_m_s") if key in data}
    if "via_m" in data:
        fields["via_m"] = tuple(_point(p, f"via_m[{i}]") for i, p in enumerate(_list(data["via_m"], "via_m")))
    if "payload_kg" in data:
        fields["payload_kg"] = _number(data["payload_kg"], "payload_kg")
    return PlanProblem(**fields)


def _text(value: Any, key: str) -> str:
    if not isinstance(value, str) or not value.strip():
        raise ProblemFileError(f"{key} must be a non-empty string, got {value!r}")
    return value


def _name(value: Any) -> str:
    name = _text(value, "name")
    if not NAME_PATTERN.match(name):
        raise ProblemFileError(f"name {name!r} must match {NAME_PATTERN.pattern} "
                               "(lower-case letters, digits, '_' and '-')")
    return name


def _tc_max(value: Any) -> float:
    return require_number("tc_max", value, ProblemFileError, 0.0, ACRA2009.command_limit, low_open=True)


def _n_intervals(value: Any) -> int | None:
    return None if value is None else require_whole_number("n_intervals", value, ProblemFileError, 4, 400)


def _tags(value: Any) -> tuple[str, ...]:
    return tuple(_text(t, f"tags[{i}]") for i, t in enumerate(_list(value, "tags")))


def _expect(value: Any) -> Expectation:
    if not isinstance(value, dict):
        raise ProblemFileError(f"expect must be an object like {{\"status\": \"solved\"}}, got {value!r}")
    unknown = sorted(set(value) - {"status", "reason"})
    if unknown:
        raise ProblemFileError(f"unknown key(s) {unknown} in expect; allowed: ['status', 'reason']")
    if "status" not in value:
        raise ProblemFileError("expect lacks 'status'")
    return Expectation(value["status"], value.get("reason"))


# --- files ---------------------------------------------------------------------------------
def read_problem(path: str | Path) -> Problem:
    """Read and validate the problem file at ``path`` (UTF-8 JSON); its ``name`` must equal
    the file's stem."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProblemFileError(f"{path}: cannot read problem file: {exc.strerror or exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ProblemFileError(f"{path}: not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    problem = Problem.from_dict(data, source=str(path))
    if problem.name != path.stem:
        raise ProblemFileError(f"{path}: name {problem.name!r} must equal the file name stem {path.stem!r}")
    return problem


def problem_files(paths: Iterable[str | Path]) -> list[Path]:
    """The problem files named by ``paths``: files as given, directories expanded to their
    ``*.json`` files in name order."""
    files: list[Path] = []
    for entry in paths:
        path = Path(entry)
        if path.is_dir():
            found = sorted(path.glob("*.json"))
            if not found:
                raise ProblemFileError(f"{path}: directory holds no *.json problem files")
            files.extend(found)
        elif path.is_file():
            files.append(path)
        else:
            raise ProblemFileError(f"{path}: no such problem file or directory")
    return files


def load_problems(paths: Iterable[str | Path] | str | Path) -> list[Problem]:
    """Read and validate every problem under ``paths`` (files or directories).

    Returns the problems in the order found (directories sorted by file name). Raises
    :class:`ProblemFileError` for the first bad file, or when two files share a name.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    problems: list[Problem] = []
    seen: dict[str, str] = {}
    for path in problem_files(paths):
        problem = read_problem(path)
        if problem.name in seen:
            raise ProblemFileError(f"{path}: problem name {problem.name!r} also used by {seen[problem.name]}")
        seen[problem.name] = str(path)
        problems.append(problem)
    return problems


def select_problems(problems: list[Problem], names: Iterable[str]) -> list[Problem]:
    """The problems named in ``names``, in suite order; an unknown name is an error listing
    the known ones."""
    wanted = list(names)
    known = {p.name for p in problems}
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise ProblemFileError(f"unknown problem name(s) {unknown}; known: {sorted(known)}")
    return [p for p in problems if p.name in set(wanted)]
