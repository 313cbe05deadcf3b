"""The independent world (:mod:`.independent_world`) as the physics inside the emulated USB
Falcon, so that ``experiment run --device emulated`` records it through the project's own
executor and threaded USB driver, in wall-clock time, exactly as a user records a real device.

:class:`WorldPlant` has what the emulator asks of its plant (``step(commands or None)`` ->
counts, ``time_s``, ``dt_s``): the world's own integrator and friction, the device firmware's
command path (a delay line of 2 + the world's extra delay periods, the last command held for
the command hold, then no force), and the effects outside the library that act on the command
(a dead band; a motor gain drifting linearly in time). :func:`open_world_device` is the device
factory's emulated branch with that plant; ``benchmarks/record_world.py`` runs the command line
with it.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from falcon_plan.sim.firmware import Firmware

from .independent_world import SUBSTEP_TARGET_HZ, World, _Layout, _period, _start_point

DRIFT_SPAN_S = 12.0
"""A drifting motor gain changes by its ``gain_drift`` over this long [s] (about one recording)."""


class WorldPlant:
    """The independent ``world`` stepped one control period at a time at ``rate_hz`` [Hz],
    starting at rest at the legs' home angle; ``deadband`` [command units] and
    ``gain_drift`` [relative change over :data:`DRIFT_SPAN_S`] act on the command."""

    def __init__(self, world: World, rate_hz: float = 1000.0, *, deadband: float = 0.0,
                 gain_drift: float = 0.0) -> None:
        params = world.params
        self.world, self.rate_hz, self.dt_s = world, float(rate_hz), 1.0 / float(rate_hz)
        self.deadband, self.gain_drift = float(deadband), float(gain_drift)
        layout = _Layout(params, world.two_mass, max(1, int(round(SUBSTEP_TARGET_HZ / self.rate_hz))))
        self._fn = _period(layout)
        self._fn.inputs[2][:] = world.vector(self.dt_s / layout.substeps)
        self._home = params.theta_home_rad + world.encoder_offset_rad
        self._cpr = params.counts_per_rad
        theta0 = np.full(3, params.theta_home_rad)
        self._x = np.zeros(12 if world.two_mass else 6)
        self._x[0:3] = _start_point(theta0, params)
        if world.two_mass:
            self._x[6:9] = theta0
        self._k = 0
        self._firmware = Firmware(params.command_delay_samples + world.extra_delay,
                                  max(1, int(round(params.command_hold_s * self.rate_hz))))
        self.acting_commands = np.zeros(3)
        self._counts = np.floor((theta0 - self._home) * self._cpr + 0.5).astype(np.int64)

    @property
    def time_s(self) -> float:
        """Time lived since the start [s]."""
        return self._k * self.dt_s

    @property
    def counts(self) -> np.ndarray:
        """The encoder counts now (int64, (3,))."""
        return self._counts.copy()

    def step(self, commands: Any) -> np.ndarray:
        """One control period with ``commands`` (3 numbers) issued now, or None (nothing
        arrived: the firmware holds the last one until its hold runs out); returns the counts
        at the period's end."""
        issued = None if commands is None else np.clip(np.rint(np.asarray(commands, float)), -4096, 4096)
        self.acting_commands = self._firmware.push(issued)
        command = self.acting_commands
        if self.deadband:
            command = np.sign(command) * np.maximum(np.abs(command) - self.deadband, 0.0)
        if self.gain_drift:
            command = command * (1.0 + self.gain_drift * self.time_s / DRIFT_SPAN_S)
        fn = self._fn
        fn.inputs[0][:] = self._x
        fn.inputs[1][:] = command
        fn()
        x = fn.outputs[0].copy()
        if not np.all(np.isfinite(x)):
            raise RuntimeError("the independent world diverged")
        self._x = x
        self._k += 1
        motor = x[6:9] if self.world.two_mass else np.asarray(fn.outputs[1]).ravel()
        self._counts = np.floor((np.asarray(motor).ravel() - self._home) * self._cpr + 0.5).astype(np.int64)
        return self._counts.copy()


def open_world_device(plant: WorldPlant, *, rate_hz: float, usb_timing: Any, firmware: Any = None) -> Any:
    """An open :class:`~falcon_plan.devices.usb_falcon.UsbFalcon` on the emulated Falcon
    backend whose physics is ``plant``, through the threaded USB driver when ``usb_timing``
    (a :class:`~falcon_plan.devices.emulated.UsbTiming`) is given (as the device factory
    opens ``--device emulated``)."""
    from falcon_plan.devices.emulated import EmulatedFalconBackend, FaultPlan
    from falcon_plan.devices.usb_falcon import UsbFalcon
    from falcon_plan.execution.device_factory import write_dummy_firmware

    backend = EmulatedFalconBackend(plant, FaultPlan(), timing=usb_timing)
    dummy = write_dummy_firmware() if firmware is None else None
    try:
        device = UsbFalcon(dummy or firmware, backend=backend, rate_hz=rate_hz, realtime=False,
                           io="blocking" if usb_timing is None else "threaded")
        device.open()
    finally:
        if dummy is not None:
            dummy.unlink(missing_ok=True)
    return device


__all__ = ["WorldPlant", "open_world_device", "DRIFT_SPAN_S"]
