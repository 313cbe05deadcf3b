"""The discrepancy workflow on every test case, own plant and independent world: a table of
named vs true effects, fitted vs true parameters, held-out replay error before and after, and
the time of each case (wall and CPU), with the time of one closed-loop replay of the same training log (the
named reference, measured in the same run) and their ratio.

Usage: ``python benchmarks/bench_discrepancy.py [--world-only | --plant-only] [--cases a,b]
[--out results.json]``. Timings vary run to run on a shared machine; trust the ratios more.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))      # the test tree's case definitions (tests/discrepancy)

from falcon_plan.discrepancy.replay import closed_loop_replay, log_controller  # noqa: E402
from falcon_plan.discrepancy.workflow import find_discrepancy  # noqa: E402
from falcon_plan.model.dynamics import FalconModel  # noqa: E402
from falcon_plan.model.effects import NOMINAL  # noqa: E402


def _row(source: str, name: str, train: Any, held: Any, true_names: tuple[str, ...],
         checked: dict[str, Any]) -> dict[str, Any]:
    model = FalconModel()
    start, cpu = time.perf_counter(), time.process_time()
    report = find_discrepancy(train, held)
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    start = time.perf_counter()
    closed_loop_replay(train, NOMINAL, model, float(train.meta["rate_hz"]), log_controller(train))
    replay = time.perf_counter() - start
    fitted = {k: p.value for k, p in report.parameters.items()}
    if report.corrected.extra_delay_samples:
        fitted["extra_delay_samples"] = report.corrected.extra_delay_samples
    return {"source": source, "case": name, "true": list(true_names), "named": report.effects,
            "ok": sorted(report.effects) == sorted(true_names),
            "true_values": checked, "fitted": fitted,
            "heldout_before": report.heldout_before.rms_counts_all,
            "heldout_after": report.heldout_after.rms_counts_all,
            "unexplained": dataclasses.asdict(report.unexplained.where) if report.unexplained.where else None,
            "seconds": wall, "cpu_seconds": cpu, "replay_reference_s": replay, "ratio_to_one_replay": wall / replay}


def run(world: bool, plant: bool, only: list[str] | None) -> list[dict[str, Any]]:
    rows = []
    if plant:
        from tests.discrepancy.conftest import CASES, case_logs
        for name, case in CASES.items():
            if only and name not in only:
                continue
            train, held = case_logs(name)
            rows.append(_row("own plant", name, train, held, case.names, dict(case.checked)))
            print(_fmt(rows[-1]), flush=True)
    if world:
        from tests.discrepancy.world_cases import WORLD_CASES, world_logs
        for name, case in WORLD_CASES.items():
            if only and name not in only:
                continue
            train, held = world_logs(case)
            true = {k: v[0] for k, v in case.checked.items()}
            rows.append(_row("independent world", name, train, held, case.names, true))
            print(_fmt(rows[-1]), flush=True)
    return rows


def _num(x: Any) -> str:
    return f"{x:.4g}" if isinstance(x, float) and math.isfinite(x) else str(x)


def _fmt(r: dict[str, Any]) -> str:
    fitted = ", ".join(f"{k}={_num(v)}" + (f" (true {_num(r['true_values'][k])})" if k in r["true_values"] else "")
                       for k, v in r["fitted"].items()) or "-"
    where = "" if r["unexplained"] is None else \
        f" unexplained: {r['unexplained']['leg_name']} leg, {r['unexplained']['phase']}"
    return (f"| {r['source']} | {r['case']} | {', '.join(r['true'])} | {', '.join(r['named'])}"
            f"{' ✓' if r['ok'] else ' ✗'}{where} | {fitted} | {r['heldout_before']:.2f} -> "
            f"{r['heldout_after']:.2f} | {r['seconds']:.1f} s, CPU {r['cpu_seconds']:.1f} s "
            f"({r['ratio_to_one_replay']:.0f}x one replay) |")


def main(argv: list[str] | None = None) -> int:
    """Run the cases, print a markdown table, write JSON to ``--out`` if given."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world-only", action="store_true")
    parser.add_argument("--plant-only", action="store_true")
    parser.add_argument("--cases", default=None, help="comma-separated case names (default all)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    print("| source | case | true effects | named | fitted (true) | held-out RMS counts before -> after | time |")
    print("|---|---|---|---|---|---|---|")
    rows = run(not args.plant_only, not args.world_only, args.cases.split(",") if args.cases else None)
    times = sorted(r["seconds"] for r in rows)
    if times:
        cpu = sorted(r["cpu_seconds"] for r in rows)
        print(f"\n{sum(r['ok'] for r in rows)}/{len(rows)} named exactly; time per case median "
              f"{times[len(times) // 2]:.1f} s, min {times[0]:.1f} s, max {times[-1]:.1f} s; CPU time "
              f"median {cpu[len(cpu) // 2]:.1f} s, min {cpu[0]:.1f} s, max {cpu[-1]:.1f} s "
              f"({sum(c <= 5.0 for c in cpu)}/{len(cpu)} cases <= 5 s)")
    if args.out is not None:
        args.out.write_text(json.dumps(rows, indent=2, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
