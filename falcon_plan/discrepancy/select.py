"""Choosing effects by evidence: BIC and greedy forward selection with a backward check.

For a residual of n scalar samples with residual sum of squares RSS under a model with k
fitted parameters, the Bayesian information criterion (Gaussian errors) is

    BIC = n_eff ln(RSS / n) + k ln(n_eff),

where n_eff = n / tau is the effective number of independent samples (tau the residual's
integrated autocorrelation time: the smoothed, closed-loop residuals are far from white and
counting every sample would overstate the evidence; the replay criterion caps n_eff further,
see :mod:`.workflow`). A drop of BIC by more than
:data:`DEFAULT_THRESHOLD` = 10 when an effect is added is "very strong" evidence (Kass &
Raftery 1995) and the effect is added; the best such effect is added each round (greedy
forward selection), so several effects are chosen when the data call for them. When another
candidate comes within the threshold of the best one, the data cannot tell them apart: both
are reported as indistinguishable instead of guessing. After the forward pass, any chosen
effect whose removal no longer costs more than the threshold is dropped (backward check).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, Callable

DEFAULT_THRESHOLD = 10.0
"""Delta BIC above which an effect counts as found ("very strong" evidence)."""


def bic(rss: float, n: int, k: int, n_eff: float) -> float:
    """BIC of a fit with ``rss`` over ``n`` residuals, ``k`` parameters and ``n_eff``
    effective samples (see the module docstring)."""
    if rss <= 0 or n <= 0:
        return -math.inf
    return n_eff * math.log(rss / n) + k * math.log(max(n_eff, 2.0))


@dataclass(frozen=True)
class Evaluation:
    """One fitted candidate set under one criterion.

    ``names`` the candidates of the set; ``values``/``std``: fitted Effects fields and their standard deviations; ``rss`` over
    ``n`` residuals; ``k`` fitted parameters; ``bic`` the criterion value; ``detail`` anything
    the criterion wants to keep (e.g. the fit object).
    """

    names: tuple[str, ...]
    values: dict[str, float]
    std: dict[str, float]
    rss: float
    n: int
    k: int
    bic: float
    detail: Any = field(default=None, compare=False, repr=False)


@dataclass
class Selection:
    """Outcome of a selection: ``base`` (the names always kept), the ``chosen`` names,
    ``evaluations`` (every evaluation made, keyed by the sorted tuple of names), the
    ``indistinguishable`` groups, the round-by-round log ``rounds`` and the names the backward
    check ``dropped``."""

    base: tuple[str, ...]
    chosen: tuple[str, ...]
    evaluations: dict[tuple[str, ...], Evaluation]
    indistinguishable: list[tuple[str, ...]]
    rounds: list[dict[str, float]]
    """Per round: candidate -> delta BIC against the model of that round (positive favours
    adding it)."""
    dropped: list[str]

    def evaluation(self, names: tuple[str, ...] | list[str]) -> Evaluation:
        """The evaluation of a set (order does not matter)."""
        return self.evaluations[tuple(sorted(names))]

    @property
    def final(self) -> Evaluation:
        """The chosen model's evaluation."""
        return self.evaluation(self.chosen)


def greedy_select(evaluate: Callable[[tuple[str, ...]], Evaluation], candidates: list[str],
                  threshold: float = DEFAULT_THRESHOLD, base: tuple[str, ...] = (),
                  together: Callable[[list[Callable[[], Evaluation]]], list[Evaluation]] | None = None) -> Selection:
    """Greedy forward selection over ``candidates`` on top of ``base`` (always kept), then a
    backward check over the chosen ones; an effect enters or stays when it moves BIC by more
    than ``threshold``. ``evaluate(names)`` fits a set and returns its
    :class:`Evaluation` (calls are cached here). ``together`` runs a round's fits (one more
    candidate each, independent of one another) and returns their evaluations in order (e.g.
    side by side); None: one by one."""
    cache: dict[tuple[str, ...], Evaluation] = {}

    def ev(names: tuple[str, ...]) -> Evaluation:
        key = tuple(sorted(names))
        if key not in cache:
            cache[key] = evaluate(key)
        return cache[key]

    current = tuple(base)
    rounds: list[dict[str, float]] = []
    groups: list[tuple[str, ...]] = []
    while True:
        remaining = [c for c in candidates if c not in current]
        if not remaining:
            break
        here = ev(current)
        missing = [key for key in (tuple(sorted(current + (c,))) for c in remaining) if key not in cache]
        if together is not None and len(missing) > 1:
            cache.update(zip(missing, together([functools.partial(evaluate, key) for key in missing])))
        deltas = {c: here.bic - ev(current + (c,)).bic for c in remaining}
        rounds.append(deltas)
        best = max(deltas, key=lambda c: deltas[c])
        if deltas[best] <= threshold:
            break
        rivals = tuple(c for c in remaining if c != best and deltas[c] > threshold
                       and deltas[best] - deltas[c] < threshold)
        if rivals:
            groups.append((best,) + rivals)
        current = current + (best,)
    dropped: list[str] = []
    changed = True
    while changed:
        changed = False
        for c in [c for c in current if c not in base]:
            without = tuple(x for x in current if x != c)
            if ev(without).bic - ev(current).bic <= threshold:
                current = without
                dropped.append(c)
                changed = True
                break
    groups = [g for g in groups if g[0] in current]
    return Selection(tuple(base), current, cache, groups, rounds, dropped)
