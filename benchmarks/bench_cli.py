"""How long a user waits for the command line: process wall time of whole ``falcon-plan`` runs.

Each command is a separate process (``subprocess.run``), exactly as a user types it, and is
timed from start to exit. The commands take turns, ``--repeat`` rounds (each round runs every
command once, so all see the same load), after one untimed round that fills the kernel cache
and the operating system's file cache (``warm``). Reported: median and min per command
[s], and each median over the median of the reference ``python -c "import numpy"`` measured
in the same rounds (the machine is shared: compare the ratios; the targets of issue 28 are
absolute times on a quiet machine, where ``import numpy`` takes about 0.1 s):

- ``python -c pass`` and ``python -c "import numpy"``: the references (the interpreter and
  the one library every command needs);
- ``falcon-plan --help`` (target <= 0.3 s);
- ``falcon-plan plan --from 0,0,0.12 --to 0.03,0.02,0.14`` (target <= 1.0 s): the default
  plan and its report (dense re-check, refinement, plant run; the toppra and ruckig
  cross-checks only with ``--crosscheck``);
- the same with ``--crosscheck`` and with ``--fast``, and with ``--plot`` (matplotlib);
- with ``--cold``, also one run of the default plan on an empty kernel cache (a fresh
  machine: every kernel compiled; tens of seconds).

``--profile`` instead prints where one default plan's time goes (``python -X importtime``
grouped by the heavy libraries, then the phases of the command).

The timed processes keep Python's bytecode cache (in a temporary folder), as a user's
machine does: where ``PYTHONDONTWRITEBYTECODE`` is set, every process compiles the package's
modules from source again (0.1-0.2 s more, most of it in the parser's imports).

Where the time goes (2026-11-27, the 2-core machine shared with other jobs, load about 3;
``--repeat 5``, min of 5 / median; ``import numpy`` 0.09 / 0.15 s): ``--help`` 0.17 / 0.20 s,
the default plan 0.75 / 0.91 s (before compiled_points merged only when compiling, measured
right after: 0.97 / 1.02 s), ``--crosscheck`` 1.63 / 1.93 s, ``--plot`` 1.66 / 2.66 s. One
default plan by ``--profile`` at load 2.5 (1.01 s until exit): imports of the planner (numpy
0.10 s, casadi, ruckig) 0.09 s, the parser 0.04 s, the set-up 0.49 s (the planner's graphs
built and kernels loaded with a small plan 0.20 s, the plant's LQR linearisation and design
0.29 s), the plan and its checks 0.30 s (solve 0.19 s, plant run 0.07 s, dense re-check and
refinement the rest), the report 0.09 s; the interpreter's start 0.03 s. The toppra and
ruckig cross-checks (``--crosscheck``) add about 0.9 s, mostly the imports toppra brings
(scipy, matplotlib); a plot (matplotlib) about 1 s.

Usage: ``python benchmarks/bench_cli.py [--repeat 5] [--cold] [--json OUT] [--profile]``.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PLAN = ["plan", "--from", "0,0,0.12", "--to", "0.03,0.02,0.14"]
TARGETS_S = {"falcon-plan --help": 0.3, "falcon-plan " + " ".join(PLAN): 1.0}
"""Issue 28's targets: process wall time on a quiet machine with a warm kernel cache [s]."""
REFERENCE = "python -c 'import numpy'"


def falcon_plan() -> list[str]:
    """The ``falcon-plan`` console script next to this interpreter, else ``python -m falcon_plan.cli``."""
    script = Path(sys.executable).with_name("falcon-plan")
    return [str(script)] if script.exists() else [sys.executable, "-m", "falcon_plan.cli"]


def commands(plot: Path) -> dict[str, list[str]]:
    """Label -> argv of every timed command."""
    fp = falcon_plan()
    return {
        "python -c pass": [sys.executable, "-c", "pass"],
        REFERENCE: [sys.executable, "-c", "import numpy"],
        "falcon-plan --help": [*fp, "--help"],
        "falcon-plan " + " ".join(PLAN): [*fp, *PLAN],
        "falcon-plan " + " ".join(PLAN) + " --fast": [*fp, *PLAN, "--fast"],
        "falcon-plan " + " ".join(PLAN) + " --crosscheck": [*fp, *PLAN, "--crosscheck"],
        "falcon-plan " + " ".join(PLAN) + " --plot FILE.png": [*fp, *PLAN, "--plot", str(plot)],
    }


def run_once(argv: list[str], env: dict[str, str] | None = None) -> float:
    """Wall time [s] of one process running ``argv`` (it must succeed)."""
    start = time.perf_counter()
    done = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({done.returncode}): {done.stderr.decode()[-500:]}")
    return elapsed


