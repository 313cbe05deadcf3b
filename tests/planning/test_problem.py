"""PlanProblem / PlanOptions validation and JSON round trips."""
from __future__ import annotations

import math

import pytest

from falcon_plan.errors import InputError, InvalidProblemError, WorkspaceError
import dataclasses

from falcon_plan.planning.problem import (OPTION_FIELDS, OPTION_PARTS, Checks, CommandLimits, PlanOptions, PlanProblem,
                                          SolverSettings, Transcription)


def test_defaults_are_rest_to_rest_and_2500() -> None:
    problem = PlanProblem((0, 0, 0.12), (0.01, 0, 0.12))
    assert problem.is_rest_to_rest
    assert PlanOptions().limits.tc_max == 2500.0


@pytest.mark.parametrize("tc_max", [0.0, -1.0, 4096.5, math.nan, math.inf, True, "2500"])
def test_tc_max_outside_range_is_rejected(tc_max: object) -> None:
    with pytest.raises(InvalidProblemError, match="tc_max"):
        PlanOptions.of(tc_max=tc_max)  # type: ignore[arg-type]


def test_tc_max_upper_bound_is_allowed() -> None:
    assert PlanOptions.of(tc_max=4096).limits.tc_max == 4096.0


@pytest.mark.parametrize("bad", [(0, 0), (0, 0, math.nan), "abc", (0, 0, 0.1, 0)])
def test_points_must_be_three_finite_numbers(bad: object) -> None:
    with pytest.raises(InvalidProblemError, match="start_m"):
        PlanProblem(bad, (0, 0, 0.12))  # type: ignore[arg-type]


def test_bad_options_name_the_field() -> None:
    with pytest.raises(InvalidProblemError, match="n_intervals"):
        PlanOptions.of(n_intervals=2)
    with pytest.raises(InvalidProblemError, match="hessian"):
        PlanOptions.of(hessian="newton")
    with pytest.raises(InvalidProblemError, match="payload_kg"):
        PlanProblem((0, 0, 0.12), (0.01, 0, 0.12), payload_kg=-0.1)


def test_round_trip_and_unknown_keys() -> None:
    problem = PlanProblem((0, 0, 0.12), (0.01, 0, 0.12), via_m=[(0.005, 0.001, 0.121)], payload_kg=0.05)
    assert PlanProblem.from_dict(problem.to_dict()) == problem
    options = PlanOptions.fast(tc_max=3000)
    assert PlanOptions.from_dict(options.to_dict()) == options
    with pytest.raises(InvalidProblemError, match=r"unknown planner option 'tcmax'; allowed: .*'tc_max'"):
        PlanOptions.from_dict({"tcmax": 2500})
    with pytest.raises(InvalidProblemError, match=r"unknown CommandLimits field\(s\) \['refine'\]"):
        PlanOptions.from_dict({"limits": {"refine": False}})
    with pytest.raises(InvalidProblemError, match="unknown PlanProblem field"):
        PlanProblem.from_dict({"start_m": [0, 0, 0.12], "goal_m": [0, 0, 0.13], "speed": 1})


def test_workspace_error_names_the_point_and_why(model) -> None:
    with pytest.raises(WorkspaceError, match="goal .* outside the workspace: not reachable"):
        PlanProblem((0, 0, 0.12), (0.3, 0, 0.12)).require_in_workspace(model)
    with pytest.raises(WorkspaceError, match="via point 0"):
        PlanProblem((0, 0, 0.12), (0.01, 0, 0.12), via_m=[(0, 0.12, 0.125)]).require_in_workspace(model)


def test_options_are_four_parts_with_unique_names() -> None:
    """Physics, transcription, solver and checks are separate values; every option name
    belongs to exactly one part, so options can be given by name."""
    assert list(OPTION_PARTS) == ["limits", "transcription", "solver", "checks"]
    names = [f.name for cls in OPTION_PARTS.values() for f in dataclasses.fields(cls)]
    assert len(names) == len(set(names)) == len(OPTION_FIELDS)
    options = PlanOptions.of(tc_max=2000, profile="constant", hessian="exact", refine=False)
    assert options == PlanOptions(limits=CommandLimits(tc_max=2000), transcription=Transcription(profile="constant"),
                                  solver=SolverSettings(hessian="exact"), checks=Checks(refine=False))
    assert options.replace(n_intervals=30).transcription == Transcription(profile="constant", n_intervals=30)
    assert options.replace(n_intervals=30).limits is options.limits


def test_options_json_is_nested_by_part_and_accepts_names() -> None:
    options = PlanOptions.fast(limit="device", n_intervals=16)
    data = options.to_dict()
    assert set(data) == set(OPTION_PARTS) and data["limits"]["limit"] == "device"
    assert data["checks"]["refine"] is False and data["transcription"]["n_intervals"] == 16
    # by name on top of the parts: what the service's requests and --options send
    assert PlanOptions.from_dict({**data, "n_intervals": 20}).transcription.n_intervals == 20
    assert PlanOptions.from_dict({"tc_max": 2000}) == PlanOptions.of(tc_max=2000)
    with pytest.raises(InvalidProblemError, match="options.limits must be an object"):
        PlanOptions.from_dict({"limits": 3})
    with pytest.raises(InvalidProblemError, match="PlanOptions.checks must be a Checks"):
        PlanOptions(checks={"refine": False})  # type: ignore[arg-type]


@pytest.mark.parametrize("build, field, allowed", [
    (lambda: PlanProblem((0.0, 0.0, 0.12), (0.0, "x", 0.13)), "goal_m", "3 finite numbers (x, y, z)"),
    (lambda: PlanProblem((0.0, 0.0, 0.12), (0.0, 0.0, 0.13), via_m=[(0.0, 0.0, 0.12)] * 9), "via_m", "at most 8 via points"),
    (lambda: PlanProblem((0.0, 0.0, 0.12), (0.0, 0.0, 0.13), payload_kg=2.0), "payload_kg", "in [0, 1]"),
    (lambda: PlanProblem((0.0, 0.0, 0.12), (0.0, 0.0, 0.13), goal_velocity_m_s=(6.0, 0.0, 0.0)),
     "goal_velocity_m_s", "a speed of at most 5 m/s"),
    (lambda: PlanOptions.of(n_intervals=3), "n_intervals", "a whole number in [4, 400]"),
    (lambda: PlanOptions.of(crosscheck="yes"), "crosscheck", "true or false"),
    (lambda: PlanOptions.of(replan_search="fastest"), "replan_search", "one of ('shortest', 'first')"),
    (lambda: PlanOptions.of(no_such_option=1), "no_such_option", sorted(OPTION_FIELDS)),
])
def test_a_refusal_names_its_field_and_what_is_allowed(build, field, allowed):
    """Every refusal of a problem or an option carries the field it refuses and what that field
    allows as values (the service's error replies read them; nothing parses the message)."""
    with pytest.raises(InvalidProblemError) as info:
        build()
    assert info.value.field == field and info.value.allowed == allowed, (info.value.field, info.value.allowed)
    assert isinstance(info.value, InputError) and isinstance(info.value, ValueError)
