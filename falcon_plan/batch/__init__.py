"""Batch benchmark: named planning problems (``problems/*.json``, :mod:`.loader`), the runner
that plans, cross-checks and executes each on the simulated plant (:mod:`.runner`), and the
results table, summary and plots (:mod:`.summary`). The command is ``falcon-plan bench``."""
from falcon_plan.batch.loader import Expectation, Problem, ProblemFileError, load_problems, select_problems
from falcon_plan.batch.runner import BatchResult, ResultRow, RunOptions, run_batch, run_problem
from falcon_plan.batch.summary import summarise, write_results

__all__ = ["Expectation", "Problem", "ProblemFileError", "load_problems", "select_problems", "BatchResult",
           "ResultRow", "RunOptions", "run_batch", "run_problem", "summarise", "write_results"]
