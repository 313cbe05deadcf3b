"""Finding, naming and fitting what the model misses, from falcon logs.

``find_discrepancy(train_log, heldout_log) -> DiscrepancyReport`` (see :mod:`.workflow`);
``write_report`` (:mod:`.report`); the candidate effects (:mod:`.library`); excitation designs
(:mod:`.excitation`) and synthetic logs (:mod:`.synth`).
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from falcon_plan.discrepancy.library import CANDIDATES, LIBRARY, CandidateEffect
    from falcon_plan.discrepancy.workflow import DiscrepancyReport, ParameterEstimate, find_discrepancy

_LAZY = {"CANDIDATES": "library", "LIBRARY": "library", "CandidateEffect": "library",
         "DiscrepancyReport": "workflow", "ParameterEstimate": "workflow", "find_discrepancy": "workflow"}
"""Public name -> its module, imported on first use (importing a submodule, e.g. the
command line's ``excitation.KINDS``, does not load the identification and its solvers)."""


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["find_discrepancy", "DiscrepancyReport", "ParameterEstimate", "CANDIDATES", "LIBRARY",
           "CandidateEffect"]
