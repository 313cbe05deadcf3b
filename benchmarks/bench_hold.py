"""The hold while a run is prepared: does it keep its rate on a busy machine?

``run_from_here`` holds the device from homing on (``HoldLoop``, a thread at the loop rate)
while the caller's thread prepares the run (the approach, the LQR gain schedule along the
whole plan). Each run here: the emulated Falcon through the threaded USB driver in wall-clock
time with its grip let go (``released_grip="falls"``: under zero force it falls), a 2 s
excitation at 1 kHz, beside ``--stress`` CPU-burning processes, each run in a fresh process
(the first preparation in a process is the one that loads kernels and builds the forward
kinematics). From the device's own wire record, per run: whether it stopped (a safety stop:
the hold lost the device), the fewest packets in a 50 ms window of the hold's first second
(1 kHz: 50), and the packets at the command limit (+-2480) from the hold's 31st packet to its
700th (the first 30 brake the fall at the limit by design).

Before/after a change: run this file with ``PYTHONPATH`` at the other checkout (the rehearsal
before homing is then whatever that checkout does).

Measured (``--runs 6 --stress 1``, 2026-11-30, the old and new trees alternately): at 5549802,
3 of 6 runs stopped, 43-75 packets at the limit, worst window 0-12 packets; with the
preparation giving way to the hold's ticks and rehearsed before homing, 0 of 6, 0, 32-42.

Usage::

    python benchmarks/bench_hold.py [--runs 6] [--stress 1]
"""
from __future__ import annotations

import argparse
import multiprocessing
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WINDOW_S = 0.05
LIMIT = 2480
BRAKING_PACKETS = 30
JUDGED_PACKETS = 700


def _burn() -> None:  # pragma: no cover - a stress process
    while True:
        pass


def one_run(wire_path: Path) -> str:
    """One held run (module docstring), its wire record written to ``wire_path``; returns the
    stop's reason, or "" when it completed."""
    from falcon_plan.approach import run_from_here
    from falcon_plan.devices.emulated import UsbTiming
    from falcon_plan.discrepancy.excitation import design_trajectory
    from falcon_plan.errors import SafetyStop
    from falcon_plan.execution.device_factory import open_device
    from falcon_plan.execution.safety import SafetyConfig
    from falcon_plan.model.dynamics import FalconModel

    model = FalconModel()
    trajectory = design_trajectory("fourier", 2.0, 0, 1000.0, model)
    device = open_device("emulated", rate_hz=1000.0, model=model,
                         usb_timing=UsbTiming(clock="wall", released_grip="falls"))
    try:
        with device, open(wire_path, "w") as wire:
            device.backend.falcon.wire_log = wire
            try:
                run_from_here(device, "emulated", trajectory, model, rate_hz=1000.0,
                              log_path=wire_path.with_suffix(".csv"), preroll_s=0.5, settle_s=0.1,
                              safety=SafetyConfig(watchdog_timeout_s=0.09))
            finally:
                device.backend.falcon.wire_log = None
    except SafetyStop as exc:
        return str(exc).split(":")[0]
    return ""


def judge(wire_path: Path) -> tuple[int, int]:
    """(fewest packets in a WINDOW_S window of the hold's first second, packets at the limit
    from its packet BRAKING_PACKETS + 1 to JUDGED_PACKETS) from a wire record."""
    import numpy as np

    wire = np.loadtxt(wire_path, ndmin=2)
    t = wire[:, 0]
    forced = np.flatnonzero(np.any(wire[:, 1:4] != 0, axis=1))
    t0 = t[forced[0]]
    starts = np.arange(t0, min(t0 + 1.0, t[-1]) - WINDOW_S, WINDOW_S)
    fewest = min(int(((t >= s) & (t < s + WINDOW_S)).sum()) for s in starts) if starts.size else 0
    judged = wire[forced[0] + BRAKING_PACKETS:forced[0] + JUDGED_PACKETS, 1:4]
    return fewest, int((np.abs(judged) >= LIMIT).any(axis=1).sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=6, help="runs, each in a fresh process")
    parser.add_argument("--stress", type=int, default=1, help="CPU-burning processes beside the runs")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)   # a child: one run, this wire record
    args = parser.parse_args()
    if args.one is not None:
        print(one_run(Path(args.one)))
        return
    burners = [multiprocessing.Process(target=_burn, daemon=True) for _ in range(args.stress)]
    for p in burners:
        p.start()
    stops = 0
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(args.runs):
                wire = Path(tmp) / f"wire{i}.txt"
                done = subprocess.run([sys.executable, __file__, "--one", str(wire)], cwd=ROOT,
                                      capture_output=True, text=True, check=False)
                if done.returncode != 0:
                    print(f"run {i}: failed: {done.stderr.strip().splitlines()[-1:]}", flush=True)
                    continue
                reason = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else ""
                stops += bool(reason)
                fewest, at_limit = judge(wire)
                print(f"run {i}: {'STOPPED (' + reason + ')' if reason else 'completed'}; fewest packets in "
                      f"{WINDOW_S * 1e3:.0f} ms {fewest}; at the limit {at_limit}", flush=True)
    finally:
        for p in burners:
            p.terminate()
    print(f"{stops} of {args.runs} runs stopped (stress {args.stress})")


if __name__ == "__main__":
    main()
