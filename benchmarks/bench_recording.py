"""What recording and the live view cost the 1 kHz control loop.

Part 1, the hand-off: the time of one ``RunRecorder.row`` call (what the executor pays per
tick for a recording or a live view: one row into the shared-memory ring) against a bare
``deque.append`` and an empty method call, while the recording process is busy encoding and
writing; and the recording process's own work per row (encoding and writing an MCAP), in units
of a ``json.dumps`` of a small dict.

Part 2, the loop: the executor at 1 kHz, paced, on the simulated device (``--device emulated``:
the emulated Falcon, the whole USB path, noisier), the same planned move in rounds that
alternate (each round starting with the next variant)

- ``none``: no recording (the reference of the same round);
- ``mcap``: an MCAP recording;
- ``live``: the Foxglove live view, no client connected (nothing is encoded);
- ``live+client``: the live view with a WebSocket client subscribed to every channel (the
  tests' client, ``tests/recording/foxglove_client.py``, in a process of its own);
- ``mcap+live+client``: both.

Reported per variant: the loop's own work per tick (``busy`` p50/p99, from a tick's start to
its next wait), start-error jitter p99 and missed deadlines, and the busy p50 and p99 minus the
same round's ``none`` (the recording's whole cost per tick, the recording process's share of
the machine included; the issue asks for at most 20 us a tick); and the hand-off's CPU time per
tick in the executor's loop itself (``RowSink.row``, the loop thread's CPU clock around the
call: what the loop pays directly, with and without a client). The busy difference is the
difference of two runs on a shared machine (tens of us apart between rounds of the same
variant), the hand-off time a direct measurement of every tick. ``--stress N`` runs N
CPU-bound processes meanwhile (the second case: the other core busy).

Part 3, the same without the device and the controller: the executor's deadline scheme at
1 kHz doing nothing but handing a row to a recorder (an MCAP file), against doing nothing. This
loop runs at the default priority (the executor's paced loop is SCHED_FIFO where allowed), so
the recording process's batches can delay its wake-ups on a busy machine: its missed deadlines
are what the executor's real-time priority spares it.

Usage: ``python benchmarks/bench_recording.py [--rounds N] [--stress N] [--out results.json]``
(needs the test extra's ``websockets`` for the client). The machine is shared: run it with ``nice`` and
trust the differences within one run.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from falcon_plan.execution.device_factory import open_device, read_position
from falcon_plan.execution.executor import ExecutionStatus, Executor
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.recording.live import LiveView
from falcon_plan.recording.mcapfile import McapRecording
from falcon_plan.recording.recorder import RunRecorder

CLIENT = Path(__file__).resolve().parents[1] / "tests" / "recording" / "foxglove_client.py"

FAST_USB = dict(check_timeout_s=0.02, echo_timeout_s=0.05, reply_timeout_s=0.01)
ENDS_M = (np.array([-0.015, -0.015, 0.12]), np.array([0.015, 0.015, 0.12]))
"""Every run moves from where the device is to the farther of these two points [m]."""
HOLD_S = 1.5
"""Every run holds the start this long before the move [s]: about 2000 ticks a run, so that a
run's p99 is not one or two ticks."""
VARIANTS = ("none", "mcap", "live", "live+client", "mcap+live+client")


