"""Devices the executor drives: the USB Falcon, the emulated Falcon, the simulated plant.

``base`` holds the :class:`Device` contract; ``protocol`` the pure packet codec;
``usb_falcon`` the pyusb driver (pyusb imported only when a device is opened); ``emulated``
a pyusb backend that behaves like a Falcon (imports pyusb; not re-exported here);
``sim_device`` the simulated device.
"""
from falcon_plan.devices.base import (COMMAND_LIMIT, LED_BLUE, LED_GREEN, LED_RED,
                                      BackendMissingError, BaseDevice, Device,
                                      DeviceDisconnectedError, DeviceNotFoundError,
                                      DevicePermissionError, DeviceReading, DeviceTimeoutError,
                                      FirmwareError)
from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.devices.usb_falcon import UsbFalcon

__all__ = [
    "COMMAND_LIMIT", "LED_BLUE", "LED_GREEN", "LED_RED", "BackendMissingError", "BaseDevice",
    "Device", "DeviceDisconnectedError", "DeviceNotFoundError", "DevicePermissionError",
    "DeviceReading", "DeviceTimeoutError", "FirmwareError", "SimDevice", "UsbFalcon",
]
