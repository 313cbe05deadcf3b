"""The quick examples run as written and write only into the folder they are given (never
into the working folder); the slower ones are exercised by their modules' tests."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.mark.parametrize("name, expected, outputs", [
    ("01_kinematics_and_dynamics.py", "commands that hold the device still", []),
    ("03_execute_on_the_simulated_plant.py", "status: completed", ["03_run.csv", "03_run.png"]),
])
def test_example_runs(name: str, expected: str, outputs: list[str], tmp_path: Path) -> None:
    cwd, out = tmp_path / "cwd", tmp_path / "out"
    cwd.mkdir()
    args = [] if not outputs else ["--out", str(out)]
    done = subprocess.run([sys.executable, str(EXAMPLES / name), *args], cwd=cwd, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert expected in done.stdout
    assert list(cwd.iterdir()) == []  # nothing left in the working folder
    assert sorted(p.name for p in out.iterdir()) == sorted(outputs) if outputs else not out.exists()
