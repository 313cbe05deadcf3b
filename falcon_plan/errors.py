"""The exception hierarchy of falcon-plan.

Every error the library raises derives from :class:`FalconPlanError` and, where it fits, also
from a builtin (``ValueError``, ``RuntimeError``, ``IOError``) so callers can catch either.
Messages name the problem and what is allowed.
"""
from __future__ import annotations

from typing import Any


class FalconPlanError(Exception):
    """Root of all falcon-plan errors."""


class InputError(FalconPlanError, ValueError):
    """A value given to falcon-plan is outside what is allowed. Besides the one-line message,
    ``field`` names the value where known (``goal_m``, ``via_m[1]``, ``tc_max``) and
    ``allowed`` says what it may be (``"in [0, 1]"``, ``"true or false"``), so that a caller
    (the service's error replies) reads them instead of parsing the message."""

    def __init__(self, message: str, *, field: str | None = None, allowed: Any = None) -> None:
        super().__init__(message)
        self.field = field
        self.allowed = allowed


class InvalidParameterError(InputError):
    """A parameter set or option has a value outside what is allowed."""


class WorkspaceError(FalconPlanError, ValueError):
    """A point is outside the workspace (unreachable, beyond a leg-angle limit, or too close
    to a singularity). ``message`` is the one-line summary; ``reasons`` lists why, per point
    that failed."""

    def __init__(self, message: str, reasons: list[str] | None = None) -> None:
        super().__init__(message)
        self.reasons = reasons or []


class KinematicsError(FalconPlanError, RuntimeError):
    """A kinematic solve (forward kinematics) did not converge."""


class InvalidProblemError(InputError):
    """A planning problem is malformed or cannot be solved as posed."""


class CrosscheckError(FalconPlanError, ValueError):
    """A reference motion (toppra, ruckig) cannot be computed for this problem; the planner
    notes it, or reports it as the fallback's failure."""


class PlanningFailed(FalconPlanError, RuntimeError):
    """The planner could not produce a verified trajectory: ``message`` says why in one line,
    ``report`` (a PlanReport, or None) what happened. (Typed ``Any``: the errors sit below
    every other module, so they name no type from above.)"""

    def __init__(self, message: str, report: Any = None) -> None:
        super().__init__(message)
        self.report = report


class LogFormatError(FalconPlanError, ValueError):
    """A falcon log file does not follow the format of MODEL-CONVENTIONS."""


class DeviceError(FalconPlanError, IOError):
    """A device failed (USB error, timeout, disconnect, bad packet stream, firmware)."""


class SafetyStop(FalconPlanError, RuntimeError):
    """Execution was stopped by a safety check (watchdog, workspace guard, not homed)."""


class OutputError(FalconPlanError, OSError):
    """An output file cannot be written (missing folder, no permission, disk full)."""
