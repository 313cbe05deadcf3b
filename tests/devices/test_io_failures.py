"""Failures of the threaded USB I/O (the default, what real hardware runs), through the real
pyusb code path against the emulated Falcon: a backend that raises (USB errors and others) or
hangs, in the OUT and the IN transfer, once or every time, mid-run. What counts is what the
emulated device received (its own record), never the driver's belief: the run must stop with
an error naming the cause, and zero force must reach the device by a path that does not go
through the failed thread. Also the device's watchdog thread and its emergency zero in
threaded mode, each with a stall shorter than the run, so that a test fails when that stop is
taken out. Every wait is for a condition, with a generous time limit (no fixed sleeps)."""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import pytest

from falcon_plan.devices.base import DeviceTimeoutError, ZeroForceError
from falcon_plan.devices.emulated import NEVER, EmulatedFalconBackend, FaultPlan, TransferFault
from falcon_plan.devices.usb_falcon import UsbFalcon
from falcon_plan.errors import DeviceError, SafetyStop

THREADED = dict(realtime=False, io="threaded", check_timeout_s=0.02, echo_timeout_s=0.05,
                reply_timeout_s=0.025)
"""Threaded I/O, the loop unpaced (each exchange still waits up to one period for a new
status), short protocol timeouts (the emulator answers at once) but a silence bound of
100 ms, which a loaded machine's scheduling does not reach."""
RATE_HZ = 1000.0
FORCE = [720, -9, -504]
"""The command applied when the I/O fails (the issue's example)."""
HOMING_PACKETS = 3
FAULT_AFTER = 60
"""Runtime packets (homing included) before the injected fault: mid-run."""
SILENCE_S = THREADED["reply_timeout_s"] * (3 + 1)
"""The driver's silence bound: reply_timeout_s x (resends + 1) [s]."""
MAX_TICKS = 5000
CAUSES = {"usb-eio": "USBError", "usb-pipe": "USBError", "usb-timeout": "USB timeout",
          "runtime": "RuntimeError: emulated backend failure",
          "value": "ValueError: emulated backend got a bad buffer",
          "os": "OSError"}
"""What the error must name for each injected exception kind."""
DOING = {"write": "writer thread stopped while writing a command packet",
         "read": "reader thread stopped while reading status packets"}


