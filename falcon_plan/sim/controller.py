"""Moved: the controller lives in :mod:`falcon_plan.control` (one controller for the
executor, the simulated experiments, the discrepancy replay and the planner's plant check).
These names are kept for existing imports."""
from falcon_plan.control import (COMMAND_LIMIT, DEFAULT_KD, DEFAULT_KP,  # noqa: F401
                                 DEFAULT_VELOCITY_CUTOFF_HZ, EncoderPD, pd_law,
                                 velocity_filter_alpha)

__all__ = ["EncoderPD", "pd_law", "velocity_filter_alpha", "DEFAULT_KP", "DEFAULT_KD",
           "DEFAULT_VELOCITY_CUTOFF_HZ", "COMMAND_LIMIT"]
