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
Every name is loaded on first use (the model pulls in numpy, scipy and CasADi, planning the
solvers, plotting matplotlib), so importing the package, or the command line, costs almost
nothing.
"""
from __future__ import annotations

import importlib
import logging
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what type checkers and editors see; at run time __getattr__ imports on use
    from falcon_plan.errors import (DeviceError, FalconPlanError, InvalidParameterError, InvalidProblemError,
                                    KinematicsError, LogFormatError, PlanningFailed, SafetyStop, WorkspaceError)
    from falcon_plan.falconlog import FalconLog, read_log
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.effects import Effects
    from falcon_plan.model.kinematics import (counts_to_angles, counts_to_position, forward_kinematics,
                                              inverse_kinematics, jacobian, position_to_counts)
    from falcon_plan.model.modelfile import load_model
    from falcon_plan.model.params import ACRA2009, LIBNIFALCON, FalconParams, get_params
    from falcon_plan.model.workspace import DEFAULT_LIMITS, WorkspaceLimits, check_workspace, in_workspace
    from falcon_plan.planning.api import plan, warm_up
    from falcon_plan.planning.problem import Checks, CommandLimits, PlanOptions, SolverSettings, Transcription
    from falcon_plan.planning.report import Plan
    from falcon_plan.control import Controller
    from falcon_plan.lqr import GainSchedule
    from falcon_plan.plots import plot_gains, plot_plan, plot_run
    from falcon_plan.trajectory import Trajectory

logging.getLogger(__name__).addHandler(logging.NullHandler())

_MODULES = {
    "falcon_plan.errors": ("DeviceError", "FalconPlanError", "InvalidParameterError", "InvalidProblemError",
                           "KinematicsError", "LogFormatError", "PlanningFailed", "SafetyStop", "WorkspaceError"),
    "falcon_plan.model.dynamics": ("FalconModel",),
    "falcon_plan.model.effects": ("Effects",),
    "falcon_plan.model.modelfile": ("load_model",),
    "falcon_plan.model.kinematics": ("counts_to_angles", "counts_to_position", "forward_kinematics",
                                     "inverse_kinematics", "jacobian", "position_to_counts"),
    "falcon_plan.model.params": ("ACRA2009", "LIBNIFALCON", "FalconParams", "get_params"),
    "falcon_plan.model.workspace": ("DEFAULT_LIMITS", "WorkspaceLimits", "check_workspace", "in_workspace"),
    "falcon_plan.planning.api": ("plan", "warm_up"),
    "falcon_plan.planning.problem": ("PlanOptions", "CommandLimits", "Transcription", "SolverSettings", "Checks"),
    "falcon_plan.planning.report": ("Plan",),
    "falcon_plan.trajectory": ("Trajectory",),
    "falcon_plan.falconlog": ("FalconLog", "read_log"),
    "falcon_plan.plots": ("plot_plan", "plot_run", "plot_gains"),
    "falcon_plan.control": ("Controller",),
    "falcon_plan.lqr": ("GainSchedule",),
}
_LAZY = {name: module for module, names in _MODULES.items() for name in names}
"""Every public name -> the module that defines it, imported on first use: ``import falcon_plan``
(and so every ``falcon_plan.*`` import, the command line's included) loads neither numpy nor
CasADi until a name that needs them is used."""


def __getattr__(name: str) -> Any:
    if name == "__version__":
        return _version()
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value  # later lookups skip __getattr__
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY, "__version__"})


def _version() -> str:
    """The installed version of falcon-plan ("unknown" in a source tree that is not installed)."""
    from importlib import metadata

    try:
        return metadata.version("falcon-plan")
    except metadata.PackageNotFoundError:
        return "unknown"


__all__ = sorted(_LAZY)
