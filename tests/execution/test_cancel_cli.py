"""Ctrl-C (and SIGTERM, SIGHUP) during ``falcon-plan execute`` is a cancel: the simulated device
brakes to rest and is held (the run's report has the brake); with ``--release`` it is let go at
once."""
from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _execute_and_interrupt(extra: list[str], signum: int = signal.SIGINT) -> tuple[int, dict, str]:
    argv = [sys.executable, "-m", "falcon_plan.cli", "execute", "--device", "sim", "--to", "0.02,-0.01,0.12",
            "--planner", "quintic", "--realtime", "--preroll", "2.0", "--json", *extra]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FALCON_PLAN_LOG": "WARNING", "PYTHONFAULTHANDLER": "1"}
    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        # wait for the run to begin (the progress line), then Ctrl-C the process group
        while True:
            ready, _, _ = select.select([proc.stderr], [], [], 120)
            assert ready, "execute printed nothing within 120 s"
            line = proc.stderr.readline()
            assert line, f"execute ended early: {proc.communicate()}"
            if "executing on the sim device" in line:
                break
        os.killpg(proc.pid, signum)
        try:
            out, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:   # say where it hangs: SIGABRT dumps every thread's stack
            os.kill(proc.pid, signal.SIGABRT)
            _, err = proc.communicate(timeout=30)
            raise AssertionError(f"still running 60 s after {signal.Signals(signum).name}; its threads:\n"
                                 f"{err[-8000:]}") from None
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    return proc.returncode, json.loads(out), err


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["SIGINT", "SIGTERM", "SIGHUP"])
@pytest.mark.parametrize("release", [False, True])
def test_ctrl_c_in_execute_is_a_cancel(release: bool, signum: int, tmp_path: Path) -> None:
    """Ctrl-C, a termination request and a closed terminal (SIGHUP: before, the process died
    with the device still driven) all cancel the run: it brakes (or, with --release, lets go),
    and the process ends with 128 + the signal; its log ends saying the run was cancelled."""
    from falcon_plan.falconlog import END_KEY, read_log

    log = tmp_path / "run.csv"
    code, doc, err = _execute_and_interrupt(["--log", str(log), *(["--release"] if release else [])], signum)
    run = doc["execution"]
    assert code == 128 + signum and run["status"] == "cancelled", (code, run, err)
    assert read_log(log).meta[END_KEY] == "cancelled" and len(read_log(log)) == run["samples"]
    assert "Traceback" not in err
    if release:
        assert run["brake"] is None and run["samples"] < run["planned_samples"]
        assert "releasing the grip at once" in err and "braking" not in err, err
    else:
        # cancelled early in the run (the approach from the homed device, or the pre-roll):
        # braked within the bound, held, then the run ended
        assert run["brake"] is not None and run["brake"]["peak_feedforward"] <= 2350
        assert "braking to rest" in err
        assert run["samples"] + run["skipped_slots"] >= run["planned_samples"], run


def test_a_signal_after_the_run_ends_the_command_with_one_line(tmp_path: Path) -> None:
    """SIGTERM once the run is over (its log ends ``completed``; the plot is being drawn): the
    device was closed with zero force; the command ends with 143 and says so in one line (it
    used to end silently)."""
    from falcon_plan.falconlog import END_KEY, read_log

    log = tmp_path / "run.csv"
    argv = [sys.executable, "-m", "falcon_plan.cli", "execute", "--device", "sim", "--to", "0.02,-0.01,0.12",
            "--planner", "quintic", "--log", str(log), "--plot", str(tmp_path / "run.png")]   # (a second or more)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FALCON_PLAN_LOG": "WARNING"}
    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not (log.exists() and log.read_text().rstrip().endswith("# end: completed")):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == "falcon-plan execute: terminated by SIGTERM", err
    assert "Traceback" not in err and read_log(log).meta[END_KEY] == "completed"
