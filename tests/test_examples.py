"""The quick examples run as written (the slower ones are exercised by their modules' tests)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.mark.parametrize("name, expected", [
    ("01_kinematics_and_dynamics.py", "commands that hold the device still"),
    ("03_execute_on_the_simulated_plant.py", "status: completed"),
])
def test_example_runs(name: str, expected: str, tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(EXAMPLES / name)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert expected in done.stdout
