"""Streaming trajectories to a device and measuring how well they are tracked.

:class:`~falcon_plan.execution.executor.Executor` (PD + feed-forward at the device's rate,
falcon log, tracking and timing report), its safety layer
(:mod:`~falcon_plan.execution.safety`) and device opening
(:mod:`~falcon_plan.execution.device_factory`). Execution builds on the model, the devices,
the controller (:mod:`falcon_plan.control`), the trajectory (:mod:`falcon_plan.trajectory`)
and the loop timing (:mod:`falcon_plan.timing`); it does not import planning.
"""
from falcon_plan.execution.executor import ExecutionReport, ExecutionStatus, Executor, TrackingError
from falcon_plan.execution.safety import SafetyConfig

__all__ = ["Executor", "ExecutionReport", "ExecutionStatus", "TrackingError", "SafetyConfig"]
