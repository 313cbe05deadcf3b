"""The safe stop's cost and latency (issue 24 item 3).

1. Compute cost at many cancel ticks of a planned move, against a reference timed in the same
   run (one LQR design along the whole move: what Executor.prepare does before every run):
   the stop's first commands made with the plan (``first_commands`` for every tick), the
   loop's work before the stop's first command is sent (their look-up and the controller's
   ``quick_tail``), the rest of the quick brake (``quick_brake`` and ``quick_tail``: a worker's
   since the stop's first commands hold its first FIRST_BRAKE_TICKS exactly; before, the loop's
   once the first command was sent) and the minimum-time brake made off the loop (``plan_brake`` and
   ``splice_tail``, the stop's designed gains). A paced loop at 800 Hz has 1.25 ms per tick.
2. Latency on paced runs (the simulated device paced by the executor to wall-clock deadlines),
   quiet and beside ``--stress`` CPU-burning processes: a thread (at normal priority, then at
   the loop's real-time priority) sets the cancel at a random instant of the motion; "first brake command after cancel [periods]" is from that instant to
   when the first braking command (the row at ``report.brake.tick``) was handed to the device,
   in periods (<= 1: the stop begins at the first deadline after the cancel arrived); the
   same from the moment the cancel's flag was set (the cancel's arrival at the executor: a
   normal-priority canceller can be held up by a busy machine between its clock reading and
   its ``set()``, reported beside it as "canceller's clock reading to its flag set"), and the
   same in ticks: the slot the first brake command was sent in, after the slot of the first deadline after
   the cancel (0: that very one; a loop held up by the machine counts here too); the slots skipped
   in the ``AFTER_TICKS`` ticks from that first deadline on (p50/max over the runs: the loop held
   up after the cancel, by its own work on the stop, by the workers beside it or by the machine),
   against the same in the ``AFTER_TICKS`` ticks before the cancel (the machine's share) and the loop's own work on
   the stop (``ExecutionReport.stop_work_us``: CPU time of the loop's thread per tick, its max per
   run; absent before it was reported).

Before/after a change: run this file with ``PYTHONPATH`` at the other checkout. Measured
(``--repeat 3 --runs 60 --stress 0,1``, back to back, 2026-11-27): runs with a slot skipped in
the 20 ticks after the cancel, quiet / + 1 stress process (normal, real-time canceller), before
the rest of the quick brake left the loop 60, 57 / 58, 44 of 60 (p50 2, 1 / 1, 1; max 5, 4 / 6, 4),
after 27, 32 / 24, 18 (p50 0, 1 / 0, 0; max 5, 6 / 5, 5), the 20 ticks before the cancel 1, 0 /
1, 0; in the 4 ticks after the first brake command 60, 57 / 58, 44 -> 6, 12 / 6, 4; the loop's
stop work per tick at most 0.54-0.67 ms (CPU, p50 of the runs' max 0.36-0.40 ms).

From the cancel's flag (``--repeat 1 --runs 20 --stress 1``, 2026-11-27 22:57 UTC, load ~4 from
other sessions besides the stress process): first brake command p50 0.70 / max 0.97 periods
after the flag was set (normal-priority canceller; its clock reading to its flag: p50 3 us,
max 9 us), 0.73 / 0.95 with a real-time canceller; 0 of 20 runs over one period in either;
a slot skipped in the 20 ticks after the cancel in 2 and 3 of 20 runs (max 1), none before.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_brake.py --repeat 20 --runs 10 --stress 0,1
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time

import numpy as np

from bench_executor import cpu_stress
from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.execution.braking import STOP_HOLD_S, first_commands, plan_brake, quick_brake
from falcon_plan.execution.executor import Executor
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import counts_to_position
from falcon_plan.planning.api import plan_problem
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.timing import realtime_thread

RATE = 800.0
AFTER_TICKS = 20
"""Slots skipped are counted over this many ticks from the first deadline after the cancel."""


class _SentTimes:
    """A row sink keeping when each row's command was sent [s, monotonic]."""

    def __init__(self) -> None:
        self.sent: dict[int, float] = {}

    def start(self, meta, model) -> None:  # noqa: ANN001
        self.sent = {}

    def row(self, t_s, enc, tc, ref, measured_m, planned_m, timing) -> None:  # noqa: ANN001
        self.sent[int(round(t_s * RATE))] = timing.sent_us * 1e-6 if timing is not None else float("nan")

    def first_sent_from(self, tick: int) -> float:
        """When the first row at or after ``tick`` was sent [s, monotonic]."""
        return self.sent[min(k for k in self.sent if k >= tick)]

    def finish(self, report) -> None:  # noqa: ANN001
        pass


