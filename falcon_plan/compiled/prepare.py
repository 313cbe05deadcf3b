"""Build the compiled kernels of the default paths ahead, once per machine.

The first plan on a fresh machine compiles the planner's RK4 step and its adjoint (30-50 s of
one core for each command rule at ``-O1``; all groups together 83 s on a fresh 2-core machine), the first simulation the plant's step,
the first ``discrepancy`` its replays' loops (25 of its first 31 s on a log recorded through the
USB path), and so on (:mod:`falcon_plan.compiled.build` caches every library). Run lazily, that time
lands on whatever comes first: a service's planning process, a test, the demo. This module
runs the default paths once, each group of kernels in its own process so that the groups
compile side by side on the machine's cores, and says which groups are ready.

Run: ``python -m falcon_plan.compiled.prepare`` (``dev.py setup`` does). A machine whose
libraries are all cached finishes in a few seconds.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Callable


def _plan(limit: str) -> None:
    from falcon_plan.planning.api import warm_up
    from falcon_plan.planning.problem import PlanOptions

    warm_up(options=PlanOptions.fast(limit=limit))


def _simulate() -> None:
    import falcon_plan as fp
    from falcon_plan.execution.device_factory import open_device, read_position
    from falcon_plan.execution.executor import Executor

    model = fp.FalconModel()
    with open_device("sim", rate_hz=800.0, model=model, start_m=(0.0, 0.0, 0.12)) as device:
        device.home()
        start = read_position(device, model.params)
        result = fp.plan(start, (0.01, 0.0, 0.125), fp.PlanOptions.fast(), model)
        Executor(device, model, 800.0).run(result.trajectory)


def _identify() -> None:
    """The user's identification path, briefly: a short excitation recorded on the emulated
    Falcon through the USB path with wall-clock timing (``experiment run``), then
    ``discrepancy`` on it (its replays run the rigid and the compliant plant's timed loops)."""
    import tempfile
    from pathlib import Path

    from falcon_plan.cli import main

    with tempfile.TemporaryDirectory(prefix="falcon-plan-prepare-") as folder:
        log = str(Path(folder) / "run.csv")
        record = ["experiment", "run", "--device", "emulated", "--usb-timing", "wall", "--kind", "mixed",
                  "--duration", "2", "--out", log]
        # a stall of the busy machine (the other groups compile beside it) can stop a run: once more
        if main(record) != 0 and main(record) != 0:
            raise RuntimeError(f"falcon-plan {' '.join(record)} failed twice")
        if main(["discrepancy", log, "--heldout", log, "--out", str(Path(folder) / "found")]) != 0:
            raise RuntimeError("falcon-plan discrepancy failed on the recording")


INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT)."""

GROUPS: dict[str, Callable[[], None]] = {
    "planner, device command limit": lambda: _plan("device"),
    "planner, constant command limit": lambda: _plan("constant"),
    "simulated plant and executor": _simulate,
    "identification replays": _identify,
}
"""The groups of kernels, each built by running the path that uses it (the slowest first)."""


def prepare(jobs: int | None = None, out=sys.stderr) -> int:
    """Build every group of :data:`GROUPS` in its own process, ``jobs`` at a time (default:
    the machine's cores); says on ``out`` when each is ready. Returns 0, or 1 if a group failed
    (its output is shown; the kernels it needs are then compiled on first use)."""
    jobs = max(1, jobs or os.cpu_count() or 1)
    waiting = list(GROUPS)
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    failed = 0
    t0 = time.monotonic()
    out.write(f"building the compiled kernels ({len(waiting)} groups, {jobs} at a time; once per machine, "
              "a few minutes on a fresh one)\n")
    while waiting or running:
        while waiting and len(running) < jobs:
            name = waiting.pop(0)
            process = subprocess.Popen([sys.executable, "-m", "falcon_plan.compiled.prepare", "--group", name],
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            running[name] = (process, time.monotonic())
        for name, (process, started) in list(running.items()):
            if process.poll() is None:
                continue
            del running[name]
            output = process.stdout.read() if process.stdout else ""
            if process.returncode == 0:
                out.write(f"  ready: {name} ({time.monotonic() - started:.0f} s)\n")
            else:
                failed += 1
                out.write(f"  failed: {name} (exit status {process.returncode}); its kernels compile on first "
                          f"use instead:\n{output}\n")
        time.sleep(0.2)
    out.write(f"compiled kernels ready in {time.monotonic() - t0:.0f} s\n")
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    """The command line ``argv`` (default: the process's): build every group, or one with
    ``--group``; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m falcon_plan.compiled.prepare", description=__doc__.splitlines()[0])
    parser.add_argument("--group", choices=sorted(GROUPS), help="build one group in this process")
    parser.add_argument("--jobs", type=int, default=None, help="groups built at once (default: the cores)")
    args = parser.parse_args(argv)
    try:
        if args.group is not None:
            GROUPS[args.group]()
            return 0
        return prepare(args.jobs)
    except KeyboardInterrupt:  # the groups (same process group) stop too; a later run finishes the set
        if args.group is None:
            sys.stderr.write("building the compiled kernels: interrupted (what was built is kept)\n")
        return INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
