"""UsbFalcon over the real pyusb code path, against the emulated Falcon backend."""
from __future__ import annotations

import errno
import hashlib
import time
from pathlib import Path

import numpy as np
import pytest
import usb.core
import usb.util

from falcon_plan.devices import protocol as proto
from falcon_plan.devices.base import (LED_BLUE, LED_RED, BackendMissingError,
                                      DeviceDisconnectedError, DeviceNotFoundError,
                                      DevicePermissionError, DeviceTimeoutError, FirmwareError)
from falcon_plan.devices.emulated import NEVER, EmulatedFalconBackend, FaultPlan
from falcon_plan.devices.usb_falcon import UsbFalcon
from falcon_plan.errors import DeviceError, SafetyStop


def make_falcon(backend: EmulatedFalconBackend, firmware: Path | None, **kw) -> UsbFalcon:
    """A UsbFalcon with test timings (fast timeouts, no pacing) and blocking I/O (each reading
    answers its own command, so tests can compare it with the plant)."""
    options = dict(backend=backend, realtime=False, io="blocking", check_timeout_s=0.02,
                   echo_timeout_s=0.05, reply_timeout_s=0.01)
    options.update(kw)
    return UsbFalcon(firmware, **options)


def test_emulated_device_enumerates_through_pyusb(stub_plant) -> None:
    backend = EmulatedFalconBackend(stub_plant)
    dev = usb.core.find(idVendor=0x0403, idProduct=0xCB48, backend=backend)
    assert dev is not None and (dev.idVendor, dev.idProduct) == (0x0403, 0xCB48)
    dev.set_configuration()
    intf = dev.get_active_configuration()[(0, 0)]
    addresses = sorted(ep.bEndpointAddress for ep in intf)
    assert addresses == [0x02, 0x81]
    assert all(ep.wMaxPacketSize == 64 for ep in intf)
    assert bytes(dev.read(0x81, 64)) == b"\x31\x60"      # no data: just the 2 status bytes
    usb.util.dispose_resources(dev)


def test_firmware_load_follows_the_documented_steps(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant)
    falcon = backend.falcon
    with make_falcon(backend, firmware) as dev:
        assert bytes(falcon.image) == firmware.read_bytes()
        assert falcon.firmware_running and dev.check_attempts == 1
        assert (falcon.baud_divisor, falcon.latency_ms, falcon.data_format) == (2, 1, 0x0008)
        assert falcon.flow_control == 0 and not falcon.rts
        requests = [(r, v) for _, r, v, _ in falcon.control_log]
        steps = [(0, 1), (0, 2), (9, 16), (3, 0x4138), (4, 0x0008), (2, 0), (1, 0x0200),
                 (1, 0x0100), (1, 0x0101), (1, 0x0100), (3, 0x15), (9, 1), (3, 2), (0, 1),
                 (0, 2)]
        it = iter(requests)
        assert all(step in it for step in steps), requests   # in this order
        assert requests.count((1, 0x0101)) == 1                # one DTR rise: one set-up
        assert dev.exchange([0, 0, 0]).homed == (False, False, False)
    assert backend.open_handles == 0 and not backend.claimed


def test_firmware_check_is_resent_without_a_new_dtr_pulse(stub_plant, firmware: Path) -> None:
    # libnifalcon setFirmwareMode: one set-up, then the check bytes resent as they are
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(failed_checks=7))
    with make_falcon(backend, firmware) as dev:
        assert dev.check_attempts == 8 and backend.falcon.check_attempts == 8
        assert backend.falcon.firmware_running and dev.load_attempts == 1
        requests = [(r, v) for _, r, v, _ in backend.falcon.control_log]
        assert requests.count((1, 0x0101)) == 1                # DTR raised once, not 8 times
        assert backend.falcon.load_attempts == 1


def test_firmware_check_failing_after_all_retries(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(failed_checks=NEVER))
    dev = make_falcon(backend, firmware, check_retries=5, load_retries=2)
    with pytest.raises(FirmwareError, match="firmware load failed 2 times.*check failed 5 "
                                            "times.*power supply"):
        dev.open()
    assert backend.falcon.check_attempts == 10 and not dev.is_open
    assert backend.falcon.load_attempts == 2 and backend.open_count == 2   # closed, reopened
    assert backend.open_handles == 0 and not backend.claimed     # released
    np.testing.assert_array_equal(backend.falcon.held_commands, 0)


