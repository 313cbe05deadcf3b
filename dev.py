#!/usr/bin/env python3
"""Set up falcon-plan in a local virtual environment and run its main job or its tests.

Needs only Python 3.11+ (standard library). Usage:

    python3 dev.py demo     # set up, start the Zenoh service (peer mode, simulated device)
                            # and send it one plan-and-execute goal end to end
    python3 dev.py test     # set up, then run the whole test suite with pytest

Extra arguments after the command go to the program (``demo``) or to pytest (``test``).
The environment lives in ``.venv/`` beside this file; set FALCON_PLAN_VENV to move it.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = Path(os.environ.get("FALCON_PLAN_VENV", ROOT / ".venv"))
STAMP = VENV / ".falcon-plan-installed"


def _python() -> Path:
    sub = "Scripts" if os.name == "nt" else "bin"
    return VENV / sub / ("python.exe" if os.name == "nt" else "python")


def setup() -> Path:
    """Create the virtual environment, install the project (editable) with its test extra, and
    build the compiled kernels (:mod:`falcon_plan.compiled.prepare`)."""
    if sys.version_info < (3, 11):
        sys.exit(f"falcon-plan needs Python 3.11 or newer; this is {sys.version.split()[0]}")
    py = _python()
    pyproject = ROOT / "pyproject.toml"
    if not py.exists():
        print(f"[dev] creating virtual environment in {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    if not STAMP.exists() or STAMP.stat().st_mtime < pyproject.stat().st_mtime:
        print("[dev] installing falcon-plan and its dependencies", flush=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", "--upgrade", "pip"], check=True)
        subprocess.run([str(py), "-m", "pip", "install", "-q", "-e", f"{ROOT}[test]"], check=True)
        STAMP.touch()
        # the compiled kernels (minutes on a fresh machine, seconds once cached): built with the
        # installation, side by side, rather than inside the first plan, test or service that
        # needs them (whatever is missing later is compiled on first use)
        subprocess.run([str(py), "-m", "falcon_plan.compiled.prepare"], cwd=ROOT, check=False)
    return py


INTERRUPTED = 130
"""Exit status after Ctrl-C (128 + SIGINT), as the falcon-plan commands use."""


def run(argv: list[str]) -> int:
    """Run ``argv`` in ROOT and return its exit status. Ctrl-C reaches the child too (the
    same process group) and the child reports it in its own line; this waits for it, and
    passes the interrupt on only if the child has not ended within a few seconds (an
    interrupt sent to this process alone)."""
    child = subprocess.Popen(argv, cwd=ROOT)
    while True:
        try:
            return child.wait()
        except KeyboardInterrupt:
            try:
                return child.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                child.send_signal(signal.SIGINT)
            except KeyboardInterrupt:
                continue


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in {"demo", "test", "setup"}:
        print(__doc__)
        return 2
    try:
        py = setup()
    except KeyboardInterrupt:
        print("[dev] interrupted (run it again to finish the set-up)", file=sys.stderr)
        return INTERRUPTED
    except subprocess.CalledProcessError as exc:
        print(f"[dev] error: {' '.join(map(str, exc.cmd))} failed with status {exc.returncode}", file=sys.stderr)
        return exc.returncode if exc.returncode > 0 else INTERRUPTED
    command, rest = argv[0], argv[1:]
    if command == "setup":
        return 0
    if command == "demo":
        return run([str(py), "-m", "falcon_plan.cli", "demo", *rest])
    return run([str(py), "-m", "pytest", *rest])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
