"""falcon-plan: trajectory planning and optimal control for the Novint Falcon.

Public API (more is re-exported as the packages land)::

    import falcon_plan as fp
    model = fp.FalconModel()                       # acra2009 parameters, nominal effects
    model = fp.load_model("model.json")            # a model file (e.g. a corrected model)
    fp.inverse_kinematics([0.0, 0.0, 0.12])        # leg angles [rad]
"""
from __future__ import annotations

import logging

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

__all__ = [
    "ACRA2009", "LIBNIFALCON", "DEFAULT_LIMITS", "DeviceError", "Effects", "FalconModel",
    "FalconParams", "FalconPlanError", "InvalidParameterError", "InvalidProblemError",
    "KinematicsError", "LogFormatError", "PlanningFailed", "SafetyStop", "WorkspaceError",
    "WorkspaceLimits", "check_workspace", "counts_to_angles", "counts_to_position",
    "forward_kinematics", "get_params", "in_workspace", "inverse_kinematics", "jacobian", "load_model",
    "position_to_counts",
]