def handoff(model: FalconModel, calls: int = 10_000) -> dict[str, float]:
    """Part 1: ns per call of RunRecorder.row (MCAP recording, its process busy), deque.append and
    an empty method."""
    class Empty:
        def row(self, *args: Any) -> None:
            pass

    enc, tc, ref, p = np.zeros(3, np.int64), np.zeros(3, np.int64), np.zeros(3), np.array([0.0, 0.0, 0.12])
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as folder:
        recorder = RunRecorder(Path(folder) / "bench.mcap")
        recorder.start({"rate_hz": "1000"}, model)
        queue: collections.deque[Any] = collections.deque()
        empty = Empty()
        for name, call in (("deque_append_ns", lambda k: queue.append((k * 1e-3, enc, tc, ref, p, p, None))),
                           ("empty_method_ns", lambda k: empty.row(k * 1e-3, enc, tc, ref, p, p)),
                           ("recorder_row_ns", lambda k: recorder.row(k * 1e-3, enc, tc, ref, p, p))):
            best = []
            for _ in range(5):
                t0 = time.perf_counter_ns()
                for k in range(calls // 5):
                    call(k)
                best.append((time.perf_counter_ns() - t0) / (calls // 5))
            out[name] = min(best)  # the loop's own cost, least disturbed by the machine
        t0 = time.perf_counter()
        recorder.close()
        out["recorder_drain_s"] = time.perf_counter() - t0
        out["recorder_rows"] = recorder.rows
        # the recording process's work per row (encoding and writing), done here in line
        from falcon_plan.recording.channels import RowEncoder

        encoder = RowEncoder(model.params, model.params.command_limit)
        rows = 2000
        with McapRecording(Path(folder) / "work.mcap") as recording:
            t0 = time.perf_counter()
            for k in range(rows):
                enc[0] = k % 50
                recording.write_all(encoder.encode(k * 1e-3, enc, tc, ref, p, p))
            out["background_work_per_row_us"] = (time.perf_counter() - t0) / rows * 1e6
        small = {"t_s": 0.0, "counts": [1, 2, 3], "angle_rad": [0.1, 0.2, 0.3]}
        t0 = time.perf_counter()
        for _ in range(20000):
            json.dumps(small)
        out["reference_json_dumps_us"] = (time.perf_counter() - t0) / 20000 * 1e6
    return out


class Watcher:
    """The tests' Foxglove WebSocket client in a process of its own, subscribed to every channel."""

    def __init__(self, url: str) -> None:
        self.proc = subprocess.Popen([sys.executable, str(CLIENT), url], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline().strip() if self.proc.stdout else ""
        if line != "subscribed":
            self.proc.kill()
            raise RuntimeError(f"the Foxglove client did not subscribe: {line!r}")
        self.received = 0

    def close(self) -> None:
        """Stop the client; :attr:`received` is the number of messages it got."""
        out, _ = self.proc.communicate(timeout=30)
        self.received = int(out.split()[-1])


class TimedSink:
    """The executor's row sink ``sink`` with the loop thread's CPU time of every ``row`` call
    kept (``row_ns``, one entry a tick)."""

    def __init__(self, sink: RunRecorder) -> None:
        self.sink = sink
        self.row_ns: list[int] = []

    def start(self, meta: dict[str, str], model: FalconModel) -> None:
        self.sink.start(meta, model)

    def row(self, *row: Any) -> None:
        c0 = time.thread_time_ns()
        self.sink.row(*row)
        self.row_ns.append(time.thread_time_ns() - c0)

    def finish(self, report: Any) -> None:
        self.sink.finish(report)


def loop_rounds(model: FalconModel, rounds: int, folder: Path, kind: str = "sim") -> list[dict[str, Any]]:
    """Part 2: every variant once per round, the same move, on the ``kind`` device at 1 kHz."""
    rows = []
    live = LiveView(port=0)
    extra = FAST_USB if kind == "emulated" else {"start_m": (0.0, 0.0, 0.12)}
    device = open_device(kind, rate_hz=1000.0, model=model, **extra)
    from falcon_plan.planning.api import plan
    from falcon_plan.planning.problem import PlanOptions

    try:
        with device:
            device.home(timeout_s=5.0)
            for r in range(rounds):
                for variant in VARIANTS[r % len(VARIANTS):] + VARIANTS[:r % len(VARIANTS)]:  # no variant always first
                    start = read_position(device, model.params)
                    goal = max(ENDS_M, key=lambda end: float(np.linalg.norm(end - start)))
                    traj = plan(start, goal, PlanOptions.fast(), model).trajectory
                    watcher = Watcher(live.url) if "client" in variant else None
                    if watcher is not None:
                        deadline = time.monotonic() + 10
                        while not live.watched and time.monotonic() < deadline:
                            time.sleep(0.01)
                    recording = folder / f"{r}_{variant}.mcap" if "mcap" in variant else None
                    recorder = RunRecorder(recording, live if "live" in variant else None) \
                        if variant != "none" else None
                    timed = TimedSink(recorder) if recorder is not None else None
                    ex = Executor(device, model, 1000.0, pace=True, preroll_s=HOLD_S, settle_s=0.2, sink=timed)
                    report = ex.run(traj)
                    if recorder is not None:
                        recorder.close()
                    received = 0
                    if watcher is not None:
                        time.sleep(0.2)  # the last batch on its way
                        watcher.close()
                        received = watcher.received
                    tm = report.timing
                    if report.status != ExecutionStatus.COMPLETED or tm is None or tm.busy_p50_us is None:
                        print(f"  round {r} {variant:17s} {report.status}: {report.reason} (not counted)",
                              file=sys.stderr)
                        if hasattr(device, "plant"):  # a simulated device that fell: put it back
                            device.plant.reset(ENDS_M[0])
                        continue
                    row = {"round": r, "variant": variant, "status": report.status, "ticks": tm.ticks,
                           "busy_p50_us": tm.busy_p50_us, "busy_p99_us": tm.busy_p99_us,
                           "jitter_p99_us": tm.p99_us, "missed": tm.missed_deadlines, "messages_received": received}
                    if timed is not None:
                        row["handoff_cpu_p50_us"], row["handoff_cpu_p99_us"] = (
                            float(x) * 1e-3 for x in np.percentile(timed.row_ns, [50, 99]))
                    rows.append(row)
                    print(f"  round {r} {variant:17s} busy p50 {tm.busy_p50_us:6.1f} us p99 {tm.busy_p99_us:6.1f} us"
                          f" | jitter p99 {tm.p99_us:6.1f} us, missed {tm.missed_deadlines}/{tm.ticks}"
                          + (f" | hand-off CPU p50 {row['handoff_cpu_p50_us']:.1f} us p99 {row['handoff_cpu_p99_us']:.1f} us"
                             if timed is not None else "")
                          + (f" | client got {received} messages" if watcher else ""), file=sys.stderr)
    finally:
        live.close()
    return rows


BARE_VARIANTS = ("bare", "deque", "recorder")


class Deque:
    """A row sink that appends the row to a deque (the reference hand-off)."""

    def __init__(self) -> None:
        self.queue: collections.deque[Any] = collections.deque()

    def row(self, *row: Any) -> None:
        self.queue.append(row)


def bare_rounds(model: FalconModel, rounds: int, folder: Path, ticks: int = 3000) -> list[dict[str, Any]]:
    """Part 3: the executor's deadline scheme at 1 kHz doing nothing but (``recorder``) hand a row
    to a recorder writing an MCAP file, (``deque``) append the same row to a deque (the least a
    hand-off can cost, for reference) or (``bare``) nothing: the recording's effect on the
    loop's timing without the device and the controller around it; and the hand-off's own CPU
    time per row (the loop thread's CPU clock)."""
    from falcon_plan.falconlog import TickTiming
    from falcon_plan.timing import DeadlineTimer

    enc, tc, ref, p = np.zeros(3, np.int64), np.zeros(3, np.int64), np.zeros(3), np.array([0.0, 0.0, 0.12])
    rows = []
    for r in range(rounds):
        for variant in BARE_VARIANTS[r % 3:] + BARE_VARIANTS[:r % 3]:
            recorder: Any = None
            if variant == "recorder":
                recorder = RunRecorder(folder / f"bare_{r}.mcap")
                recorder.start({"rate_hz": "1000"}, model)
            elif variant == "deque":
                recorder = Deque()
            cpu_ns = np.zeros(ticks)
            timer = DeadlineTimer(1000.0, capacity=ticks)
            timer.start(time.perf_counter() + 1e-3)
            k = 0
            while k < ticks:
                k = timer.wait(k)
                if recorder is not None and k < ticks:
                    c0 = time.thread_time_ns()
                    recorder.row(k * 1e-3, enc, tc, ref, p, p, TickTiming(k, k, 0))
                    cpu_ns[k] = time.thread_time_ns() - c0
                k += 1
            if variant == "recorder":
                recorder.close()
            tm = timer.summary()
            row = {"round": r, "variant": variant, "missed": tm.missed_deadlines, "ticks": tm.ticks,
                   "jitter_p99_us": tm.p99_us, "busy_p50_us": tm.busy_p50_us, "busy_p99_us": tm.busy_p99_us}
            if recorder is not None:
                row["handoff_cpu_p50_us"] = float(np.percentile(cpu_ns[cpu_ns > 0], 50)) * 1e-3
                row["handoff_cpu_p99_us"] = float(np.percentile(cpu_ns[cpu_ns > 0], 99)) * 1e-3
            rows.append(row)
            print(f"  round {r} {variant:9s} jitter p99 {tm.p99_us:6.1f} us, busy p50 {tm.busy_p50_us:5.1f} us "
                  f"p99 {tm.busy_p99_us:6.1f} us, missed {tm.missed_deadlines}/{tm.ticks}"
                  + (f" | hand-off CPU time p50 {row['handoff_cpu_p50_us']:.1f} us p99 {row['handoff_cpu_p99_us']:.1f} us"
                     if recorder is not None else ""), file=sys.stderr)
    return rows


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per variant: medians over rounds, and busy p50 minus the same round's ``none``."""
    out: dict[str, Any] = {}
    none = {row["round"]: row for row in rows if row["variant"] == "none"}
    for variant in VARIANTS:
        mine = [row for row in rows if row["variant"] == variant and row["round"] in none]
        if not mine:
            continue
        out[variant] = {
            "busy_p50_us": statistics.median(row["busy_p50_us"] for row in mine),
            "busy_p99_us": statistics.median(row["busy_p99_us"] for row in mine),
            "jitter_p99_us": statistics.median(row["jitter_p99_us"] for row in mine),
            "missed": sum(row["missed"] for row in mine), "ticks": sum(row["ticks"] for row in mine),
            "busy_p50_minus_none_us": statistics.median(row["busy_p50_us"] - none[row["round"]]["busy_p50_us"]
                                                        for row in mine),
            "busy_p99_minus_none_us": statistics.median(row["busy_p99_us"] - none[row["round"]]["busy_p99_us"]
                                                        for row in mine)}
        if variant != "none":
            out[variant]["handoff_cpu_p50_us"] = statistics.median(row["handoff_cpu_p50_us"] for row in mine)
            out[variant]["handoff_cpu_p99_us"] = statistics.median(row["handoff_cpu_p99_us"] for row in mine)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3, help="rounds of every variant (default 3)")
    parser.add_argument("--device", choices=("sim", "emulated"), default="sim", help="the device (default sim)")
    parser.add_argument("--stress", type=int, default=0, metavar="N",
                        help="run N CPU-bound processes meanwhile (default 0)")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = parser.parse_args()
    model = FalconModel()
    stress = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.stress)]
    try:
        return measure(args, model)
    finally:
        for proc in stress:
            proc.kill()
            proc.wait()


def measure(args: argparse.Namespace, model: FalconModel) -> int:
    """The three parts, printed on stderr (and written to ``args.out``)."""
    print(f"load average {os.getloadavg()[0]:.2f}, {args.stress} CPU-stress process(es)", file=sys.stderr)
    print("part 1: the hand-off", file=sys.stderr)
    part1 = handoff(model)
    print(f"  RunRecorder.row {part1['recorder_row_ns']:.0f} ns, deque.append {part1['deque_append_ns']:.0f} ns, "
          f"empty method {part1['empty_method_ns']:.0f} ns; the recording process's work per row "
          f"{part1['background_work_per_row_us']:.1f} us (= {part1['background_work_per_row_us'] / part1['reference_json_dumps_us']:.1f}"
          f" json.dumps of a small dict)", file=sys.stderr)
    print(f"part 2: the executor at 1 kHz on the {args.device} device", file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="bench-recording-") as folder:
        rows = loop_rounds(model, args.rounds, Path(folder), args.device)
    print("part 3: a bare 1 kHz deadline loop, with and without handing rows to a recorder", file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="bench-recording-") as folder:
        bare = bare_rounds(model, args.rounds, Path(folder))
    table = summary(rows)
    for variant, row in table.items():
        print(f"  {variant:17s} busy p50 {row['busy_p50_us']:6.1f} us ({row['busy_p50_minus_none_us']:+5.1f} vs none),"
              f" p99 {row['busy_p99_us']:6.1f} us ({row['busy_p99_minus_none_us']:+6.1f}) | jitter p99 {row['jitter_p99_us']:6.1f} us | missed "
              f"{row['missed']}/{row['ticks']}"
              + (f" | hand-off CPU p50 {row['handoff_cpu_p50_us']:.1f} us p99 {row['handoff_cpu_p99_us']:.1f} us"
                 if "handoff_cpu_p50_us" in row else ""), file=sys.stderr)
    for variant in BARE_VARIANTS:
        mine = [row for row in bare if row["variant"] == variant]
        print(f"  bare loop {variant:9s} busy p50 {statistics.median(r['busy_p50_us'] for r in mine):5.1f} us, p99 "
              f"{statistics.median(r['busy_p99_us'] for r in mine):6.1f} us"
              + (f" | hand-off CPU time p50 {statistics.median(r['handoff_cpu_p50_us'] for r in mine):.1f} us, p99 "
                 f"{statistics.median(r['handoff_cpu_p99_us'] for r in mine):.1f} us" if variant != "bare" else ""),
              file=sys.stderr)
    print(f"load average {os.getloadavg()[0]:.2f}", file=sys.stderr)
    results = {"handoff": part1, "rounds": rows, "summary": table, "bare_loop": bare, "stress": args.stress}
    if args.out is not None:
        args.out.write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
