"""BIC and greedy selection on a synthetic linear-regression problem (no dynamics): the
selection logic alone, with known answers."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.discrepancy.select import Evaluation, bic, greedy_select

N = 2000


def _problem(coefs: dict[str, float], twin: bool = False, seed: int = 0):
    """Columns a, b, c, (d: a near-copy of a when ``twin``); y = sum coef * column + noise."""
    rng = np.random.default_rng(seed)
    cols = {name: rng.normal(size=N) for name in "abc"}
    if twin:
        cols["d"] = cols["a"] + 0.01 * rng.normal(size=N)
    y = sum(coefs.get(k, 0.0) * v for k, v in cols.items()) + rng.normal(size=N)

    def evaluate(names: tuple[str, ...]) -> Evaluation:
        if names:
            x = np.column_stack([cols[n] for n in names])
            beta, *_ = np.linalg.lstsq(x, y, rcond=None)
            r = y - x @ beta
        else:
            beta, r = np.zeros(0), y
        rss = float(r @ r)
        return Evaluation(names, dict(zip(names, beta)), {}, rss, N, len(names), bic(rss, N, len(names), N))

    return evaluate, list(cols)


def test_bic_penalises_parameters() -> None:
    assert bic(100.0, 100, 1, 100) - bic(100.0, 100, 0, 100) == pytest.approx(np.log(100))
    assert bic(50.0, 100, 1, 100) < bic(100.0, 100, 0, 100)


def test_picks_every_strong_effect_and_nothing_else() -> None:
    evaluate, names = _problem({"a": 0.5, "c": 0.3})
    sel = greedy_select(evaluate, names)
    assert sorted(sel.chosen) == ["a", "c"]
    assert sel.final.values["a"] == pytest.approx(0.5, abs=0.05)
    assert sel.rounds[0]["a"] > sel.rounds[0]["c"] > 10


def test_answers_nothing_on_pure_noise() -> None:
    evaluate, names = _problem({})
    sel = greedy_select(evaluate, names)
    assert sel.chosen == ()
    assert all(d < 10 for d in sel.rounds[0].values())


def test_reports_candidates_it_cannot_tell_apart() -> None:
    evaluate, names = _problem({"a": 0.5}, twin=True)
    sel = greedy_select(evaluate, names)
    assert len(sel.chosen) == 1 and sel.chosen[0] in ("a", "d")
    assert sel.indistinguishable and set(sel.indistinguishable[0]) == {"a", "d"}


def test_rivals_are_smooth_effects_that_also_passed_close_to_the_chosen_one() -> None:
    """A chosen smooth effect's rivals (weighed on the training replay by find_discrepancy):
    the smooth candidates of the round that added it which also passed the threshold and came
    within RIVAL_MARGIN thresholds of it; not one far behind, below the threshold, already
    chosen, or a plant-only effect."""
    from falcon_plan.discrepancy.select import Selection
    from falcon_plan.discrepancy.workflow import RIVAL_MARGIN, _rivals

    t = 10.0
    close = 100.0 - RIVAL_MARGIN * t / 2
    rounds = [{"viscous_friction": 200.0, "payload_mass": 80.0, "motor_gain": 78.0},
              {"payload_mass": 100.0, "motor_gain": close, "link_mass": 100.0 - RIVAL_MARGIN * t - 1,
               "coulomb_friction": t - 1, "backlash": 99.0}]
    sel = Selection((), ("viscous_friction", "payload_mass"), {}, [], rounds, [])
    assert _rivals(sel, t) == [("payload_mass", "motor_gain")]