def warm_env(tmp: Path) -> dict[str, str]:
    """The environment of the timed processes: Python's bytecode cache on (in ``tmp``, never in
    the tree), as on a user's machine, even where ``PYTHONDONTWRITEBYTECODE`` is set (then every
    process compiles the package's ~60 modules from source again: 0.1-0.2 s)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return {**env, "PYTHONPYCACHEPREFIX": str(tmp / "pycache")}


def measure(repeat: int, cold: bool) -> dict[str, dict[str, float]]:
    """Median and min wall time per command over ``repeat`` rounds (after one untimed round)."""
    with tempfile.TemporaryDirectory(prefix="bench-cli-") as tmp:
        cmds = commands(Path(tmp) / "plan.png")
        env = warm_env(Path(tmp))
        times: dict[str, list[float]] = {label: [] for label in cmds}
        for round_ in range(repeat + 1):
            for label, argv in cmds.items():
                elapsed = run_once(argv, env)
                if round_ > 0:
                    times[label].append(elapsed)
        result = {label: {"median_s": statistics.median(t), "min_s": min(t)} for label, t in times.items()}
        if cold:
            env = {**env, "FALCON_PLAN_CACHE": str(Path(tmp) / "empty-cache")}
            label = "falcon-plan " + " ".join(PLAN) + " (cold kernel cache)"
            once = run_once(cmds["falcon-plan " + " ".join(PLAN)], env)
            result[label] = {"median_s": once, "min_s": once}
    reference = result[REFERENCE]["median_s"]
    for label, row in result.items():
        row["over_reference"] = row["median_s"] / reference
        if label in TARGETS_S:
            row["target_s"] = TARGETS_S[label]
    return result


def profile() -> None:
    """Where one default plan's time goes: imports grouped by library, then the command's phases."""
    with tempfile.TemporaryDirectory(prefix="bench-cli-") as tmp:
        env = warm_env(Path(tmp))
        run_once([*falcon_plan(), *PLAN], env)  # the bytecode cache filled
        _profile(env)


def _profile(env: dict[str, str]) -> None:
    """:func:`profile` in the environment ``env``."""
    argv = [sys.executable, "-X", "importtime", "-m", "falcon_plan.cli", *PLAN]
    done = subprocess.run(argv, capture_output=True, text=True, check=True, env=env)
    own: dict[str, float] = {}
    for line in done.stderr.splitlines():
        m = re.match(r"import time:\s+(\d+) \|\s+\d+ \| (\s*)(\S+)", line)
        if m:
            top = m.group(3).split(".")[0]
            own[top] = own.get(top, 0.0) + int(m.group(1)) / 1e6
    total = sum(own.values())
    print(f"imports: {total:.2f} s in all (self time per top-level package, -X importtime)")
    for name, seconds in sorted(own.items(), key=lambda kv: -kv[1])[:12]:
        print(f"  {name:24s} {seconds:6.3f} s")
    code = ("import time, sys; t = time.perf_counter(); sys.argv = ['falcon-plan', *sys.argv[1:]]\n"
            "marks = {}\n"
            "def timed(name, fn):\n"
            "    def wrapper(*a, **k):\n"
            "        s = time.perf_counter(); r = fn(*a, **k)\n"
            "        marks[name] = marks.get(name, 0.0) + time.perf_counter() - s; return r\n"
            "    return wrapper\n"
            "from falcon_plan import cli\n"
            "from falcon_plan.commands import common\n"
            "cli.build_parser = timed('parser (imports of the commands, argparse)', cli.build_parser)\n"
            "s = time.perf_counter(); import falcon_plan.planning.api as api, falcon_plan.planning.verify as verify\n"
            "import falcon_plan.planning.pipeline as pipeline\n"
            "marks['imports of the planner (numpy, casadi, ruckig, ...)'] = time.perf_counter() - s\n"
            "common.prepare_planner = timed('set-up (prepare_planner, in all)', common.prepare_planner)\n"
            "api.warm_up = timed('  the planner (graphs built, kernels loaded, a small plan)', api.warm_up)\n"
            "api.plan_problem = timed('plan_problem (the plan and its checks, in all)', api.plan_problem)\n"
            "for stage in ('coarse_solve', 'switching_plan', 'transcription_solve', 'dense_check', 'resolve'):\n"
            "    setattr(pipeline, stage, timed('  the plan (kernels loaded, graphs built, solved)', getattr(pipeline, stage)))\n"
            "verify.plant_check = timed('  plant run (plant kernels loaded, run)', verify.plant_check)\n"
            "status = cli.main(sys.argv[1:])\n"
            "marks['whole process until exit'] = time.perf_counter() - t\n"
            "print(marks, file=sys.stderr)\n")
    done = subprocess.run([sys.executable, "-c", code, *PLAN], capture_output=True, text=True, check=True, env=env)
    marks = eval(done.stderr.strip().splitlines()[-1])  # noqa: S307 - our own dict of floats
    setup, planner = "set-up (prepare_planner, in all)", "  the planner (graphs built, kernels loaded, a small plan)"
    controller = "  the plant's controller (LQR linearisation and design, a hold run)"
    marks[controller] = marks[setup] - marks[planner]
    top = sum(seconds for name, seconds in marks.items() if not name.startswith(" ") and not name.startswith("whole"))
    marks["the rest (the report computed and printed)"] = marks["whole process until exit"] - top
    order = ["imports of the planner (numpy, casadi, ruckig, ...)", "parser (imports of the commands, argparse)",
             setup, planner, controller, "plan_problem (the plan and its checks, in all)",
             "  the plan (kernels loaded, graphs built, solved)", "  plant run (plant kernels loaded, run)",
             "the rest (the report computed and printed)", "whole process until exit"]
    print("phases (the interpreter's own start and exit come on top):")
    for name in order:
        print(f"  {name:68s} {marks.get(name, float('nan')):6.3f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=5, help="timed rounds (default 5)")
    parser.add_argument("--cold", action="store_true", help="also time one plan on an empty kernel cache")
    parser.add_argument("--json", type=Path, help="write the figures to this file")
    parser.add_argument("--profile", action="store_true", help="print where one plan's time goes instead")
    args = parser.parse_args()
    if args.profile:
        profile()
        return
    result = measure(args.repeat, args.cold)
    print(f"{'command':78s} {'median':>8s} {'min':>7s} {'/numpy':>7s} {'target':>7s}")
    for label, row in result.items():
        target = f"{row['target_s']:.1f}" if "target_s" in row else ""
        print(f"{label:78s} {row['median_s']:7.3f}s {row['min_s']:6.3f}s {row['over_reference']:7.2f} {target:>7s}")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
