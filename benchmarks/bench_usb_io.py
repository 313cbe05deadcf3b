"""Loop rate of the USB driver against an emulated Falcon with real bus timing.

The emulated Falcon (:class:`~falcon_plan.devices.emulated.EmulatedFalconBackend` with
:class:`~falcon_plan.devices.emulated.UsbTiming`: 1 ms USB frames, the serial link at
1.5 Mbaud, the FTDI latency timer at the 1 ms the driver sets) stands behind the real driver
(:class:`~falcon_plan.devices.usb_falcon.UsbFalcon`, the whole pyusb path). Its plant is a
stand-in that moves each leg by ``-command // 64`` counts per packet, so the cost measured is
the I/O's, not a simulation's.

Per round, in the same process one after the other:

- reference: a bare loop with the executor's deadline scheme (``timing.run_bare_loop``) doing
  nothing but waiting for its deadlines at 1 kHz;
- ``blocking``: each tick writes one command and reads until its answer arrives;
- ``threaded``: a writer and a reader thread, each tick hands over its command and takes the
  newest status (the design the driver uses on a real Falcon).

Each device loop is paced by the same deadline timer at 1 kHz for ``--ticks`` slots and sends
a command step on leg 0 half way. Reported per design: ticks run, achieved rate (ticks per
second of wall time) and its ratio to the reference's, missed deadlines (ticks starting more
than a period late) and skipped slots, p99 start error, packets that reached the device per
second, and the command-to-encoder delay in ticks (from the step to the first reading that
shows it).

Usage: ``python benchmarks/bench_usb_io.py [--rounds N] [--ticks N] [--out results.json]``.
The machine is shared: trust ratios within a run.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.devices.emulated import EmulatedFalconBackend, UsbTiming
from falcon_plan.devices.usb_falcon import UsbFalcon
from falcon_plan.timing import DeadlineTimer, run_bare_loop

RATE_HZ = 1000.0
STEP = np.array([640, 0, 0])
"""Command step on leg 0 [command units] (10 counts per packet on the stand-in plant)."""


class CountingPlant:
    """Stand-in plant: each packet moves every leg by ``-command // 64`` counts."""

    rate_hz = RATE_HZ
    time_s = 0.0

    def __init__(self) -> None:
        self.counts = np.zeros(3, dtype=np.int64)

    def step(self, commands: Any) -> np.ndarray:
        self.counts = self.counts - np.asarray(commands, dtype=np.int64) // 64
        return self.counts.copy()


def device_loop(io: str, ticks: int, firmware: Path) -> dict[str, Any]:
    """Open the timed emulated Falcon with ``io``, home it, run ``ticks`` paced slots."""
    backend = EmulatedFalconBackend(CountingPlant(), homing_packets=2, timing=UsbTiming())
    with UsbFalcon(firmware, backend=backend, realtime=False, io=io) as dev:
        dev.home()
        timer = DeadlineTimer(RATE_HZ, capacity=ticks)
        packets0 = backend.falcon.packets_received
        slot, done, step_at, delay = 0, 0, None, None
        first = dev.exchange([0, 0, 0]).counts[0]
        t0 = time.perf_counter()
        timer.start(t0 + 1.0 / RATE_HZ)
        while slot < ticks:
            slot = timer.wait(slot)
            command = STEP if slot >= ticks // 2 else np.zeros(3, dtype=np.int64)
            if step_at is None and command.any():
                step_at = done
            reading = dev.exchange(command)
            if step_at is not None and delay is None and reading.counts[0] != first:
                delay = done - step_at
            done += 1
            slot += 1
        wall = time.perf_counter() - t0
        packets = backend.falcon.packets_received - packets0
    summary = timer.summary()
    return {"io": io, "ticks": done, "wall_s": wall, "rate_hz": done / wall,
            "missed_deadlines": summary.missed_deadlines, "skipped_slots": summary.skipped_slots,
            "p99_us": summary.p99_us, "device_packets_per_s": packets / wall,
            "delay_ticks": delay}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3, help="rounds (default 3)")
    parser.add_argument("--ticks", type=int, default=2000, help="slots per loop (default 2000)")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = parser.parse_args()
    fd, name = tempfile.mkstemp(suffix=".bin")
    with os.fdopen(fd, "wb") as handle:
        handle.write(np.random.default_rng(0).integers(0, 256, 1000, dtype=np.uint8).tobytes())
    rows: list[dict[str, Any]] = []
    try:
        for r in range(args.rounds):
            bare = run_bare_loop(RATE_HZ, args.ticks)
            ref = {"io": "reference", "ticks": bare.ticks,
                   "rate_hz": bare.ticks / ((bare.ticks + bare.skipped_slots) / RATE_HZ),
                   "missed_deadlines": bare.missed_deadlines,
                   "skipped_slots": bare.skipped_slots, "p99_us": bare.p99_us}
            round_rows = [ref] + [device_loop(io, args.ticks, Path(name))
                                  for io in ("blocking", "threaded")]
            for row in round_rows:
                row["round"] = r
                row["rate_ratio"] = row["rate_hz"] / ref["rate_hz"]
            rows += round_rows
    finally:
        Path(name).unlink(missing_ok=True)
    print(f"{'round':>5} {'design':>10} {'ticks':>6} {'rate Hz':>8} {'ratio':>6} {'missed':>7} "
          f"{'skipped':>8} {'p99 us':>8} {'pkts/s':>7} {'delay':>6}")
    for row in rows:
        pkts = row.get("device_packets_per_s")
        print(f"{row['round']:>5} {row['io']:>10} {row['ticks']:>6} {row['rate_hz']:>8.1f} "
              f"{row['rate_ratio']:>6.3f} {row['missed_deadlines']:>7} {row['skipped_slots']:>8} "
              f"{row['p99_us']:>8.0f} {'' if pkts is None else f'{pkts:7.1f}':>7} "
              f"{'' if row.get('delay_ticks') is None else row['delay_ticks']:>6}")
    for io in ("blocking", "threaded"):
        ratios = [row["rate_ratio"] for row in rows if row["io"] == io]
        print(f"median rate ratio {io}/reference: {statistics.median(ratios):.3f}")
    if args.out is not None:
        args.out.write_text(json.dumps({"rate_hz": RATE_HZ, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