class _StampedCancel(threading.Event):
    """A cancel event that keeps when its flag was set [s, monotonic]: the cancel's arrival at
    the executor (the canceller's own delays before its ``set()`` call, a user thread held up by
    a busy machine, come before it)."""

    def __init__(self) -> None:
        super().__init__()
        self.set_at: float | None = None

    def set(self) -> None:
        if self.set_at is None:
            self.set_at = time.monotonic()
        super().set()


def compute_costs(model: FalconModel, plan, repeat: int) -> dict[str, float]:
    with SimDevice(model=model, rate_hz=RATE) as dev:
        ex = Executor(dev, model, preroll_s=0.05)
        s = ex.prepare(plan.trajectory)
        c = ex.controller
        hold = int(STOP_HOLD_S * RATE)
        ticks = np.arange(45, 40 + int(plan.trajectory.duration_s * RATE), 5)
        first_s, quick_s, refined_s, ref_s, table_s = [], [], [], [], []
        for _ in range(repeat):
            t0 = time.perf_counter()
            c.schedule(s.ref_counts + 1e-6 * len(ref_s), model)  # a fresh design (not cached)
            ref_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            first_commands(s.ref_counts, s.position_m, s.velocity_m_s, range(s.t_s.shape[0]), model,
                           c.feedforward_effects, RATE, c.feedforward_lead_samples)
            table_s.append(time.perf_counter() - t0)
            for k in ticks:
                args = (s.ref_counts, s.position_m, s.velocity_m_s, int(k), model, c.feedforward_effects, RATE,
                        c.feedforward_lead_samples)
                t0 = time.perf_counter()
                c.quick_tail(s.tracker, int(k), *s.first_brake.at(int(k)), model)
                t1 = time.perf_counter()
                b = quick_brake(*args, hold)
                c.quick_tail(s.tracker, int(k), b.ref_counts, b.feedforward, model)
                t2 = time.perf_counter()
                b = plan_brake(*args, hold)
                c.splice_tail(s.tracker, int(k), b.ref_counts, b.feedforward, model)
                first_s.append(t1 - t0)
                quick_s.append(t2 - t1)
                refined_s.append(time.perf_counter() - t2)
    ms = lambda x, q: float(np.percentile(x, q)) * 1e3  # noqa: E731
    return {"samples": len(quick_s), "period_ms": 1e3 / RATE,
            "loop_first_command_p50_ms": ms(first_s, 50), "loop_first_command_p99_ms": ms(first_s, 99),
            "rest_of_quick_brake_p50_ms": ms(quick_s, 50), "rest_of_quick_brake_p99_ms": ms(quick_s, 99),
            "offloop_min_time_p50_ms": ms(refined_s, 50), "offloop_min_time_p99_ms": ms(refined_s, 99),
            "reference_design_p50_ms": ms(ref_s, 50), "first_commands_with_the_plan_p50_ms": ms(table_s, 50),
            "loop_first_command_p50_over_reference": ms(first_s, 50) / ms(ref_s, 50)}


