"""MCAP recordings: a run recorded live equals its falcon log and the converter's file; every
message fits its JSON Schema; the derived values agree with independent computations; the
file is readable after every way the writing process can end."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from falcon_plan.approach import run_from_here
from falcon_plan.execution.executor import LOG_FLUSH_S
from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.errors import LogFormatError
from falcon_plan.falconlog import read_log, write_log
from falcon_plan.model.kinematics import inverse_kinematics
from falcon_plan.model.params import ACRA2009
from falcon_plan.planning.quintic import quintic_trajectory
from falcon_plan.recording.channels import SCHEMAS
from falcon_plan.recording.mcapfile import copy_recording, scan

ROOT = Path(__file__).resolve().parents[2]


# --- a small JSON Schema check (the subset the recording's schemas use) ----------------------

def _check(value: Any, schema: dict[str, Any], where: str = "$") -> None:
    if "oneOf" in schema:
        fits = 0
        for option in schema["oneOf"]:
            try:
                _check(value, option, where)
                fits += 1
            except AssertionError:
                pass
        assert fits == 1, f"{where}: {value!r} fits {fits} of the oneOf options"
        return
    kinds = schema.get("type")
    if kinds is not None:
        kinds = [kinds] if isinstance(kinds, str) else kinds
        python = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None)}
        ok = any((k == "integer" and isinstance(value, int) and not isinstance(value, bool))
                 or (k == "number" and isinstance(value, (int, float)) and not isinstance(value, bool))
                 or (k in python and isinstance(value, python[k])) for k in kinds)
        assert ok, f"{where}: {value!r} is not of type {kinds}"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        assert math.isfinite(value), f"{where}: not finite"
        assert value >= schema.get("minimum", -math.inf) and value <= schema.get("maximum", math.inf), where
    if isinstance(value, dict):
        for name in schema.get("required", []):
            assert name in value, f"{where}: missing {name!r}"
        for name, item in value.items():
            if name in schema.get("properties", {}):
                _check(item, schema["properties"][name], f"{where}.{name}")
            else:
                extra = schema.get("additionalProperties", True)
                assert extra is not False, f"{where}: unexpected {name!r}"
                if isinstance(extra, dict):
                    _check(item, extra, f"{where}.{name}")
    if isinstance(value, list):
        assert schema.get("minItems", 0) <= len(value) <= schema.get("maxItems", math.inf), where
        for k, item in enumerate(value):
            if "items" in schema:
                _check(item, schema["items"], f"{where}[{k}]")


def test_the_schema_check_refuses_what_does_not_fit() -> None:
    schema = SCHEMAS["falcon_plan.Legs"]
    good = {"t_s": 0.0, "counts": [1, 2, 3], "angle_rad": [0.1, 0.2, 0.3], "speed_rad_s": [0.0, 0.0, 0.0]}
    _check(good, schema)
    for bad in ({**good, "counts": [1, 2]}, {**good, "counts": [1.5, 2, 3]}, {k: v for k, v in good.items() if k != "t_s"}):
        with pytest.raises(AssertionError):
            _check(bad, schema)


# --- a recorded run -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A quintic move on the simulated device, logged as CSV and recorded as MCAP in the same run."""
    from falcon_plan.model.dynamics import FalconModel

    model = FalconModel(ACRA2009)
    folder = tmp_path_factory.mktemp("recorded")
    home = np.array([0.0, 0.0, 0.12])
    device = SimDevice(model=model, rate_hz=800.0, start_position_m=home)
    device.open()
    device.home()
    try:
        move = quintic_trajectory(home, home + [0.03, -0.02, 0.01], model, rate_hz=800.0)
        report, _ = run_from_here(device, "sim", move, model, rate_hz=800.0, log_path=folder / "run.csv",
                                  mcap=folder / "run.mcap", pace=False, preroll_s=0.2, settle_s=0.1,
                                  plan_report={"method": "quintic"})
    finally:
        device.close()
    assert report.status == "completed"
    return {"folder": folder, "csv": folder / "run.csv", "mcap": folder / "run.mcap", "report": report}


def _messages(contents: Any, topic: str) -> list[dict[str, Any]]:
    return [json.loads(data) for _, data in contents.topic(topic)]


