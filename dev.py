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
    """Create the virtual environment and install the project (editable) with its test extra."""
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
    return py


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in {"demo", "test", "setup"}:
        print(__doc__)
        return 2
    py = setup()
    command, rest = argv[0], argv[1:]
    if command == "setup":
        return 0
    if command == "demo":
        return subprocess.call([str(py), "-m", "falcon_plan.cli", "demo", *rest], cwd=ROOT)
    return subprocess.call([str(py), "-m", "pytest", *rest], cwd=ROOT)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