@pytest.mark.parametrize("stage", ["run", "check"])
def test_a_load_failing_twice_then_succeeding(stub_plant, firmware: Path, stage: str) -> None:
    # libnifalcon FalconCLIBase: retry the whole load with close and reopen (issue #33: "you
    # often need to do it several times")
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(failed_loads=2,
                                                          failed_load_stage=stage))
    with make_falcon(backend, firmware, check_retries=3, running_check_reads=20) as dev:
        assert dev.load_attempts == 3 and backend.falcon.load_attempts == 3
        assert backend.open_count == 3 and backend.open_handles == 1
        assert backend.falcon.firmware_running
        assert bytes(backend.falcon.image) == firmware.read_bytes()
        assert dev.exchange([0, 0, 0]).counts.shape == (3,)
    with pytest.raises(FirmwareError, match="load failed 2 times"):
        make_falcon(EmulatedFalconBackend(stub_plant, FaultPlan(failed_loads=2)), firmware,
                    load_retries=2, running_check_reads=20).open()


def test_running_check_is_patient(stub_plant, firmware: Path) -> None:
    # the first status packet may take many I/O loops (libnifalcon isFirmwareLoaded: 10 x 100)
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(drop_every=1))
    dev = make_falcon(backend, None, load_retries=1, running_check_rounds=3,
                      running_check_reads=5)
    backend.falcon.firmware_running, backend.falcon._stage = True, "running"
    with pytest.raises(FirmwareError, match=r"no status packets \(3 x 5 reads\)"):
        dev.open()
    assert backend.falcon.packets_received == 3               # one command per round


def test_missing_firmware_file_names_the_path(stub_plant, tmp_path: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant)
    missing = tmp_path / "nope.bin"
    with pytest.raises(FirmwareError, match=f"firmware file not found: {missing}"):
        make_falcon(backend, missing).open()
    assert backend.falcon.control_log == []              # the device was never touched


def test_rejected_echo_names_the_byte(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(corrupt_echo_at=130))
    with pytest.raises(FirmwareError, match="echo mismatch in image bytes 124..185 at byte 130"):
        make_falcon(backend, firmware).open()
    assert not backend.falcon.firmware_running and backend.open_handles == 0


def test_wrong_image_gives_no_status_packets(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant,
                                    expected_image_sha256=hashlib.sha256(b"x").hexdigest())
    with pytest.raises(FirmwareError, match="sent no status packet.*not the nVent firmware"):
        make_falcon(backend, firmware, load_retries=1, running_check_reads=20).open()


def test_open_without_firmware_path(stub_plant, firmware: Path) -> None:
    with pytest.raises(FirmwareError, match="not running.*pass firmware_path"):
        make_falcon(EmulatedFalconBackend(stub_plant), None).open()
    backend = EmulatedFalconBackend(stub_plant, firmware_running=True)
    with make_falcon(backend, None) as dev:
        assert dev.exchange([0, 0, 0]).counts.shape == (3,)
    assert backend.falcon.control_log[0][1] == 9          # straight to runtime settings
    with make_falcon(backend, firmware) as dev:               # reload over a running one
        assert dev.check_attempts == 1 and backend.falcon.firmware_running


def test_homing_then_a_command_stream_moves_the_plant(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, homing_packets=25)
    falcon = backend.falcon
    with make_falcon(backend, firmware) as dev:
        before = dev.exchange([0, 0, 0])
        assert before.counts.tolist() == [1234, -2345, 3456]   # arbitrary until homed
        with pytest.raises(SafetyStop, match="before homing"):
            dev.exchange([500, 0, 0])
        np.testing.assert_array_equal(falcon.held_commands, 0)
        dev.home(timeout_s=1.0)
        assert dev.homed and falcon.last_flags & proto.FLAG_HOMING
        homing_packets = falcon.packets_received
        assert homing_packets >= 25 + 10                       # leg 2 homes last
        falcon.buttons = 0b0101
        start = dev.exchange([0, 0, 0], leds=LED_BLUE)
        assert start.buttons == 0b0101 and start.all_homed
        assert start.counts.tolist() == stub_plant.counts.tolist()
        assert falcon.last_flags == LED_BLUE | proto.FLAG_HOMING   # the flag is kept
        for _ in range(50):
            reading = dev.exchange([640, -640, 99999], leds=LED_RED)
        np.testing.assert_array_equal(falcon.last_commands, [640, -640, 4096])   # clamped
        np.testing.assert_array_equal(reading.counts - start.counts, [-500, 500, -3200])
        assert reading.t_s > start.t_s
    np.testing.assert_array_equal(falcon.held_commands, 0)
    assert falcon.last_flags == proto.FLAG_HOMING              # even the closing zero


