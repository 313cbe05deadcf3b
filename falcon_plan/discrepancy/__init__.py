"""Finding, naming and fitting what the model misses, from falcon logs.

``find_discrepancy(train_log, heldout_log) -> DiscrepancyReport`` (see :mod:`.workflow`);
``write_report`` (:mod:`.report`); the candidate effects (:mod:`.library`); excitation designs
(:mod:`.excitation`) and synthetic logs (:mod:`.synth`).
"""
from falcon_plan.discrepancy.library import CANDIDATES, LIBRARY, CandidateEffect
from falcon_plan.discrepancy.workflow import DiscrepancyReport, ParameterEstimate, find_discrepancy

__all__ = ["find_discrepancy", "DiscrepancyReport", "ParameterEstimate", "CANDIDATES", "LIBRARY",
           "CandidateEffect"]
