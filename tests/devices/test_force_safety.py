"""Force safety without trusting the firmware: the emulated firmware keeps the last command
forever (its default, since nothing public documents a timeout), so every path must end in a
zero command sent by the host: the watchdog thread, a tick stuck in I/O, and every exit path
of the process (normal end, an exception, SIGINT, SIGTERM, SIGHUP and the other signals that
end a process, interpreter exit), the latter run
in subprocesses whose emulated device writes every packet it receives to a file."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from falcon_plan.devices.emulated import EmulatedFalconBackend
from falcon_plan.devices.usb_falcon import UsbFalcon
from falcon_plan.errors import SafetyStop

FAST = dict(realtime=False, io="blocking", check_timeout_s=0.02, echo_timeout_s=0.05,
            reply_timeout_s=0.01)


def test_the_emulated_firmware_holds_the_last_command_forever(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, homing_packets=2)
    with UsbFalcon(firmware, backend=backend, watchdog_s=None, **FAST) as dev:
        dev.home()
        dev.exchange([300, -200, 100])
        time.sleep(0.25)                                    # no packet for 250 ms
        np.testing.assert_array_equal(backend.falcon.held_commands, [300, -200, 100])
    np.testing.assert_array_equal(backend.falcon.held_commands, 0)     # close() sent zero


def test_the_watchdog_thread_zeroes_a_stalled_loop(stub_plant, firmware: Path) -> None:
    backend = EmulatedFalconBackend(stub_plant, homing_packets=2)
    with UsbFalcon(firmware, backend=backend, watchdog_s=0.04, **FAST) as dev:
        dev.home()
        dev.exchange([0, 0, 0])
        time.sleep(0.15)                     # zero force applied: a pause is not a stall
        assert dev.watchdog_trips == 0
        t_stall = time.monotonic()           # before the tick's kick: a trip is never earlier
        dev.exchange([300, -200, 100])
        while not np.all(backend.falcon.held_commands == 0) and time.monotonic() < t_stall + 5:
            time.sleep(0.002)
        zeroed_after = time.monotonic() - t_stall
        np.testing.assert_array_equal(backend.falcon.held_commands, 0)
        assert 0.04 <= zeroed_after < 0.04 * 1.2 + 0.5, zeroed_after   # slack for a loaded machine
        assert dev.watchdog_trips == 1 and "watchdog" in dev.stall_reason
        with pytest.raises(SafetyStop, match="watchdog: no device tick"):
            dev.exchange([300, -200, 100])   # the loop comes back: told once, force stays 0
        np.testing.assert_array_equal(backend.falcon.held_commands, 0)
        dev.exchange([50, 0, 0])             # reported: the caller may go on
        np.testing.assert_array_equal(backend.falcon.held_commands, [50, 0, 0])


def test_a_tick_stuck_in_its_read_is_overtaken_by_the_emergency_zero(
        stub_plant, firmware: Path) -> None:
    inside, release = threading.Event(), threading.Event()

    class StuckRead(EmulatedFalconBackend):
        def bulk_read(self, *args):
            if self.falcon.last_commands.tolist() == [777, 0, 0] and not release.is_set():
                inside.set()
                release.wait(2.0)          # the loop hangs in the IN transfer
            return super().bulk_read(*args)

    backend = StuckRead(stub_plant, homing_packets=1)
    with UsbFalcon(firmware, backend=backend, watchdog_s=0.03, **FAST) as dev:
        dev.home()
        raised: list[BaseException] = []

        def tick() -> None:
            try:
                dev.exchange([777, 0, 0])
            except SafetyStop as exc:
                raised.append(exc)

        loop = threading.Thread(target=tick)
        loop.start()
        assert inside.wait(2.0)
        t0 = time.monotonic()
        while backend.falcon.last_commands.tolist() != [0, 0, 0] and time.monotonic() < t0 + 1:
            time.sleep(0.002)
        # the watchdog wrote a zero packet on the free OUT endpoint while the read hung
        np.testing.assert_array_equal(backend.falcon.held_commands, 0)
        assert dev.watchdog_trips == 1
        release.set()
        loop.join(2.0)
        assert raised and "watchdog" in str(raised[0])   # the loop learns of the stall
        np.testing.assert_array_equal(backend.falcon.held_commands, 0)


def test_a_write_stuck_past_the_watchdog_is_followed_by_zero(stub_plant_class,
                                                             firmware: Path) -> None:
    # A stuck OUT transfer cannot be overtaken (the next packet queues behind it), so its
    # command lands after the watchdog fired: the tick sends zero again when it returns.
    class SlowPlant(stub_plant_class):
        def step(self, commands):
            if list(commands) == [777, 0, 0]:
                time.sleep(0.15)
            return super().step(commands)

    plant = SlowPlant()
    backend = EmulatedFalconBackend(plant, homing_packets=1)
    with UsbFalcon(firmware, backend=backend, watchdog_s=0.03, **FAST) as dev:
        dev.home()
        dev.exchange([100, 0, 0])
        with pytest.raises(SafetyStop, match="watchdog"):
            dev.exchange([777, 0, 0])
        assert dev.watchdog_trips == 1
        assert plant.sent[-1] == [0, 0, 0] and [777, 0, 0] in plant.sent
        np.testing.assert_array_equal(backend.falcon.held_commands, 0)


# --- exit paths, in subprocesses -----------------------------------------------------------
SCRIPT = textwrap.dedent('''
    import sys, time
    import numpy as np
    from falcon_plan.devices.emulated import EmulatedFalconBackend
    from falcon_plan.devices.usb_falcon import UsbFalcon

    class Plant:
        rate_hz, time_s = 1000.0, 0.0
        def step(self, commands):
            return np.zeros(3, dtype=np.int64)

    mode, tap, firmware, io = sys.argv[1:5]
    backend = EmulatedFalconBackend(Plant(), homing_packets=2, wire_log=tap)
    # no watchdog: the zero must come from the exit path itself
    dev = UsbFalcon(firmware, backend=backend, realtime=True, io=io, watchdog_s=None,
                    check_timeout_s=0.02, echo_timeout_s=0.05, reply_timeout_s=0.05)

    def force_ticks(n):
        for _ in range(n):
            dev.exchange([400, -300, 200])

    if mode == "normal":
        with dev:
            dev.home()
            force_ticks(20)
    elif mode == "exception":
        with dev:
            dev.home()
            force_ticks(20)
            raise RuntimeError("a bug in the caller")
    elif mode == "interpreter-exit":
        dev.open()
        dev.home()
        force_ticks(20)
        sys.exit(0)                        # never closed: atexit must zero it
    else:                                  # a signal arrives while force is applied
        dev.open()
        dev.home()
        force_ticks(20)
        print("forcing", flush=True)
        while True:
            force_ticks(1)
''')


def _run(tmp_path: Path, firmware: Path, mode: str, sig: int | None = None, io: str = "blocking"):
    script = tmp_path / "exit_path.py"
    script.write_text(SCRIPT)
    tap = tmp_path / f"wire-{mode}.log"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.Popen([sys.executable, str(script), mode, str(tap), str(firmware), io],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    if sig is not None:
        assert proc.stdout.readline().strip() == "forcing"
        time.sleep(0.05)
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    rows = [line.split() for line in tap.read_text().splitlines()]
    commands = np.array([[int(v) for v in row[1:4]] for row in rows])
    return proc.returncode, err, commands


@pytest.mark.parametrize("mode, sig, code", [
    ("normal", None, 0),
    ("exception", None, 1),
    ("interpreter-exit", None, 0),
    ("signal", signal.SIGINT, None),
    ("signal", signal.SIGTERM, 128 + signal.SIGTERM),
    ("signal", signal.SIGHUP, 128 + signal.SIGHUP),      # the terminal closed, an ssh session lost
    ("signal", signal.SIGQUIT, 128 + signal.SIGQUIT),
    ("signal", signal.SIGUSR1, 128 + signal.SIGUSR1),
], ids=["normal-end", "exception", "interpreter-exit", "SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1"])
@pytest.mark.parametrize("io", ["threaded", "blocking"])
@pytest.mark.slow
def test_every_exit_path_ends_in_zero_force(tmp_path: Path, firmware: Path, mode: str,
                                            sig: int | None, code: int | None, io: str) -> None:
    returncode, err, commands = _run(tmp_path, firmware, mode, sig, io)
    if code is not None:
        assert returncode == code, err
    else:                                   # SIGINT: KeyboardInterrupt, however Python exits
        assert returncode != 0 and "KeyboardInterrupt" in err, err
    # force was applied (threaded: a command not yet written is replaced by the next one)
    assert (commands == [400, -300, 200]).all(axis=1).sum() >= (20 if io == "blocking" else 1)
    np.testing.assert_array_equal(commands[-1], [0, 0, 0])       # and the device ended at 0
    if mode == "exception":
        assert "a bug in the caller" in err