def test_homed_bits_come_only_with_the_homing_flag(stub_plant, firmware: Path) -> None:
    # libnifalcon FalconFirmwareNovintSDK.h: "(If homing mode on) Top Encoder Homed"; a driver
    # that dropped the flag after homing would see the device unhomed and stop every run
    backend = EmulatedFalconBackend(stub_plant, homing_packets=3)
    falcon = backend.falcon
    with make_falcon(backend, firmware) as dev:
        dev.home()
        for _ in range(20):
            assert dev.exchange([64, 0, 0]).all_homed          # force flows: still homed
        assert stub_plant.sent[-1] == [64, 0, 0]
        raw = backend.falcon
        raw.receive(proto.encode_command_packet((0, 0, 0), 0), time.monotonic())
        without = proto.decode_status_packet(bytes(raw.in_buffer[-16:]))
        assert without.homed == (False, False, False)           # flag dropped: bits gone
        raw.in_buffer.clear()
        assert dev.exchange([0, 0, 0]).homed == (True, True, True)
        assert falcon.reported_homed == (True, True, True)


def test_homing_timeout_names_the_legs(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, homing_packets=10 ** 9)
    with make_falcon(backend, firmware) as dev:
        with pytest.raises(DeviceTimeoutError,
                           match=r"legs \[0, 1, 2\] not homed.*pull the grip"):
            dev.home(timeout_s=0.05)
        np.testing.assert_array_equal(backend.falcon.held_commands, 0)


def test_counts_unwrap_across_the_16_bit_wire(stub_plant_class, firmware: Path) -> None:
    plant = stub_plant_class(start_counts=(30000, -30000, 0))
    backend = EmulatedFalconBackend(plant, homing_packets=1)
    with make_falcon(backend, firmware) as dev:
        dev.home()
        for _ in range(80):
            reading = dev.exchange([-4096, 4096, 0])             # 64 counts per tick
        np.testing.assert_array_equal(reading.counts, plant.counts)
        assert plant.counts[0] > 32767 and plant.counts[1] < -32768


FAULTS = {
    "short reads": FaultPlan(max_read_bytes=3),
    "misaligned reads": FaultPlan(garbage_every=2, garbage_bytes=7, seed=3),
    "dropped packets": FaultPlan(drop_every=5),
    "all at once": FaultPlan(max_read_bytes=5, garbage_every=3, drop_every=7, seed=4),
}


@pytest.mark.parametrize("faults", FAULTS.values(), ids=FAULTS.keys())
def test_stream_survives_faults(stub_plant, firmware: Path, faults: FaultPlan) -> None:
    backend = EmulatedFalconBackend(stub_plant, faults, homing_packets=3)
    with make_falcon(backend, firmware) as dev:
        dev.home()
        for k in range(150):
            command = [(k % 7) * 64, -64, 0]
            reading = dev.exchange(command)
            # every reading is the plant's state right after this command was applied
            assert reading.counts.tolist() == stub_plant.counts.tolist()
            assert stub_plant.sent[-1] == command
        if faults.drop_every:
            assert dev.resent_packets >= 150 // faults.drop_every
    np.testing.assert_array_equal(backend.falcon.held_commands, 0)


def test_device_that_stops_answering(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(silent_after=40), homing_packets=3)
    with make_falcon(backend, firmware) as dev:
        dev.home()
        with pytest.raises(DeviceTimeoutError, match="did not answer 4 command packets"):
            for _ in range(100):
                dev.exchange([300, 300, 300])
        np.testing.assert_array_equal(backend.falcon.held_commands, 0)


