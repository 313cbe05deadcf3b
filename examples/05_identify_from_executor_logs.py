"""Identification from executor logs: one row per hidden effect on the simulated device.

For each case of the discrepancy tests (tests/discrepancy/conftest.py: the same effects and
magnitudes), the executor records a training excitation (mixed, 6 s) and a held-out one
(fourier, 4 s) on the simulated device with the effects hidden in it (opened afresh for each,
starting at home), through the same path as ``falcon-plan experiment run`` (home, approach
move, executor, falcon log); then
``find_discrepancy`` names and fits the effects. Prints a Markdown table: named vs true,
fitted vs true, held-out replay error before/after, time; and writes the logs and the table
into the output folder.

Run: .venv/bin/python examples/05_identify_from_executor_logs.py [CASE ...] [--out DIR]
(default: every case, out/examples)
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "discrepancy"))

from conftest import CASES  # noqa: E402

from falcon_plan.discrepancy.excitation import design_trajectory  # noqa: E402
from falcon_plan.discrepancy.workflow import find_discrepancy  # noqa: E402
from falcon_plan.approach import run_from_here  # noqa: E402
from falcon_plan.execution.device_factory import open_device  # noqa: E402
from falcon_plan.execution.executor import ExecutionStatus  # noqa: E402
from falcon_plan.falconlog import read_log  # noqa: E402
from falcon_plan.model.dynamics import FalconModel  # noqa: E402


DEFAULT_OUT = Path(__file__).resolve().parents[1] / "out" / "examples"


def say(text: str) -> None:
    """Progress on stderr (the table goes to stdout)."""
    print(text, file=sys.stderr, flush=True)


def record(effects, folder: Path, prefix: str, rate_hz: float = 800.0):
    """(training, held-out) executor logs on the simulated device hiding ``effects``, written
    as ``folder/<prefix>_train.csv`` and ``_heldout.csv``."""
    model = FalconModel()
    logs = []
    for name, kind, seconds, seed in (("train", "mixed", 6.0, 11), ("heldout", "fourier", 4.0, 23)):
        path = folder / f"{prefix}_{name}.csv"
        say(f"  recording the {name} log ({kind}, {seconds:g} s of motion) -> {path.name}")
        with open_device("sim", rate_hz=rate_hz, model=model, effects=effects) as device:
            report, _ = run_from_here(device, "sim", design_trajectory(kind, seconds, seed, rate_hz), model,
                                      rate_hz=rate_hz, log_path=path, controller_kind="pd")  # as experiment run records
        assert report.status == ExecutionStatus.COMPLETED, report.reason
        logs.append(read_log(path))
    return logs


def fitted_vs_true(fitted, effects) -> str:
    """``field value (true value)`` for each fitted field; the true value is the hidden
    effects' (the nominal one where the case did not set it)."""
    return ", ".join(f"{f} {p.value:.4g} (true {getattr(effects, f):.4g})" for f, p in fitted.items()) or "-"


def main(names: list[str], out_dir: Path) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = ["| case | named | fitted (true) | held-out RMS before -> after [counts] | identify [s] |",
            "|---|---|---|---|---|"]
    print("\n".join(rows), flush=True)
    for i, name in enumerate(names, 1):
        case = CASES[name]
        say(f"case {i}/{len(names)}: {name}")
        train, held = record(case.effects, out_dir, f"05_{name}")
        say("  identifying (replays and fits of every candidate effect; 5-45 s)")
        t0 = time.perf_counter()
        rep = find_discrepancy(train, held)
        took = time.perf_counter() - t0
        mark = "" if tuple(sorted(rep.effects)) == tuple(sorted(case.names)) else " **(true: " + \
            ", ".join(case.names) + ")**"
        rows.append(f"| {name} | {', '.join(rep.effects)}{mark} | {fitted_vs_true(rep.parameters, case.effects)} | "
                    f"{rep.heldout_before.rms_counts_all:.3g} -> {rep.heldout_after.rms_counts_all:.3g} | "
                    f"{took:.1f} |")
        print(rows[-1], flush=True)
    table = out_dir / "05_table.md"
    table.write_text("\n".join(rows) + "\n")
    say(f"wrote {table} and the falcon logs beside it")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("cases", nargs="*", metavar="CASE", help=f"cases to run (default all: {', '.join(CASES)})")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default out/examples)")
    args = parser.parse_args()
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        parser.error(f"unknown case(s) {', '.join(unknown)}; allowed: {', '.join(CASES)}")
    main(args.cases or list(CASES), args.out)
