"""Opening the device an execution runs on: simulated, emulated USB, or the real Falcon.

- ``sim``: :class:`~falcon_plan.devices.sim_device.SimDevice`, the plant stepped directly.
- ``emulated``: the real USB driver :class:`~falcon_plan.devices.usb_falcon.UsbFalcon` over
  :class:`~falcon_plan.devices.emulated.EmulatedFalconBackend` (a SimPlant behind a pyusb
  backend). The emulated Falcon accepts ANY non-empty firmware image, so without
  ``firmware`` a dummy image (random bytes) is written to a temporary file for the load and
  deleted after; the whole loading protocol still runs. By default its transfers complete
  at once and the driver uses blocking I/O (each reading answers its own command, so a run
  is deterministic and may go faster than real time); with ``usb_timing`` (a
  :class:`~falcon_plan.devices.emulated.UsbTiming`) the bus has real frame and latency
  timing and the driver uses threaded I/O, as on the real Falcon.
- ``usb``: the real Falcon with threaded I/O; ``firmware`` (Novint's image, never shipped)
  is required unless it is running already.

Devices come back open, not homed. The executor paces real-time runs itself, so the devices
are opened with their own pacing off (``realtime=False``), which avoids two sleeps per tick.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import InvalidParameterError, KinematicsError, SafetyStop

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device
    from falcon_plan.devices.emulated import FaultPlan, UsbTiming
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.effects import Effects
    from falcon_plan.model.params import FalconParams

DEVICE_KINDS = ("sim", "emulated", "usb")
DUMMY_FIRMWARE_BYTES = 4096
"""Size of the dummy image written for the emulated device [bytes]."""


def write_dummy_firmware(directory: str | Path | None = None) -> Path:
    """A random stand-in firmware image in a new temporary file (the emulated Falcon accepts
    any non-empty image); the caller deletes it."""
    fd, name = tempfile.mkstemp(prefix="falcon-dummy-firmware-", suffix=".bin", dir=directory)
    with os.fdopen(fd, "wb") as handle:
        handle.write(np.random.default_rng(0).integers(0, 256, DUMMY_FIRMWARE_BYTES, dtype=np.uint8).tobytes())
    return Path(name)


def open_device(kind: str, *, rate_hz: float = 800.0, model: FalconModel | None = None,
                firmware: str | Path | None = None, firmware_running: bool = False,
                start_m: Any = None, effects: Effects | None = None, faults: FaultPlan | None = None,
                usb_timing: UsbTiming | None = None, **usb_options: Any) -> Device:
    """Open a device of ``kind`` (:data:`DEVICE_KINDS`) at ``rate_hz`` [Hz].

    ``model`` (FalconModel), ``start_m`` (start point [m], sim only) and ``effects`` set up
    the simulated plant (sim and emulated); ``faults`` (a devices.emulated.FaultPlan) and
    ``usb_timing`` (a devices.emulated.UsbTiming) configure the emulated device.
    ``firmware_running`` says the firmware was loaded before (a real Falcon keeps it until
    unplugged; the emulated one then starts with it running), so no image is needed.
    ``usb_options`` go to UsbFalcon (``io``, retries, timeouts, ``watchdog_s``).
    """
    if kind not in DEVICE_KINDS:
        raise InvalidParameterError(f"device must be one of {DEVICE_KINDS}, got {kind!r}")
    if kind == "sim":
        from falcon_plan.devices.sim_device import SimDevice

        device: Device = SimDevice(model=model, rate_hz=rate_hz, effects=effects, realtime=False,
                                start_position_m=start_m)
        device.open()
        return device
    from falcon_plan.devices.usb_falcon import UsbFalcon

    if kind == "usb":
        if firmware is None and not firmware_running:
            raise InvalidParameterError("the USB Falcon needs its firmware image: pass --firmware PATH "
                                        "(Novint's nVent image; the project does not ship it)")
        device = UsbFalcon(firmware, rate_hz=rate_hz, realtime=False, **usb_options)
        device.open()
        return device
    from falcon_plan.devices.emulated import EmulatedFalconBackend, FaultPlan
    from falcon_plan.sim.plant import SimPlant

    plant = SimPlant(model, rate_hz=rate_hz, effects=effects)
    backend = EmulatedFalconBackend(plant, faults if faults is not None else FaultPlan(),
                                    firmware_running=firmware_running, timing=usb_timing)
    usb_options.setdefault("io", "blocking" if usb_timing is None else "threaded")
    dummy = write_dummy_firmware() if firmware is None and not firmware_running else None
    try:
        device = UsbFalcon(dummy or firmware, backend=backend, rate_hz=rate_hz, realtime=False,
                           **usb_options)
        device.open()
    finally:
        if dummy is not None:
            dummy.unlink(missing_ok=True)
    return device


def read_position(device: Device, params: FalconParams | None = None) -> np.ndarray:
    """The device's end-effector position [m] (3,), from one zero-force tick's counts by
    forward kinematics. Raises SafetyStop if the counts have no solution."""
    from falcon_plan.model.kinematics import PositionTracker
    from falcon_plan.model.params import ACRA2009

    reading = device.exchange(np.zeros(3, dtype=np.int64))
    try:
        return PositionTracker(params or ACRA2009).position(reading.counts)
    except KinematicsError as exc:
        raise SafetyStop(f"measured counts {reading.counts.tolist()} have no forward-kinematic "
                         f"solution ({exc})") from exc
