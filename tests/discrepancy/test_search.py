"""The frugal scalar searches of the workflow (every trial there is a closed-loop replay) and
the substeps of the cable model in the replays."""
from __future__ import annotations

import math

import pytest
from scipy.optimize import minimize_scalar

from falcon_plan.discrepancy.replay import CABLE_SUBSTEP_CHOICES, cable_substeps
from falcon_plan.discrepancy.search import curvature, parabolic_minimum
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.params import ACRA2009
from falcon_plan.sim.equations import BACKLASH_CONTACT_STIFFNESS_NM_RAD


def _counted(f):
    calls = []

    def g(x: float) -> float:
        calls.append(x)
        return f(x)
    return g, calls


@pytest.mark.parametrize("grid", [(-1.0, 0.0, 1.0), (-2.0, -1.5, -1.0)])
def test_parabolic_minimum_matches_brent_in_few_evaluations(grid):
    """A smooth non-parabolic criterion: the minimum from a 3-point start (bracketing it, or
    with the minimum outside the grid) agrees with scipy's bounded Brent search."""
    def f(x: float) -> float:
        return (x - 0.37) ** 2 + 0.3 * (x - 0.37) ** 4 + 2.0
    g, calls = _counted(f)
    points = {x: f(x) for x in grid}
    x, fx = parabolic_minimum(g, points, -3.0, 3.0, 1e-3, 12)
    reference = minimize_scalar(f, bounds=(-3.0, 3.0), method="bounded", options={"xatol": 1e-6}).x
    assert x == pytest.approx(reference, abs=3e-3) and fx == pytest.approx(f(x))
    assert len(calls) <= 12 and all(-3.0 <= c <= 3.0 for c in calls)


def test_parabolic_minimum_stops_at_a_bound():
    g, calls = _counted(lambda x: -x)
    x, _ = parabolic_minimum(g, {0.0: 0.0, 0.5: -0.5}, -1.0, 1.0, 1e-3, 10)
    assert x == 1.0 and len(calls) <= 2


def test_curvature_of_a_parabola_and_of_a_flat_criterion():
    points = {x: 3.0 * (x - 0.2) ** 2 + 1.0 for x in (-1.0, -0.3, 0.1, 0.4, 1.2)}
    assert curvature(points, 0.2) == pytest.approx(6.0)
    assert curvature({x: 5.0 - x * x for x in (-1.0, 0.0, 1.0)}, 0.0) == 0.0


def test_cable_substeps_follow_the_drive_mode():
    """omega = sqrt(k / J_motor) at the leg (J_motor = motor inertia x ratio^2), computed here
    from the parameter set: the count is the smallest choice with omega / (rate n) <= phase."""
    model = FalconModel()
    inertia = ACRA2009.motor_inertia_kgm2 * ACRA2009.drive_ratio ** 2
    assert cable_substeps(Effects(), model, 800.0, 0.8) is None
    for effects, k in ((Effects(cable_stiffness_Nm_rad=30.0), 30.0),
                       (Effects(backlash_rad=0.01), BACKLASH_CONTACT_STIFFNESS_NM_RAD),
                       (Effects(cable_stiffness_Nm_rad=800.0, backlash_rad=0.01), 800.0)):
        for phase in (0.4, 1.2):
            n = cable_substeps(effects, model, 800.0, phase)
            needed = math.sqrt(k / inertia) / (800.0 * phase)
            assert n == min([c for c in CABLE_SUBSTEP_CHOICES if c >= needed] or [max(CABLE_SUBSTEP_CHOICES)])
    # the backlash contact needs the plant's default at the check's accuracy
    assert cable_substeps(Effects(backlash_rad=0.01), model, 800.0, 0.4) == 6


def test_parabolic_minimum_looks_inside_a_bound_it_reached():
    """A minimum between the grid and the bound: the outward step lands on the bound, which
    beats the grid; one step inward finds the valley and the search converges in it (it had
    stopped at the bound: a backlash fitted at its 0.04 rad bound where 0.027 was the minimum).
    Where the criterion falls all the way to the bound, the one inward step is all it costs."""
    def f(x: float) -> float:
        return abs(x - 0.8) ** 1.5 + 0.1 * (x - 0.8) ** 2
    g, calls = _counted(f)
    x, _ = parabolic_minimum(g, {-1.0: f(-1.0), -0.5: f(-0.5), 0.0: f(0.0)}, -1.0, 1.0, 1e-3, 8)
    assert 1.0 in calls and x == pytest.approx(0.8, abs=0.02)
    g, calls = _counted(lambda x: -x)
    x, _ = parabolic_minimum(g, {0.0: 0.0, 0.5: -0.5}, -1.0, 1.0, 1e-3, 10)
    assert x == 1.0 and len(calls) == 2 and 0.5 < calls[1] < 1.0
