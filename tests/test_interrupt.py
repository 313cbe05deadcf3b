"""Ctrl-C: every long-running command, and ``dev.py``, ends with exit status 130 and one line
(``falcon-plan COMMAND: interrupted``), no traceback, and leaves no process behind.

Each command runs in a real process in its own process group; once it has shown it is
running (its first line of output), SIGINT goes to the whole group, as a terminal's Ctrl-C
does (worker processes get it too).
"""
from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "falcon_plan.cli"]


def _interrupt(argv: list[str], env: dict[str, str], after_s: float = 0.0) -> tuple[int, str]:
    """Run ``argv``, wait for its first line (stdout or stderr) and ``after_s`` [s] more, send
    SIGINT to its process group; its exit status and its whole stderr."""
    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        ready, _, _ = select.select([proc.stdout, proc.stderr], [], [], 180)
        assert ready, f"{argv}: no output within 180 s"
        first = ready[0].readline()
        assert proc.poll() is None, f"{argv} ended before it could be interrupted: {first!r}"
        time.sleep(after_s)
        os.killpg(proc.pid, signal.SIGINT)
        try:
            _out, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:   # say where it hangs: SIGABRT dumps every thread's stack
            os.kill(proc.pid, signal.SIGABRT)
            _out, err = proc.communicate(timeout=30)
            raise AssertionError(f"{argv}: still running 120 s after SIGINT; its threads:\n{err[-8000:]}") from None
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    if ready[0] is proc.stderr:
        err = first + err
    # nothing of the group is left (workers, planning processes, the service's threads)
    deadline = time.monotonic() + 10
    while True:
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, f"{argv}: processes of its group outlived it"
        time.sleep(0.1)
    return proc.returncode, err


def _env(**extra: str) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(ROOT), "FALCON_PLAN_LOG": "WARNING", "PYTHONFAULTHANDLER": "1", **extra}


def _check(code: int, err: str, name: str) -> None:
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    lines = err.strip().splitlines()
    assert lines and lines[-1] == f"falcon-plan {name}: interrupted", err
    assert sum("interrupted" in line for line in lines) == 1, err
    assert code == 130, (code, err)


@pytest.mark.slow
@pytest.mark.parametrize("args, name, after_s", [
    (["experiment", "synth", "--duration", "600", "--out", "{tmp}/s.csv"], "experiment synth", 0.5),
    (["characterise", "--out", "{tmp}/ch", "--samples", "20000000"], "characterise", 0.5),
    (["bench", "problems/", "--jobs", "2", "--out", "{tmp}/bench"], "bench", 3.0),
    (["doctor", "--device", "emulated", "--out", "{tmp}/doctor"], "doctor", 1.0),
    (["demo"], "demo", 0.5),
], ids=["synth", "characterise", "bench-workers", "doctor", "demo"])
def test_ctrl_c_ends_a_command_with_one_line(tmp_path: Path, args: list[str], name: str, after_s: float) -> None:
    code, err = _interrupt([*CLI, *(a.format(tmp=tmp_path) for a in args)], _env(), after_s)
    _check(code, err, name)


@pytest.mark.slow
def test_ctrl_c_ends_dev_py_demo_with_one_line(tmp_path: Path) -> None:
    """``python3 dev.py demo``, with its environment already set up (FALCON_PLAN_VENV: a
    'venv' whose python is this interpreter, stamped as installed)."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    python = venv / "bin" / "python"
    python.write_text(f'#!/bin/sh\nexec {sys.executable} "$@"\n')
    python.chmod(0o755)
    (venv / ".falcon-plan-installed").touch()
    code, err = _interrupt([sys.executable, "dev.py", "demo"], _env(FALCON_PLAN_VENV=str(venv)), 0.5)
    _check(code, err, "demo")