def test_a_recorded_run_reads_back_as_its_falcon_log(recorded: dict[str, Any]) -> None:
    csv, mcap = read_log(recorded["csv"]), read_log(recorded["mcap"])
    assert len(mcap) == recorded["report"].samples > 300
    assert mcap == csv  # rows and metadata
    contents = scan(recorded["mcap"])
    assert contents.complete
    assert {"versions", "falcon_log", "model", "controller"} <= set(contents.metadata)
    assert contents.metadata["controller"]["controller"] == csv.meta["controller"]
    run = _messages(contents, "/falcon/run")
    assert len(run) == 1 and run[0]["status"] == "completed" and run[0]["samples"] == len(csv)
    plan = _messages(contents, "/falcon/plan")[0]
    assert plan["report"] == {"method": "quintic"} and plan["duration_s"] > 0
    with open(recorded["mcap"], "rb") as handle:  # the mcap package's own (seeking) reader
        summary = make_reader(handle).get_summary()
    assert summary is not None and summary.statistics.channel_message_counts


def test_the_converter_writes_the_same_channels_as_the_live_recording(recorded: dict[str, Any], tmp_path: Path) -> None:
    converted = tmp_path / "converted.mcap"
    write_log(converted, read_log(recorded["csv"]))
    assert read_log(converted) == read_log(recorded["csv"])
    live, conv = scan(recorded["mcap"]), scan(converted)
    for topic in ("/falcon/legs", "/falcon/commands", "/falcon/reference", "/falcon/tracking_error",
                  "/falcon/end_effector", "/falcon/scene", "/tf"):
        a, b = _messages(live, topic), _messages(conv, topic)
        assert len(a) == len(b) > 0, topic
        flat_a = np.array(_numbers(a), dtype=float)
        flat_b = np.array(_numbers(b), dtype=float)
        # positions come from the executor's forward kinematics in one, batch FK in the other
        np.testing.assert_allclose(flat_a, flat_b, atol=1e-7, err_msg=topic)


def _numbers(value: Any) -> list[float]:
    if isinstance(value, dict):
        return [x for k in sorted(value) for x in _numbers(value[k])]
    if isinstance(value, list):
        return [x for v in value for x in _numbers(v)]
    if isinstance(value, bool) or value is None:
        return [float(bool(value))]
    return [float(value)] if isinstance(value, (int, float)) else []


def test_every_message_fits_its_schema(recorded: dict[str, Any]) -> None:
    contents = scan(recorded["mcap"])
    assert set(contents.channels.values()) <= set(SCHEMAS)
    for topic, _, data in contents.messages:
        schema_name = contents.channels[topic]
        assert json.loads(contents.schemas[schema_name][1]) == SCHEMAS[schema_name]
        _check(json.loads(data), SCHEMAS[schema_name], topic)


