"""Identification from executor logs: one row per hidden effect on the simulated device.

For each case of the discrepancy tests (tests/discrepancy/conftest.py: the same effects and
magnitudes), the executor records a training excitation (mixed, 6 s) and a held-out one
(fourier, 4 s) on the simulated device with the effects hidden in it (opened afresh for each,
starting at home), through the same path as ``falcon-plan experiment run`` (home, approach
move, executor, falcon log); then
``find_discrepancy`` names and fits the effects. Prints a Markdown table: named vs true,
fitted vs true, held-out replay error before/after, time.

    .venv/bin/python examples/05_identify_from_executor_logs.py [CASE ...]
"""
from __future__ import annotations

import math
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "discrepancy"))

from conftest import CASES  # noqa: E402

from falcon_plan.discrepancy.excitation import design_trajectory  # noqa: E402
from falcon_plan.discrepancy.workflow import find_discrepancy  # noqa: E402
from falcon_plan.approach import run_from_here  # noqa: E402
from falcon_plan.execution.device_factory import open_device  # noqa: E402
from falcon_plan.falconlog import read_log  # noqa: E402
from falcon_plan.model.dynamics import FalconModel  # noqa: E402


def record(effects, folder: Path, rate_hz: float = 800.0):
    """(training, held-out) executor logs on the simulated device hiding ``effects``."""
    model = FalconModel()
    logs = []
    for name, kind, seconds, seed in (("train", "mixed", 6.0, 11), ("heldout", "fourier", 4.0, 23)):
        path = folder / f"{name}.csv"
        with open_device("sim", rate_hz=rate_hz, model=model, effects=effects) as device:
            report, _ = run_from_here(device, "sim", design_trajectory(kind, seconds, seed, rate_hz), model,
                                      rate_hz=rate_hz, log_path=path, controller_kind="pd")  # as experiment run records
        assert report.status == "completed", report.reason
        logs.append(read_log(path))
    return logs


def main(names: list[str]) -> None:
    print("| case | named | fitted (true) | held-out RMS before -> after [counts] | identify [s] |")
    print("|---|---|---|---|---|")
    for name in names or list(CASES):
        case = CASES[name]
        with tempfile.TemporaryDirectory() as tmp:
            train, held = record(case.effects, Path(tmp))
        t0 = time.perf_counter()
        rep = find_discrepancy(train, held)
        took = time.perf_counter() - t0
        fitted = ", ".join(f"{f} {p.value:.4g} ({case.checked.get(f, math.nan):.4g})"
                           for f, p in rep.parameters.items()) or "-"
        mark = "" if tuple(sorted(rep.effects)) == tuple(sorted(case.names)) else " **(true: " + \
            ", ".join(case.names) + ")**"
        print(f"| {name} | {', '.join(rep.effects)}{mark} | {fitted} | "
              f"{rep.heldout_before.rms_counts_all:.3g} -> {rep.heldout_after.rms_counts_all:.3g} | {took:.1f} |",
              flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
