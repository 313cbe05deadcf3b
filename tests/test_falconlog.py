"""The falcon log CSV: round trip, clear errors, atomic and streaming writes."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from falcon_plan.errors import InvalidParameterError, LogFormatError
from falcon_plan.falconlog import (FalconLog, LogWriter, TickTiming, parse_controller, parse_rate_hz,
                                   read_log, write_log)

HEADER = "t,enc0,enc1,enc2,tc0,tc1,tc2"


def _log(n: int = 6, with_ref: bool = True) -> FalconLog:
    rng = np.random.default_rng(3)
    t = np.arange(n) / 800.0
    t[3:] += 2 / 800.0  # a gap (lost packets) is allowed
    enc = rng.integers(-3000, 3000, (n, 3))
    tc = rng.integers(-4096, 4097, (n, 3))
    ref = rng.normal(0.0, 300.0, (n, 3)) if with_ref else None
    return FalconLog(t, enc, tc, ref, {"rate_hz": "800", "controller": "pd kp=10 kd=0.1",
                                       "params": "acra2009"})


@pytest.mark.parametrize("with_ref", [True, False])
def test_round_trip_is_exact(tmp_path: Path, with_ref: bool) -> None:
    log = _log(with_ref=with_ref)
    write_log(tmp_path / "a.csv", log)
    back = read_log(tmp_path / "a.csv")
    assert back == log
    assert back.enc.dtype == np.int64 and back.tc.dtype == np.int64
    assert back.rate_hz == 800.0
    assert back.controller is not None and back.controller.gains == {"kp": 10.0, "kd": 0.1}
    assert (back.ref is None) == (not with_ref)


def _timed(log: FalconLog) -> FalconLog:
    """``log`` with timing columns: sends ~1.25 ms apart with jitter, readings 80-300 us
    before them, the gap of ``_log`` as 2 skipped slots."""
    n = len(log)
    sent = 5_000_000_000 + np.rint(log.t_s * 1e6).astype(np.int64) + np.array([0, 40, 300, 15, 7, 900])[:n]
    read = sent - np.array([80, 300, 120, 95, 90, 100])[:n]
    skipped = np.zeros(n, np.int64)
    skipped[3] = 2
    return FalconLog(log.t_s, log.enc, log.tc, log.ref, log.meta, sent, read, skipped)


@pytest.mark.parametrize("with_ref", [True, False])
def test_timing_columns_round_trip_and_old_logs_still_read(tmp_path: Path, with_ref: bool) -> None:
    """Issue 26 item 1: per tick, when the command was handed to the driver and when its
    reading arrived (monotonic us), and the skipped slots; a log without them reads as before."""
    log = _timed(_log(with_ref=with_ref))
    write_log(tmp_path / "a.csv", log)
    header = [line for line in (tmp_path / "a.csv").read_text().splitlines() if not line.startswith("#")][0]
    assert header.endswith(",sent_us,read_us,skipped") and ("ref0" in header) == with_ref
    back = read_log(tmp_path / "a.csv")
    assert back == log and back.has_timing
    assert back.timing(3) == TickTiming(int(log.sent_us[3]), int(log.read_us[3]), 2)
    assert back.sent_us.dtype == np.int64
    assert back != _log(with_ref=with_ref)  # timing is part of the value
    old = _log(with_ref=with_ref)
    write_log(tmp_path / "old.csv", old)
    assert not read_log(tmp_path / "old.csv").has_timing and read_log(tmp_path / "old.csv").timing(0) is None
    part = back.rows(2, 5)
    assert len(part) == 3 and part.skipped.tolist() == [0, 2, 0] and part.t_s[0] == log.t_s[2]
    assert (part.ref is not None) == with_ref


def test_timing_columns_are_checked(tmp_path: Path) -> None:
    log = _log()
    with pytest.raises(LogFormatError, match="go together"):
        FalconLog(log.t_s, log.enc, log.tc, log.ref, {}, sent_us=np.zeros(len(log)))
    with pytest.raises(LogFormatError, match="skipped must be >= 0"):
        FalconLog(log.t_s, log.enc, log.tc, None, {}, np.zeros(len(log)), np.zeros(len(log)), -np.ones(len(log)))
    (tmp_path / "bad.csv").write_text(HEADER + ",sent_us,read_us,skipped\n0.0,1,2,3,4,5,6,10,9,x\n")
    with pytest.raises(LogFormatError, match=r"bad.csv:2: skipped = 'x' is not an integer"):
        read_log(tmp_path / "bad.csv")
    (tmp_path / "order.csv").write_text(HEADER + ",read_us,sent_us,skipped\n")
    with pytest.raises(LogFormatError, match="bad header"):
        read_log(tmp_path / "order.csv")
    with LogWriter(tmp_path / "w.csv", with_timing=True) as writer:
        with pytest.raises(LogFormatError, match="needs timing columns"):
            writer.write(0.0, [1, 2, 3], [0, 0, 0])
        writer.write(0.0, [1, 2, 3], [0, 0, 0], timing=TickTiming(1000, 900, 0))
    with LogWriter(tmp_path / "v.csv") as writer:
        with pytest.raises(LogFormatError, match="has no timing columns"):
            writer.write(0.0, [1, 2, 3], [0, 0, 0], timing=TickTiming(1000, 900, 0))
    assert read_log(tmp_path / "w.csv").timing(0) == TickTiming(1000, 900, 0)


def test_unknown_metadata_is_kept_but_ignored(tmp_path: Path) -> None:
    path = tmp_path / "m.csv"
    path.write_text(f"# rate_hz: 1000\n# operator: somebody\n#free comment without colon\n{HEADER}\n"
                    "0.0,1,2,3,4,5,6\n0.001,1,2,3,4,5,6\n")
    log = read_log(path)
    assert log.rate_hz == 1000.0 and log.meta["operator"] == "somebody" and len(log) == 2


@pytest.mark.parametrize("body, line, problem", [
    ("t,enc0,enc1,enc2,tc0,tc1\n0,1,2,3,4,5\n", 1, "bad header"),
    (f"{HEADER}\n0,1,2,3,4,5,6\n0.1,1,2,3,4,5\n", 3, "expected 7 columns, got 6"),
    (f"{HEADER}\n0,1,2.5,3,4,5,6\n", 2, "enc1 = '2.5' is not an integer"),
    (f"{HEADER}\n0,1,2,3,4,x,6\n", 2, "tc1 = 'x' is not an integer"),
    (f"{HEADER}\n0,1,2,3,4,5,6\n0,1,2,3,4,5,6\n", 3, "repeated row"),
    (f"{HEADER}\n0.2,1,2,3,4,5,6\n0.1,1,2,3,4,5,6\n", 3, "time not increasing"),
    (f"{HEADER}\nnan,1,2,3,4,5,6\n", 2, "NaN"),
    (f"{HEADER},ref0,ref1,ref2\n0,1,2,3,4,5,6,1.5,nan,2\n", 2, "ref1 is 'nan'"),
    (f"# rate_hz: 800\n{HEADER}\n0,1,2,3,4,5,6\n# late: x\n", 4, "after the header"),
])
def test_errors_name_line_and_problem(tmp_path: Path, body: str, line: int, problem: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(body)
    with pytest.raises(LogFormatError) as info:
        read_log(path)
    assert f"bad.csv:{line}:" in str(info.value)
    assert problem in str(info.value)


def test_missing_header_and_missing_file(tmp_path: Path) -> None:
    (tmp_path / "empty.csv").write_text("# rate_hz: 800\n")
    with pytest.raises(LogFormatError, match="no header"):
        read_log(tmp_path / "empty.csv")
    with pytest.raises(LogFormatError, match="cannot open"):
        read_log(tmp_path / "absent.csv")
    with pytest.raises(ValueError):  # LogFormatError is also a ValueError
        read_log(tmp_path / "absent.csv")


def test_metadata_helpers() -> None:
    spec = parse_controller("pd kp=12.5 kd=0.2")
    assert spec.kind == "pd" and spec.gains == {"kp": 12.5, "kd": 0.2}
    assert str(spec) == "pd kp=12.5 kd=0.2"
    assert parse_rate_hz({}) is None and parse_rate_hz({"rate_hz": "1000"}) == 1000.0
    for bad in ("kp=10", "pd kp", "pd kp=abc", ""):
        with pytest.raises(LogFormatError):
            parse_controller(bad)
    with pytest.raises(LogFormatError, match="rate_hz"):
        parse_rate_hz({"rate_hz": "-5"})


def test_value_type_checks() -> None:
    with pytest.raises(LogFormatError, match="strictly increasing"):
        FalconLog(np.array([0.0, 0.0]), np.zeros((2, 3), int), np.zeros((2, 3), int))
    with pytest.raises(LogFormatError, match="whole numbers"):
        FalconLog(np.array([0.0]), np.full((1, 3), 0.5), np.zeros((1, 3), int))
    with pytest.raises(LogFormatError, match="shape"):
        FalconLog(np.array([0.0]), np.zeros((1, 2), int), np.zeros((1, 3), int))


def test_write_log_is_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "a.csv"
    write_log(path, _log())
    before = path.read_bytes()

    def broken_replace(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError):
        write_log(path, _log(n=3))
    assert path.read_bytes() == before  # the old file is untouched
    assert [p.name for p in tmp_path.iterdir()] == ["a.csv"]  # no temporary left behind


def test_log_writer_streams_and_rejects_repeats(tmp_path: Path) -> None:
    path = tmp_path / "s.csv"
    with LogWriter(path, {"rate_hz": "800"}, with_ref=True) as writer:
        writer.write(0.0, [1, 2, 3], [4, 5, 6], [0.5, 0.5, 0.5])
        assert read_log(path).enc.tolist() == [[1, 2, 3]]  # readable while open
        with pytest.raises(LogFormatError, match="after"):
            writer.write(0.0, [1, 2, 3], [4, 5, 6], [0.5, 0.5, 0.5])
        with pytest.raises(LogFormatError, match="whole numbers"):
            writer.write(0.1, [1.5, 2, 3], [4, 5, 6], [0, 0, 0])
        with pytest.raises(LogFormatError, match="ref"):
            writer.write(0.1, [1, 2, 3], [4, 5, 6])
        writer.write(0.00375, [7, 8, 9], [0, 0, 0], [1.0, 2.0, 3.0])
    log = read_log(path)
    assert len(log) == 2 and log.rate_hz == 800.0 and log.ref is not None


def test_killed_writer_leaves_a_complete_file(tmp_path: Path) -> None:
    """A process killed mid-run (SIGKILL: no cleanup at all) leaves only whole rows."""
    path = tmp_path / "killed.csv"
    script = textwrap.dedent(f"""
        import time
        from falcon_plan.falconlog import LogWriter
        with LogWriter({str(path)!r}, {{"rate_hz": "800"}}, with_ref=False) as w:
            k = 0
            while True:
                w.write(k / 800.0, [k, -k, 2 * k], [k % 4096, 0, -(k % 4096)])
                k += 1
                if k % 50 == 0:
                    time.sleep(0.001)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:
            if path.exists() and path.stat().st_size > 20000:
                break
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    log = read_log(path)  # raises if there were a half row or a repeat
    assert len(log) > 200
    k = np.arange(len(log))
    assert np.array_equal(log.enc[:, 0], k) and np.array_equal(log.t_s, k / 800.0)
    assert path.read_bytes().endswith(b"\n")


