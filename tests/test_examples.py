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
    ("06_follow_a_moving_target.py", "plans spliced in", ["06_moving_target.png"]),
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


@pytest.mark.slow
def test_example_05_takes_out_and_names_every_true_value(tmp_path: Path) -> None:
    cwd, out = tmp_path / "cwd", tmp_path / "out"
    cwd.mkdir()
    done = subprocess.run([sys.executable, str(EXAMPLES / "05_identify_from_executor_logs.py"), "none",
                           "--out", str(out)], cwd=cwd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "| none | none |" in done.stdout and "nan" not in done.stdout
    assert "identifying" in done.stderr  # progress while it works
    assert list(cwd.iterdir()) == []
    assert sorted(p.name for p in out.iterdir()) == ["05_none_heldout.csv", "05_none_train.csv", "05_table.md"]
    bad = subprocess.run([sys.executable, str(EXAMPLES / "05_identify_from_executor_logs.py"), "nosuch"],
                         cwd=cwd, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "unknown case(s) nosuch" in bad.stderr and "Traceback" not in bad.stderr


def test_example_05_gives_the_hidden_value_of_every_fitted_field() -> None:
    """A fitted field the case did not set has the nominal value as its truth (not nan)."""
    import importlib.util
    from types import SimpleNamespace

    from falcon_plan.model.effects import Effects

    spec = importlib.util.spec_from_file_location("example05", EXAMPLES / "05_identify_from_executor_logs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    fitted = {"coulomb_leg0_Nm": SimpleNamespace(value=0.0021), "coulomb_leg1_Nm": SimpleNamespace(value=0.0079)}
    text = module.fitted_vs_true(fitted, Effects(coulomb_leg1_Nm=0.008))
    assert text == "coulomb_leg0_Nm 0.0021 (true 0), coulomb_leg1_Nm 0.0079 (true 0.008)"