def wait_for(condition, timeout_s: float = 5.0) -> bool:
    """Poll ``condition()`` until it is true or ``timeout_s`` passed; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return bool(condition())
        time.sleep(0.001)
    return True


def held(backend: EmulatedFalconBackend) -> list[int]:
    """The command the emulated firmware applies now (its own record)."""
    return backend.falcon.held_commands.tolist()


def force_until_error(dev: UsbFalcon, backend: EmulatedFalconBackend):
    """Send FORCE until an exchange raises; returns (error, exchanges that returned after the
    fault was injected, seconds from the fault to the error)."""
    returned: list[float] = []
    for _ in range(MAX_TICKS):
        try:
            dev.exchange(FORCE)
        except DeviceError as exc:
            t_error = time.monotonic()
            first = backend.falcon.first_fault_s
            assert first is not None, f"failed before the injected fault: {exc}"
            return exc, sum(t > first for t in returned), t_error - first
        returned.append(time.monotonic())
    raise AssertionError(f"no error in {MAX_TICKS} exchanges; faults hit: "
                         f"{backend.falcon.transfer_faults}")


def open_falcon(firmware: Path, plant, fault: TransferFault | None, **options) -> tuple:
    """An open, homed UsbFalcon (THREADED over ``options``; by default without its watchdog
    thread, whose own tests are below, so that a loaded machine's stall cannot stop a test
    of the I/O failures first) on an emulated Falcon with ``fault``."""
    backend = EmulatedFalconBackend(plant, FaultPlan(transfer=fault), homing_packets=HOMING_PACKETS)
    options = {**THREADED, "watchdog_s": None, **options}
    dev = UsbFalcon(firmware, backend=backend, rate_hz=RATE_HZ, **options)
    dev.open()
    dev.home(timeout_s=5.0)
    return dev, backend


@pytest.mark.parametrize("times", [1, NEVER], ids=["once", "always"])
@pytest.mark.parametrize("kind", list(CAUSES))
@pytest.mark.parametrize("direction", ["write", "read"])
def test_a_failing_transfer_stops_the_run_and_zero_reaches_the_device(
        stub_plant, firmware: Path, caplog, direction: str, kind: str, times: int) -> None:
    # "always" fails every transfer of that direction on this USB handle; a new handle works
    fault = TransferFault(direction, kind, after_packets=FAULT_AFTER, times=times)
    dev, backend = open_falcon(firmware, stub_plant, fault)
    try:
        error, late, _ = force_until_error(dev, backend)
        assert held(backend) == [0, 0, 0], f"force left on after: {error}"
        assert DOING[direction] in str(error) and CAUSES[kind] in str(error), str(error)
        assert "zero force could not be delivered" not in str(error)
        # the failing thread wakes the waiting exchange: the run stops at once, not after
        # a silence timeout (a loaded machine may let a tick or two through)
        assert late <= 3, late
        assert backend.falcon.packets_received < FAULT_AFTER + 20
        # a failed device stays stopped: no force until it is opened again
        with pytest.raises(DeviceError, match="failed earlier"):
            dev.exchange(FORCE)
        assert held(backend) == [0, 0, 0]
    finally:
        caplog.clear()
        with caplog.at_level(logging.ERROR):
            dev.close()
    assert not [r for r in caplog.records if "zero force" in r.getMessage()], caplog.text
    assert held(backend) == [0, 0, 0]
    if direction == "write" and times == NEVER:
        assert backend.open_count == 2        # zero went out on a reopened handle
    # and the device can be opened again and used
    dev.open()
    try:
        assert dev.exchange([0, 0, 0]) is not None
    finally:
        dev.close()


def test_a_single_transient_write_error_ends_the_run_yet_close_succeeds(
        stub_plant, firmware: Path, caplog) -> None:
    dev, backend = open_falcon(firmware, stub_plant, TransferFault("write", "usb-eio",
                                                                   after_packets=FAULT_AFTER))
    with caplog.at_level(logging.WARNING):
        with pytest.raises(DeviceError, match=r"writer thread.*Input/Output Error"):
            for _ in range(MAX_TICKS):
                dev.exchange(FORCE)
        assert held(backend) == [0, 0, 0]
        dev.close()
    assert "could not send zero force" not in caplog.text
    assert held(backend) == [0, 0, 0] and backend.falcon.transfer_faults == 1
    assert backend.open_count == 1            # the bus was healthy: no reopen needed


def test_a_write_path_broken_for_good_says_zero_could_not_be_delivered(
        stub_plant, firmware: Path) -> None:
    fault = TransferFault("write", "usb-eio", after_packets=FAULT_AFTER, times=NEVER,
                          cleared_by_reopen=False)
    dev, backend = open_falcon(firmware, stub_plant, fault)
    try:
        error, _, _ = force_until_error(dev, backend)
        # nothing reaches the device: the error must say so, and what to do
        assert "zero force could not be delivered" in str(error), str(error)
        assert "unplug its power supply" in str(error) and "Input/Output Error" in str(error)
        assert held(backend) == FORCE
        with pytest.raises(ZeroForceError):
            dev.zero_force()
    finally:
        dev.close()                            # logs, never raises
    assert not dev.is_open and held(backend) == FORCE   # the emulator's truth


@pytest.mark.parametrize("direction", ["write", "read"])
def test_a_hung_transfer_is_caught_by_the_silence_guard(stub_plant, firmware: Path,
                                                        direction: str) -> None:
    # a wedged host controller: the thread never returns, the reading stops changing while
    # commands keep coming; that is a timeout within the silence bound
    fault = TransferFault(direction, "hang", after_packets=FAULT_AFTER, hang_s=10.0)
    dev, backend = open_falcon(firmware, stub_plant, fault)
    try:
        error, _, elapsed = force_until_error(dev, backend)
        assert isinstance(error, DeviceTimeoutError), repr(error)
        assert "no status packet" in str(error) and "USB cable" not in str(error)
        assert {"write": "writer thread sent nothing",
                "read": "reader thread read nothing"}[direction] in str(error), str(error)
        assert SILENCE_S <= elapsed < SILENCE_S + 1.0, elapsed
        if direction == "read":              # the writer is free: zero is there already
            assert held(backend) == [0, 0, 0]
    finally:
        backend.release_hangs()
        dev.close()
    # a write released after the zero is followed by zero again (the writer's last packet),
    # or cancelled by the close
    assert wait_for(lambda: held(backend) == [0, 0, 0]), held(backend)
    assert wait_for(lambda: not any(t.name.startswith("falcon-usb") and t.is_alive()
                                    for t in threading.enumerate()))
    assert held(backend) == [0, 0, 0]


# --- the device's own watchdog thread and emergency zero, threaded I/O ---------------------
def test_the_watchdog_thread_zeroes_a_stalled_threaded_loop(stub_plant, firmware: Path) -> None:
    dev, backend = open_falcon(firmware, stub_plant, None, watchdog_s=0.04)
    try:
        for _ in range(20):
            dev.exchange(FORCE)
        assert wait_for(lambda: held(backend) == FORCE, 2.0)
        # the loop stalls (here: waits for the device to show zero); only the watchdog can end it
        t_stall = time.monotonic()
        assert wait_for(lambda: held(backend) == [0, 0, 0], 5.0), "the watchdog never zeroed"
        assert time.monotonic() - t_stall >= 0.04
        assert dev.watchdog_trips >= 1 and "watchdog" in dev.stall_reason
        with pytest.raises(SafetyStop, match="watchdog: no device tick"):
            dev.exchange(FORCE)              # the loop comes back: told once, force stays 0
        assert held(backend) == [0, 0, 0]
        dev.exchange([50, 0, 0])             # reported: the caller may go on
        assert wait_for(lambda: held(backend) == [50, 0, 0], 2.0)
    finally:
        dev.close()
    assert held(backend) == [0, 0, 0]


def test_a_threaded_tick_stuck_in_the_loop_is_overtaken_by_the_emergency_zero(
        stub_plant, firmware: Path) -> None:
    inside, release = threading.Event(), threading.Event()

    class StuckTick(UsbFalcon):
        """Stops inside the tick (holding the device lock) once the command 777 went out,
        as a loop thread that is descheduled mid-tick does."""

        def _reading(self, status, t_status):
            if self.last_commands.tolist() != [777, 0, 0] and self._in_flight.tolist() == [777, 0, 0] \
                    and not release.is_set():
                inside.set()
                release.wait(10.0)
            return super()._reading(status, t_status)

    backend = EmulatedFalconBackend(stub_plant, homing_packets=HOMING_PACKETS)
    dev = StuckTick(firmware, backend=backend, rate_hz=RATE_HZ, watchdog_s=0.03, **THREADED)
    with dev:
        dev.home(timeout_s=5.0)
        raised: list[BaseException] = []

        def tick() -> None:
            try:
                dev.exchange([777, 0, 0])
            except SafetyStop as exc:
                raised.append(exc)

        loop = threading.Thread(target=tick)
        loop.start()
        try:
            assert inside.wait(5.0)
            assert wait_for(lambda: held(backend) == [777, 0, 0], 2.0)
            # the watchdog cannot take the lock the stuck tick holds: it writes zero itself
            assert wait_for(lambda: held(backend) == [0, 0, 0], 5.0), "no emergency zero"
            assert dev.watchdog_trips >= 1 and loop.is_alive()
        finally:
            release.set()
            loop.join(5.0)
        assert raised and "watchdog" in str(raised[0])   # the loop learns of the stall
        assert held(backend) == [0, 0, 0]
    assert held(backend) == [0, 0, 0]