def test_usb_timeout(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(timeout_after=30), homing_packets=3)
    with make_falcon(backend, firmware) as dev:
        dev.home()
        with pytest.raises(DeviceTimeoutError, match="USB timeout while reading"):
            for _ in range(100):
                dev.exchange([300, 300, 300])
        np.testing.assert_array_equal(backend.falcon.held_commands, 0)


def test_disconnect_mid_run(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(disconnect_after=40), homing_packets=3)
    dev = make_falcon(backend, firmware)
    with pytest.raises(DeviceDisconnectedError, match="disconnected.*re-plug") as info:
        with dev:
            dev.home()
            for _ in range(100):
                dev.exchange([300, 300, 300])
    assert isinstance(info.value.__cause__, usb.core.USBError)
    assert info.value.__cause__.errno == errno.ENODEV
    assert not dev.is_open and backend.falcon.packets_received == 40
    # unreachable: a firmware that keeps the last command keeps it (nothing on the host can
    # reach the device); one with a finite hold drops it
    np.testing.assert_array_equal(backend.falcon.held_commands, 300)
    backend.falcon.command_hold_s = 0.05
    time.sleep(0.07)
    np.testing.assert_array_equal(backend.falcon.held_commands, 0)
    with pytest.raises(DeviceError, match="not open"):
        dev.exchange([0, 0, 0])


def test_permission_denied_explains_the_udev_rule(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, FaultPlan(permission_denied=True))
    with pytest.raises(DevicePermissionError) as info:
        make_falcon(backend, firmware).open()
    message = str(info.value)
    assert 'ATTRS{idVendor}=="0403", ATTRS{idProduct}=="cb48", MODE="0666"' in message
    assert "/etc/udev/rules.d/99-falcon.rules" in message
    assert "udevadm control --reload" in message


def test_no_device_found(firmware: Path) -> None:
    with pytest.raises(DeviceNotFoundError, match="no Novint Falcon found.*0403:cb48"):
        make_falcon(EmulatedFalconBackend(present=False), firmware).open()


def test_no_libusb_backend(monkeypatch: pytest.MonkeyPatch, firmware: Path) -> None:
    def find(**kwargs):
        raise usb.core.NoBackendError("No backend available")

    monkeypatch.setattr(usb.core, "find", find)
    with pytest.raises(BackendMissingError, match="apt install libusb-1.0-0.*Zadig"):
        UsbFalcon(firmware).open()


def test_with_the_simulated_plant(model, firmware: Path) -> None:
    plant_module = pytest.importorskip("falcon_plan.sim.plant")
    plant = plant_module.SimPlant(model, rate_hz=1000.0)
    backend = EmulatedFalconBackend(plant, FaultPlan(max_read_bytes=7, drop_every=11),
                                    homing_packets=5)
    with make_falcon(backend, firmware) as dev:
        dev.home()
        start = dev.exchange([0, 0, 0])
        for _ in range(40):
            reading = dev.exchange([-800, -800, -800])
        # negative commands drive theta1 up: counts grow (after the plant's command delay)
        assert np.all(reading.counts > start.counts + 20)
        np.testing.assert_array_equal(reading.counts, plant.counts)
    for _ in range(4):
        plant.step(None)
    np.testing.assert_array_equal(plant.acting_commands, 0)


def test_plant_failure_inside_the_emulator_is_a_device_error(stub_plant_class,
                                                             firmware: Path) -> None:
    from falcon_plan.errors import WorkspaceError

    class FallingPlant(stub_plant_class):
        def step(self, commands):
            if len(self.sent) >= 30:
                raise WorkspaceError("the simulated device left the reachable workspace")
            return super().step(commands)

    backend = EmulatedFalconBackend(FallingPlant(), homing_packets=1)
    dev = make_falcon(backend, firmware)
    with pytest.raises(DeviceError, match="USB error.*emulated Falcon.*left the reachable"):
        with dev:
            dev.home()
            for _ in range(50):
                dev.exchange([0, 0, 0])
    assert not dev.is_open and backend.open_handles == 0