def test_the_derived_channels_agree_with_independent_computations(recorded: dict[str, Any]) -> None:
    log = read_log(recorded["csv"])
    contents = scan(recorded["mcap"])
    legs = _messages(contents, "/falcon/legs")
    commands = _messages(contents, "/falcon/commands")
    ee = _messages(contents, "/falcon/end_effector")
    tracking = _messages(contents, "/falcon/tracking_error")
    counts_per_rad = 1280 * 7.62 / (2 * math.pi)  # MODEL-CONVENTIONS: 1280 counts x 7.62 per leg turn
    angle = math.radians(40.0) + log.enc / counts_per_rad
    np.testing.assert_allclose([m["angle_rad"] for m in legs], angle, rtol=1e-12)
    speed = np.vstack([np.zeros(3), np.diff(angle, axis=0) / np.diff(log.t_s)[:, None]])
    np.testing.assert_allclose([m["speed_rad_s"] for m in legs], speed, rtol=1e-9, atol=1e-9)
    u = np.minimum(np.abs(speed) / 2.0, 1.0)  # the paper's 2500 at rest, 4096 once past 2 rad/s
    np.testing.assert_allclose([m["device_limit"] for m in commands], 2500 + 1596 * u * u * (3 - 2 * u), rtol=1e-12)
    assert [m["command"] for m in commands] == log.tc.tolist()
    measured = np.array([[m["measured_m"][k] for k in "xyz"] for m in ee])
    planned = np.array([[m["planned_m"][k] for k in "xyz"] for m in ee])
    np.testing.assert_allclose(inverse_kinematics(measured).theta1, angle, atol=1e-9)  # the inverse of FK
    np.testing.assert_allclose(angles_of(log.ref), inverse_kinematics(planned).theta1, atol=1e-9)
    np.testing.assert_allclose([m["counts"] for m in tracking], log.enc - log.ref, atol=1e-9)
    error_mm = np.array([[m["position_mm"][k] for k in "xyz"] for m in tracking])
    np.testing.assert_allclose(error_mm, 1e3 * (measured - planned), atol=1e-9)
    np.testing.assert_allclose([m["norm_mm"] for m in tracking], np.linalg.norm(error_mm, axis=1), atol=1e-9)
    # the report's Cartesian tracking error (over the motion, the executor's own figure) is this one
    assert max(m["norm_mm"] for m in tracking) >= recorded["report"].tracking.norm_max_mm - 1e-9
    # 3D: the end-effector frame sits at the measured position; each leg is pivot -> knee (length a) -> effector
    frames = [m for m in _messages(contents, "/tf") if m["child_frame_id"] == "end_effector"]
    scenes = _messages(contents, "/falcon/scene")
    assert len(frames) == len(scenes) and abs(len(scenes) - log.t_s[-1] * 50) <= 2
    row = {round(t, 9): k for k, t in enumerate(log.t_s)}
    for frame, scene in zip(frames, scenes):
        k = row[round(frame["timestamp"]["sec"] + frame["timestamp"]["nsec"] * 1e-9, 9)]
        np.testing.assert_allclose([frame["translation"][c] for c in "xyz"], measured[k], atol=1e-12)
        legs_line = next(e for e in scene["entities"] if e["id"] == "legs")["lines"][0]["points"]
        points = np.array([[p[c] for c in "xyz"] for p in legs_line]).reshape(3, 4, 3)
        np.testing.assert_allclose(np.linalg.norm(points[:, 1] - points[:, 0], axis=1), ACRA2009.a_m, rtol=1e-12)
        np.testing.assert_allclose(points[:, 3], np.tile(measured[k], (3, 1)), atol=1e-12)


def angles_of(counts: np.ndarray) -> np.ndarray:
    """theta1 [rad] of counts, written out from MODEL-CONVENTIONS."""
    return math.radians(40.0) + np.asarray(counts) * 2 * math.pi / (1280 * 7.62)


def test_a_file_that_is_not_a_recording_is_refused_in_one_line(tmp_path: Path) -> None:
    other = tmp_path / "other.mcap"
    from falcon_plan.recording.mcapfile import McapRecording

    with McapRecording(other) as recording:
        recording.write("/falcon/goal", 0.0, b'{"goal_id":"g","event":"x"}')
    with pytest.raises(LogFormatError, match="no /falcon/legs and /falcon/commands channels"):
        read_log(other)
    text = tmp_path / "text.mcap"
    text.write_text("t,enc0,enc1,enc2\n")
    with pytest.raises(LogFormatError, match="not an MCAP file"):
        read_log(text)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(LogFormatError, match="empty, or cut short before its first bytes"):
        read_log(empty)


# --- every way the writer can end -------------------------------------------------------------

_RUN = """
import sys
import numpy as np
from falcon_plan.approach import run_from_here
from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.execution import executor
from falcon_plan.execution.safety import SafetyConfig
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.quintic import quintic_trajectory

csv, mcap, kind = sys.argv[1:4]

# a bug in the loop itself at row 700 (a device's failure would be a reported device error)
record = executor._Run._record
def broken_record(self, *args):
    if kind == "exception" and self.rows == 700:
        raise RuntimeError("a bug in the middle of a run")
    return record(self, *args)
executor._Run._record = broken_record
Broken = SimDevice

model = FalconModel()
home = np.array([0.0, 0.0, 0.12])
try:
    with Broken(model=model, rate_hz=800.0, start_position_m=home) as device:
        device.home()
        move = quintic_trajectory(home, home + [0.01, 0.0, 0.01], model, rate_hz=800.0)
        # paced at 800 Hz, holding the start long enough to be interrupted; the watchdog allows
        # the stalls of a crowded test machine (the device's own 100 ms hold still applies)
        run_from_here(device, "sim", move, model, rate_hz=800.0, log_path=csv, mcap=mcap, pace=kind != "exception",
                      preroll_s=30.0, safety=SafetyConfig(watchdog_timeout_s=0.09))
except KeyboardInterrupt:  # as the command line does
    sys.exit(130)
"""