def paced_latency(model: FalconModel, plan, runs: int, seed: int, realtime_canceller: bool = False) -> dict[str, object]:
    """Cancels at random instants of ``runs`` paced runs of ``plan`` (module docstring), set by
    a thread at normal priority (a user's thread, which a busy machine may hold up between its
    clock reading and the cancel, or while it holds the interpreter's lock) or, with
    ``realtime_canceller``, at the loop's real-time priority (the executor's own latency)."""
    rng = np.random.default_rng(seed)
    latencies, ticks_late, skipped, first_skipped, next_skipped, handovers = [], [], [], 0, 0, []
    skipped_after, skipped_before, stop_work, arrival, held_canceller = [], [], [], [], []
    sink = _SentTimes()
    for _ in range(runs):
        with SimDevice(model=model, rate_hz=RATE) as dev:
            dev.home()
            ex = Executor(dev, model, preroll_s=0.05, pace=True, sink=sink)
            ex.prepare(plan.trajectory)
            cancel = _StampedCancel()
            at: list[float] = []
            delay = ex.preroll_s + rng.uniform(0.1, 0.8) * plan.trajectory.duration_s

            def fire() -> None:
                if realtime_canceller:
                    realtime_thread()
                while ex.running_run() is None:        # from the run's start (not its setup)
                    time.sleep(2e-4)
                time.sleep(delay)
                at.append(time.monotonic())
                cancel.set()

            threading.Thread(target=fire, daemon=True).start()
            report = ex.run(plan.trajectory, cancel=cancel)
        if report.brake is None or not at:
            continue
        if report.timing is not None and report.timing.skipped_slots:
            skipped.append(report.timing.skipped_slots)
        tick = report.brake.tick
        first_skipped += tick not in sink.sent
        next_skipped += any(j not in sink.sent for j in range(tick + 1, tick + 5))
        latencies.append((sink.first_sent_from(tick) - at[0]) * RATE)
        arrival.append((sink.first_sent_from(tick) - cancel.set_at) * RATE)
        held_canceller.append((cancel.set_at - at[0]) * 1e6)
        # the slot of the first deadline after the cancel (slot k's deadline: t0 + k / RATE,
        # t0 the earliest a row was sent, less its slot's time)
        t0 = min(sent - k / RATE for k, sent in sink.sent.items())
        first_slot = math.ceil((at[0] - t0) * RATE)
        ticks_late.append(min(k for k in sink.sent if k >= tick) - first_slot)
        skipped_after.append(sum(j not in sink.sent for j in range(first_slot, first_slot + AFTER_TICKS)))
        skipped_before.append(sum(j not in sink.sent for j in range(first_slot - AFTER_TICKS, first_slot)))
        work = getattr(report, "stop_work_us", ())
        if work:
            stop_work.append(max(us for _, us in work))
        handovers.extend(s["tick"] - tick for s in report.splices if s["taken"])
    lat = np.array(latencies)
    first = ({f"p{q}": float(np.percentile(lat, q)) for q in (50, 99)} | {"max": float(lat.max())}) if lat.size else None
    late = np.array(ticks_late)
    arr = np.array(arrival)
    held = np.array(held_canceller)
    return {"paced_runs": len(lat), "first brake command after cancel [periods]": first,
            "runs_over_one_period": int((lat > 1.0).sum()),
            "first brake command after the cancel's flag was set [periods]":
                ({f"p{q}": float(np.percentile(arr, q)) for q in (50, 99)} | {"max": float(arr.max()),
                 "runs_over_one_period": int((arr > 1.0).sum())}) if arr.size else None,
            "canceller's clock reading to its flag set [us]":
                {"p50": float(np.median(held)), "max": float(held.max())} if held.size else None,
            "first brake command's slot after the first deadline after the cancel [ticks]":
                {"p50": float(np.median(late)), "p99": float(np.percentile(late, 99)), "max": int(late.max())}
                if late.size else None,
            "runs_whose_first_brake_slot_was_skipped": first_skipped,
            "runs_with_a_slot_skipped_in_the_4_ticks_after_it": next_skipped,
            "runs_with_skipped_slots": len(skipped),
            f"slots skipped in the {AFTER_TICKS} ticks after the cancel": {
                "p50": float(np.median(skipped_after)), "max": int(max(skipped_after)),
                "runs_with_any": int(sum(x > 0 for x in skipped_after))} if skipped_after else None,
            f"slots skipped in the {AFTER_TICKS} ticks before the cancel (reference)": {
                "p50": float(np.median(skipped_before)), "max": int(max(skipped_before)),
                "runs_with_any": int(sum(x > 0 for x in skipped_before))} if skipped_before else None,
            "loop's stop work per tick, max in a run [us]": {
                "p50": float(np.median(stop_work)), "max": float(max(stop_work))} if stop_work else None,
            "min_time_handover_ticks_after_cancel": {"taken": len(handovers), "p50": float(np.median(handovers)) if handovers else None,
                                                     "max": max(handovers) if handovers else None}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--runs", type=int, default=10, help="paced runs cancelled at a random instant")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--stress", default="0,1", help="CPU-stress processes beside the paced runs, one set of runs "
                        "per value (default 0,1)")
    args = parser.parse_args(argv)
    model = FalconModel()
    home = counts_to_position(np.zeros(3))
    plan = plan_problem(PlanProblem(tuple(home), tuple(home + [0.03, -0.02, 0.01])), PlanOptions.fast(), model)
    out = compute_costs(model, plan, args.repeat)
    for stress in (int(x) for x in args.stress.split(",")):
        with cpu_stress(stress):
            out[f"paced_stress{stress}"] = paced_latency(model, plan, args.runs, args.seed)
            out[f"paced_stress{stress}_realtime_canceller"] = paced_latency(model, plan, args.runs, args.seed, True)
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
