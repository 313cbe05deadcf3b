"""Transitional: :class:`~falcon_plan.trajectory.Trajectory` lives in
:mod:`falcon_plan.trajectory`. Only ``casadi_planner.py`` (being changed on another branch)
still imports it from here; delete this module once that import reads
``from falcon_plan.trajectory import Trajectory``."""
from falcon_plan.trajectory import Trajectory

__all__ = ["Trajectory"]