def _start(kind: str, folder: Path) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    argv = [sys.executable, "-c", _RUN, str(folder / "run.csv"), str(folder / "run.mcap"), kind]
    return subprocess.Popen(argv, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # its own process group: "sigkill-all" kills it whole


def _rows(path: Path) -> int:
    """Rows in the recording being written at ``path`` (0 before it has its first bytes)."""
    try:
        return sum(1 for topic, _, _ in scan(path).messages if topic == "/falcon/legs")
    except LogFormatError:  # not there yet, or not yet holding the magic bytes
        return 0


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def _running(pid: int) -> bool:
    """True while process ``pid`` exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["exception", "sigint", "sigterm", "sigterm-all", "sigkill", "sigkill-all"])
def test_the_recording_is_readable_however_the_writer_ends(kind: str, tmp_path: Path) -> None:
    """The recording process finishes the file on every end of the run's process, SIGKILL
    included, and when both are stopped with SIGTERM; killed together with it (the whole process
    group), the file reads up to its last chunk. The recording process never outlives the
    run's."""
    proc = _start(kind, tmp_path)
    mcap, csv = tmp_path / "run.mcap", tmp_path / "run.csv"
    workers: list[int] = []
    try:
        if kind != "exception":
            deadline = time.monotonic() + 120
            while _rows(mcap) < 450 and proc.poll() is None:  # a chunk (0.5 s, 400 rows) on disk
                assert time.monotonic() < deadline, "the run did not start recording"
                time.sleep(0.2)
            assert proc.poll() is None, proc.communicate()
            workers = _children(proc.pid)
            assert len(workers) == 1, workers  # the recording process
            if kind.endswith("-all"):
                os.killpg(proc.pid, signal.SIGKILL if kind == "sigkill-all" else signal.SIGTERM)
            else:
                proc.send_signal({"sigint": signal.SIGINT, "sigterm": signal.SIGTERM, "sigkill": signal.SIGKILL}[kind])
        _, err = proc.communicate(timeout=120)  # the recording process holds the pipes too: it has exited
        deadline = time.monotonic() + 30
        while any(_running(pid) for pid in workers):
            assert time.monotonic() < deadline, "the recording process outlived the run"
            time.sleep(0.05)
    finally:
        proc.kill()
    expected_code = {"exception": 1, "sigint": 130, "sigterm": 143, "sigterm-all": 143}.get(kind, -signal.SIGKILL)
    assert proc.returncode == expected_code, err
    assert "recording process" not in err, err  # never lost, never an error of its own
    if kind == "exception":
        assert "a bug in the middle of a run" in err
    logged, recorded = read_log(csv), read_log(mcap)
    contents = scan(mcap)
    if not kind.startswith("sigkill"):   # unwound: the log says the run was cut short
        assert logged.meta["end"] == "interrupted"
    # the CSV goes to the OS every LOG_FLUSH_S of rows: a killed run's lacks the rows since
    lost = int(round(LOG_FLUSH_S * 800)) if kind.startswith("sigkill") else 0
    if kind == "sigkill-all":
        assert not contents.complete
        # at most the chunk in progress (0.5 s at 800 Hz) and the rows not yet taken from the ring are lost
        assert len(logged) - 0.6 * 800 <= len(recorded) <= len(logged) + lost
        n = min(len(recorded), len(logged))
        for name in ("t_s", "enc", "tc", "ref"):
            np.testing.assert_array_equal(getattr(recorded, name)[:n], getattr(logged, name)[:n], err_msg=name)
        fixed = tmp_path / "fixed.mcap"
        copy_recording(mcap, fixed)
        assert scan(fixed).complete and read_log(fixed) == recorded
        mcap = fixed
    else:
        assert contents.complete
        if kind == "exception":  # an unpaced run: no per-tick timing columns
            assert recorded == logged and not recorded.has_timing
        else:  # a paced run, with its timing columns; the signal may land between the CSV row and
            # the recorder's hand-off, so the recording may lack the log's last row
            assert recorded.has_timing and "/falcon/timing" in contents.channels
            assert len(logged) - 1 <= len(recorded) <= len(logged) + lost and recorded.meta == logged.meta
            n = min(len(recorded), len(logged))
            for name in ("t_s", "enc", "tc", "ref", "sent_us", "read_us", "skipped"):
                np.testing.assert_array_equal(getattr(recorded, name)[:n], getattr(logged, name)[:n])
        assert len(recorded) >= 450
    with open(mcap, "rb") as handle:  # the mcap package's seeking reader needs the footer and summary
        reader = make_reader(handle)
        counts = reader.get_summary().statistics.channel_message_counts
        assert sum(1 for _ in reader.iter_messages(topics=["/falcon/legs"])) == len(recorded)
    assert counts


def test_convert_goes_both_ways_and_refuses_other_names(recorded: dict[str, Any], tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    from falcon_plan.cli import main

    assert main(["convert", str(recorded["csv"]), "--out", str(tmp_path / "a.mcap")]) == 0
    assert main(["convert", str(tmp_path / "a.mcap"), "--out", str(tmp_path / "b.csv")]) == 0
    assert read_log(tmp_path / "b.csv") == read_log(recorded["csv"])
    assert main(["convert", str(recorded["mcap"]), "--out", str(tmp_path / "c.mcap")]) == 0  # every channel kept
    assert scan(tmp_path / "c.mcap").channels == scan(recorded["mcap"]).channels
    capsys.readouterr()
    assert main(["convert", str(recorded["csv"]), "--out", str(tmp_path / "d.txt")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "must end in .csv (falcon log) or .mcap" in err
    assert not (tmp_path / "d.txt").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.csv",
                                                                                               "c.mcap"]


def test_the_converter_keeps_the_per_tick_timing_columns(tmp_path: Path) -> None:
    from falcon_plan.falconlog import FalconLog

    n = 40
    t = np.arange(n) / 1000.0
    t[20:] += 0.002  # two skipped slots before row 20
    skipped = np.zeros(n, dtype=int)
    skipped[20] = 2
    sent = (1_000_000 + 1e6 * t).astype(int)
    log = FalconLog(t, [[k, -k, 2 * k] for k in range(n)], [[10, -10, 0]] * n, [[k + 0.5, -k, 2 * k] for k in range(n)],
                    {"rate_hz": "1000", "controller": "pd kp=10 kd=0.1"}, sent_us=sent, read_us=sent - 300,
                    skipped=skipped)
    write_log(tmp_path / "timed.mcap", log)
    back = read_log(tmp_path / "timed.mcap")
    assert back == log and back.has_timing
    timing = _messages(scan(tmp_path / "timed.mcap"), "/falcon/timing")
    assert [m["skipped"] for m in timing] == skipped.tolist() and timing[20]["t_s"] == t[20]


def test_convert_refuses_a_log_without_rows_and_a_recording_cut_before_its_channels(
        recorded: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from falcon_plan.cli import main

    lines = Path(recorded["csv"]).read_text().splitlines(keepends=True)
    first_row = next(k for k, line in enumerate(lines) if line[:1].isdigit() or line[:1] == "-")
    header_only = tmp_path / "empty.csv"
    header_only.write_text("".join(lines[:first_row]))
    capsys.readouterr()
    assert main(["convert", str(header_only), "--out", str(tmp_path / "empty.mcap")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "has a header and no rows" in err
    assert not (tmp_path / "empty.mcap").exists()
    stub = tmp_path / "stub.mcap"
    stub.write_bytes(Path(recorded["mcap"]).read_bytes()[:100])
    assert main(["convert", str(stub), "--out", str(tmp_path / "stub.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "cut short before its first channel" in err
    assert not (tmp_path / "stub.csv").exists()
    assert main(["convert", str(stub), "--out", str(tmp_path / "stub2.mcap")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "cut short before its first channel" in err
    assert not (tmp_path / "stub2.mcap").exists()
