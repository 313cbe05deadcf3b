"""PlanProblem / PlanOptions validation and JSON round trips."""
from __future__ import annotations

import math

import pytest

from falcon_plan.errors import InvalidProblemError, WorkspaceError
from falcon_plan.planning.problem import PlanOptions, PlanProblem


def test_defaults_are_rest_to_rest_and_2500() -> None:
    problem = PlanProblem((0, 0, 0.12), (0.01, 0, 0.12))
    assert problem.is_rest_to_rest
    assert PlanOptions().tc_max == 2500.0


@pytest.mark.parametrize("tc_max", [0.0, -1.0, 4096.5, math.nan, math.inf, True, "2500"])
def test_tc_max_outside_range_is_rejected(tc_max: object) -> None:
    with pytest.raises(InvalidProblemError, match="tc_max"):
        PlanOptions(tc_max=tc_max)  # type: ignore[arg-type]


def test_tc_max_upper_bound_is_allowed() -> None:
    assert PlanOptions(tc_max=4096).tc_max == 4096.0


@pytest.mark.parametrize("bad", [(0, 0), (0, 0, math.nan), "abc", (0, 0, 0.1, 0)])
def test_points_must_be_three_finite_numbers(bad: object) -> None:
    with pytest.raises(InvalidProblemError, match="start_m"):
        PlanProblem(bad, (0, 0, 0.12))  # type: ignore[arg-type]


def test_bad_options_name_the_field() -> None:
    with pytest.raises(InvalidProblemError, match="n_intervals"):
        PlanOptions(n_intervals=2)
    with pytest.raises(InvalidProblemError, match="hessian"):
        PlanOptions(hessian="newton")
    with pytest.raises(InvalidProblemError, match="payload_kg"):
        PlanProblem((0, 0, 0.12), (0.01, 0, 0.12), payload_kg=-0.1)


def test_round_trip_and_unknown_keys() -> None:
    problem = PlanProblem((0, 0, 0.12), (0.01, 0, 0.12), via_m=[(0.005, 0.001, 0.121)], payload_kg=0.05)
    assert PlanProblem.from_dict(problem.to_dict()) == problem
    options = PlanOptions.fast(tc_max=3000)
    assert PlanOptions.from_dict(options.to_dict()) == options
    with pytest.raises(InvalidProblemError, match=r"unknown PlanOptions field\(s\) \['tcmax'\]"):
        PlanOptions.from_dict({"tcmax": 2500})
    with pytest.raises(InvalidProblemError, match="unknown PlanProblem field"):
        PlanProblem.from_dict({"start_m": [0, 0, 0.12], "goal_m": [0, 0, 0.13], "speed": 1})


def test_workspace_error_names_the_point_and_why(model) -> None:
    with pytest.raises(WorkspaceError, match="goal .* outside the workspace: not reachable"):
        PlanProblem((0, 0, 0.12), (0.3, 0, 0.12)).require_in_workspace(model)
    with pytest.raises(WorkspaceError, match="via point 0"):
        PlanProblem((0, 0, 0.12), (0.01, 0, 0.12), via_m=[(0, 0.12, 0.125)]).require_in_workspace(model)
