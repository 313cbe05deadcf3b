"""Devices the executor drives: the USB Falcon, the emulated Falcon, the simulated plant."""