def test_a_logs_notes_are_warned_once_per_file_version(tmp_path, caplog) -> None:
    """A command that reads a log twice (calibrate: its figures, then its plot) warns of the
    samples missing once; a new version of the file warns again."""
    import logging

    path = tmp_path / "gappy.csv"
    write_log(path, _log(6))          # two samples missing
    with caplog.at_level(logging.WARNING, logger="falcon_plan.falconlog"):
        read_log(path)
        read_log(path)
        assert sum("missing" in m for m in caplog.messages) == 1, caplog.messages
        time.sleep(0.01)
        write_log(path, _log(6))
        read_log(path)
    assert sum("missing" in m for m in caplog.messages) == 2, caplog.messages


def test_a_writer_that_flushes_every_few_rows_keeps_them_until_then_and_on_close(tmp_path: Path) -> None:
    """With ``flush_rows`` = 4 the rows reach the file four at a time (whole rows only), the
    rest on close; a bad ``flush_rows`` is refused with a line naming it."""
    path = tmp_path / "batched.csv"

    def rows_in_file() -> int:
        return sum(1 for line in path.read_text().splitlines() if line and not line.startswith("#")) - 1

    with LogWriter(path, {"rate_hz": "1000"}, flush_rows=4) as writer:
        for k in range(6):
            writer.write(k / 1000.0, [k, 0, 0], [0, k, 0])
            assert rows_in_file() == 4 * ((k + 1) // 4)
    log = read_log(path)
    assert len(log) == 6 and np.array_equal(log.enc[:, 0], np.arange(6))
    for bad in (0, 2.5, True):
        with pytest.raises(InvalidParameterError, match="flush_rows must be a whole number >= 1"):
            LogWriter(tmp_path / "bad.csv", flush_rows=bad)


def test_the_motion_start_is_the_logged_one_else_the_preroll() -> None:
    """``motion_start_s``: the approach and hold a run logged, else its pre-roll, else 0; a bad
    entry is a LogFormatError naming it."""
    from falcon_plan.falconlog import motion_start_s

    assert motion_start_s({"motion_start_s": "1.25", "preroll_s": "0.5"}) == 1.25
    assert motion_start_s({"preroll_s": "0.5"}) == 0.5
    assert motion_start_s({}) == 0.0
    for bad in ("-1", "nan", "soon"):
        with pytest.raises(LogFormatError, match="motion_start_s / preroll_s"):
            motion_start_s({"preroll_s": bad})


def test_a_runs_log_ends_with_how_the_run_ended(tmp_path: Path) -> None:
    """The writer's end line is read back as the ``end`` metadata; a log without one (older
    logs, a killed process) has none; a row after it, or a second one, is refused."""
    from falcon_plan.falconlog import END_KEY, LogWriter

    path = tmp_path / "run.csv"
    with LogWriter(path, {"rate_hz": "800"}) as writer:
        writer.write(0.0, [1, 2, 3], [4, 5, 6])
        writer.write(0.00125, [1, 2, 4], [4, 5, 6])
        writer.close("cancelled")
    log = read_log(path)
    assert len(log) == 2 and log.meta[END_KEY] == "cancelled" and log.meta["rate_hz"] == "800"
    assert path.read_text().endswith("# end: cancelled\n")
    write_log(tmp_path / "copy.csv", log)           # rewritten whole: the end line stays after the rows
    assert read_log(tmp_path / "copy.csv").meta[END_KEY] == "cancelled"
    assert (tmp_path / "copy.csv").read_text() == path.read_text()
    with LogWriter(tmp_path / "old.csv") as writer:
        writer.write(0.0, [1, 2, 3], [4, 5, 6])
    assert END_KEY not in read_log(tmp_path / "old.csv").meta
    for tail, problem in (("0.0025,1,2,3,4,5,6\n", "row after the end line"),
                          ("# end: completed\n", "once")):
        bad = tmp_path / "bad.csv"
        bad.write_text(path.read_text() + tail)
        with pytest.raises(LogFormatError, match=problem):
            read_log(bad)
