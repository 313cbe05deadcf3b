"""Streaming trajectories to a device and measuring how well they are tracked.

:class:`~falcon_plan.execution.executor.Executor` (PD + feed-forward at the device's rate,
falcon log, tracking and timing report), its safety layer
(:mod:`~falcon_plan.execution.safety`), deadline timing (:mod:`~falcon_plan.timing`),
device opening (:mod:`~falcon_plan.execution.device_factory`) and the quintic reference move
(:mod:`~falcon_plan.execution.quintic`).
"""
from falcon_plan.execution.executor import ExecutionReport, Executor, TrackingError
from falcon_plan.execution.quintic import quintic_trajectory
from falcon_plan.execution.safety import SafetyConfig

__all__ = ["Executor", "ExecutionReport", "TrackingError", "SafetyConfig", "quintic_trajectory"]
