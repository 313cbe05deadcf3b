"""The benchmark problem files: every committed file loads, bad files give clear errors, and
the committed files are exactly what problems/generate.py makes (and passes its checks)."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from falcon_plan.batch.loader import (
    REFUSAL_REASONS, Problem, ProblemFileError, load_problems, read_problem, select_problems)
from falcon_plan.planning.problem import PlanProblem

PROBLEMS_DIR = Path(__file__).resolve().parents[2] / "problems"

VALID = {
    "name": "demo",
    "description": "a valid problem",
    "start_m": [0.0, 0.0, 0.125],
    "goal_m": [0.01, 0.0, 0.125],
    "tc_max": 2500,
    "tags": ["short"],
    "expect": {"status": "solved"},
}


def _write(tmp_path: Path, data: object, name: str = "demo") -> Path:
    path = tmp_path / f"{name}.json"
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return path


def _generator():
    spec = importlib.util.spec_from_file_location("problems_generate", PROBLEMS_DIR / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_problem_file_loads_and_the_suite_covers_the_brief() -> None:
    problems = load_problems([PROBLEMS_DIR])
    assert len(problems) >= 30
    assert len({p.name for p in problems}) == len(problems)
    assert {p.tc_max for p in problems} >= {1500, 2000, 2500, 3500, 4096}
    tags = {t for p in problems for t in p.tags}
    assert {"short", "long", "across", "edge", "via", "payload", "motion", "refusal"} <= tags
    reasons = {p.expect.reason for p in problems if p.expect.status == "refused"}
    assert {"outside_workspace", "via_unreachable", "tc_max_too_small"} <= reasons
    assert any(not p.from_rest for p in problems) and any(p.from_rest for p in problems)
    assert any(p.motion.via_m for p in problems if p.expect.status == "solved")


def test_committed_files_match_the_generator_and_its_checks() -> None:
    generate = _generator()
    built = generate.build_problems()
    for problem in built:
        generate.check_problem(problem)  # raises AssertionError saying why
        assert (PROBLEMS_DIR / f"{problem.name}.json").read_text() == generate.problem_text(problem), problem.name
    assert sorted(p.name for p in built) == [p.name for p in load_problems([PROBLEMS_DIR])]


def test_round_trip_and_defaults(tmp_path: Path) -> None:
    problem = read_problem(_write(tmp_path, VALID))
    assert problem.motion == PlanProblem((0.0, 0.0, 0.125), (0.01, 0.0, 0.125))  # rest, no via, no payload
    assert problem.n_intervals is None and problem.from_rest
    assert Problem.from_dict(problem.to_dict()) == problem
    moving = {**VALID, "via_m": [[0.005, 0.002, 0.125]], "goal_velocity_m_s": [0.0, 0.0, 0.05], "payload_kg": 0.1}
    problem = read_problem(_write(tmp_path, moving))
    assert problem.motion == PlanProblem((0.0, 0.0, 0.125), (0.01, 0.0, 0.125), goal_velocity_m_s=(0.0, 0.0, 0.05),
                                         via_m=((0.005, 0.002, 0.125),), payload_kg=0.1)
    assert not problem.from_rest and problem.to_dict() == {k: moving[k] for k in problem.to_dict()}
    assert Problem.from_dict(problem.to_dict()) == problem


@pytest.mark.parametrize("change, message", [
    ({"colour": "red"}, "unknown key(s) ['colour']"),
    ({"start_m": [0.0, 0.1]}, "start_m must have 3 coordinates"),
    ({"goal_m": [0.0, "x", 0.1]}, "goal_m[1] must be a number"),
    ({"goal_m": [0.0, True, 0.1]}, "goal_m[1] must be a number"),
    ({"tc_max": 5000}, "tc_max must be in (0, 4096]"),
    ({"tc_max": 0}, "tc_max must be in (0, 4096]"),
    ({"payload_kg": -0.1}, "payload_kg must be in [0, 1]"),
    ({"payload_kg": True}, "payload_kg must be a number"),
    ({"goal_velocity_m_s": [6.0, 0.0, 0.0]}, "goal_velocity_m_s has speed 6 m/s; at most 5 m/s"),
    ({"via_m": [[0.0, 0.0, 0.1]] * 9}, "at most 8 via points"),
    ({"n_intervals": 2.5}, "n_intervals must be a whole number"),
    ({"via_m": [[0.0, 0.0]]}, "via_m[0] must have 3 coordinates"),
    ({"via_m": [0.0, 0.0, 0.1]}, "via_m[0] must be a JSON list"),
    ({"expect": {"status": "maybe"}}, "expect.status must be one of"),
    ({"expect": {"status": "refused"}}, "expect.reason must be one of"),
    ({"expect": {"status": "refused", "reason": "too_hard"}}, "expect.reason must be one of"),
    ({"expect": {"status": "solved", "extra": 1}}, "unknown key(s) ['extra'] in expect"),
    ({"tags": "short"}, "tags must be a JSON list"),
    ({"name": "Bad Name"}, "must match"),
    ({"description": ""}, "description must be a non-empty string"),
])
def test_malformed_fields_give_errors_naming_file_and_key(tmp_path: Path, change: dict, message: str) -> None:
    path = _write(tmp_path, {**VALID, **change})
    with pytest.raises(ProblemFileError) as info:
        read_problem(path)
    assert message in str(info.value)
    assert str(path) in str(info.value)


def test_missing_keys_are_listed(tmp_path: Path) -> None:
    data = {k: v for k, v in VALID.items() if k not in ("goal_m", "expect")}
    with pytest.raises(ProblemFileError, match=r"missing required key\(s\) \['goal_m', 'expect'\]"):
        read_problem(_write(tmp_path, data))


def test_bad_json_and_bad_paths(tmp_path: Path) -> None:
    with pytest.raises(ProblemFileError, match="not valid JSON.*line 1"):
        read_problem(_write(tmp_path, '{"name": "demo",'))
    with pytest.raises(ProblemFileError, match="one JSON object"):
        read_problem(_write(tmp_path, "[1, 2]"))
    with pytest.raises(ProblemFileError, match="no such problem file"):
        load_problems([tmp_path / "nowhere"])
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ProblemFileError, match="holds no"):
        load_problems(empty)


def test_name_must_match_file_and_be_unique(tmp_path: Path) -> None:
    with pytest.raises(ProblemFileError, match="must equal the file name stem 'other'"):
        read_problem(_write(tmp_path, VALID, name="other"))
    first = _write(tmp_path, VALID)
    second_dir = tmp_path / "more"
    second_dir.mkdir()
    second = _write(second_dir, VALID)
    with pytest.raises(ProblemFileError, match="also used by"):
        load_problems([first, second])


def test_select_problems_rejects_unknown_names() -> None:
    problems = load_problems([PROBLEMS_DIR])
    picked = select_problems(problems, ["short_x", "across_x"])
    assert [p.name for p in picked] == ["across_x", "short_x"]  # suite order
    with pytest.raises(ProblemFileError, match="unknown problem name"):
        select_problems(problems, ["no_such_problem"])


def test_refusal_reasons_documented_in_readme() -> None:
    readme = (PROBLEMS_DIR / "README.md").read_text()
    for reason in REFUSAL_REASONS:
        assert f"`{reason}`" in readme
