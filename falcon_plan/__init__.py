"""falcon-plan: trajectory planning and optimal control for the Novint Falcon.

Public API (more is re-exported as the packages land)::

    import falcon_plan as fp
    model = fp.FalconModel()                       # acra2009 parameters, nominal effects
    model = fp.load_model("model.json")            # a model file (e.g. a corrected model)
    fp.inverse_kinematics([0.0, 0.0, 0.12])        # leg angles [rad]
    result = fp.plan((0.0, 0.0, 0.12), (0.03, 0.02, 0.14), fp.PlanOptions.of(tc_max=2500), model)
    fp.plot_plan(result.trajectory, "plan.png")    # position, speeds, commands, margins

Conventions: points (x, y, z) in metres in the base frame (x right, y up, z toward the
user), control rates in Hz (800 by default), commands in the device's units (|Tc| <= 4096).
The planning and plotting names are loaded on first use (they pull in the solvers and
matplotlib).
"""
from __future__ import annotations

import importlib
import logging
from importlib import metadata as _metadata
from typing import Any

from falcon_plan.errors import (DeviceError, FalconPlanError, InvalidParameterError, InvalidProblemError,
                                KinematicsError, LogFormatError, PlanningFailed, SafetyStop, WorkspaceError)
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.modelfile import load_model
from falcon_plan.model.kinematics import (counts_to_angles, counts_to_position, forward_kinematics,
                                          inverse_kinematics, jacobian, position_to_counts)
from falcon_plan.model.params import ACRA2009, LIBNIFALCON, FalconParams, get_params
from falcon_plan.model.workspace import DEFAULT_LIMITS, WorkspaceLimits, check_workspace, in_workspace

logging.getLogger(__name__).addHandler(logging.NullHandler())

_LAZY = {"plan": "falcon_plan.planning.api", "warm_up": "falcon_plan.planning.api", "PlanOptions": "falcon_plan.planning.problem",
         "CommandLimits": "falcon_plan.planning.problem", "Transcription": "falcon_plan.planning.problem",
         "SolverSettings": "falcon_plan.planning.problem", "Checks": "falcon_plan.planning.problem",
         "Plan": "falcon_plan.planning.report", "Trajectory": "falcon_plan.trajectory",
         "FalconLog": "falcon_plan.falconlog", "read_log": "falcon_plan.falconlog",
         "plot_plan": "falcon_plan.plots", "plot_run": "falcon_plan.plots", "plot_gains": "falcon_plan.plots",
         "Controller": "falcon_plan.control", "GainSchedule": "falcon_plan.lqr"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

try:
    __version__ = _metadata.version("falcon-plan")
except _metadata.PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "unknown"

__all__ = [
    "ACRA2009", "LIBNIFALCON", "DEFAULT_LIMITS", "DeviceError", "Effects", "FalconModel",
    "FalconParams", "FalconPlanError", "InvalidParameterError", "InvalidProblemError",
    "KinematicsError", "LogFormatError", "PlanningFailed", "SafetyStop", "WorkspaceError",
    "WorkspaceLimits", "check_workspace", "counts_to_angles", "counts_to_position",
    "forward_kinematics", "get_params", "in_workspace", "inverse_kinematics", "jacobian", "load_model",
    "position_to_counts", *sorted(_LAZY),
]
