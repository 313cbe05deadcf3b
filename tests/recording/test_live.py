"""The live view: a Foxglove WebSocket client on loopback subscribes and gets the run's rows."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from falcon_plan.approach import run_from_here
from falcon_plan.devices.sim_device import SimDevice
from falcon_plan.falconlog import read_log
from falcon_plan.planning.quintic import quintic_trajectory
from falcon_plan.recording.channels import SCHEMAS, TOPICS
from falcon_plan.recording.live import LiveView

pytest.importorskip("websockets", reason="the test extra (websockets) is needed for the live view test")
from .foxglove_client import SUBPROTOCOLS, Client  # noqa: E402

WATCH = ("/falcon/legs", "/falcon/commands", "/falcon/scene", "/tf", "/falcon/run")

def _wait(condition: Any, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


@pytest.mark.slow
def test_a_client_sees_the_run_live(model: Any, tmp_path: Path) -> None:
    home = np.array([0.0, 0.0, 0.12])
    with LiveView(port=0) as live:
        assert live.url.startswith("ws://127.0.0.1:")
        client = Client(live.url, WATCH)
        try:
            assert client.subscribed.wait(30) and client.error is None, client.error
            assert client.subprotocol in SUBPROTOCOLS
            # every topic is advertised before any run, with its JSON Schema
            assert set(client.advertised) == set(TOPICS)
            for topic, channel in client.advertised.items():
                assert channel["encoding"] == "json" and channel["schemaEncoding"] == "jsonschema"
                assert channel["schemaName"] == TOPICS[topic]
                assert json.loads(channel["schema"]) == SCHEMAS[TOPICS[topic]]
            _wait(lambda: live.watched)
            with SimDevice(model=model, rate_hz=800.0, start_position_m=home) as device:
                device.home()
                move = quintic_trajectory(home, home + [0.02, 0.01, 0.0], model, rate_hz=800.0)
                t0 = time.time_ns()
                report, _ = run_from_here(device, "sim", move, model, rate_hz=800.0, log_path=tmp_path / "run.csv",
                                          live=live, pace=True, preroll_s=0.1, settle_s=0.1)
            assert report.status == "completed"
            log = read_log(tmp_path / "run.csv")
            _wait(lambda: len(client.of("/falcon/run")) == 1)  # the run's report comes last
        finally:
            client.close()
        assert client.error is None, client.error
    legs = client.of("/falcon/legs")
    # every channel at 50 Hz: one row per 1/50 s of the run, its counts those of the log's row
    rows = {t: k for k, t in enumerate(log.t_s.tolist())}
    picked = [rows[body["t_s"]] for _, body in legs]
    assert [body["counts"] for _, body in legs] == log.enc[picked].tolist()
    assert picked[0] == 0 and log.t_s[-1] - log.t_s[picked[-1]] < 0.02
    for a, b in zip(picked[:-1], picked[1:]):  # each the first row at least 1/50 s after the one before
        assert log.t_s[b] >= log.t_s[a] + 0.02 > log.t_s[b - 1] - 1e-12
    assert len(client.of("/falcon/commands")) == len(client.of("/falcon/scene")) == len(legs)
    times = np.array([t for t, _ in legs])
    # wall-clock log times: from the run's start, as far apart as the rows (the run was paced)
    assert t0 <= times[0] <= time.time_ns() and np.all(np.diff(times) > 0)
    np.testing.assert_allclose(np.diff(times) * 1e-9, np.diff(log.t_s[picked]), atol=1e-6)
    scenes = client.of("/falcon/scene")
    assert abs(len(scenes) - 50 * log.t_s[-1]) <= 2  # 50 Hz
    assert {e["id"] for e in scenes[0][1]["entities"]} == {"base", "legs", "end_effector"}
    frames = [body for _, body in client.of("/tf")]
    assert {(f["parent_frame_id"], f["child_frame_id"]) for f in frames} == {
        ("world", "falcon_base"), ("falcon_base", "end_effector"), ("falcon_base", "end_effector_planned")}


def test_without_a_client_the_recorder_does_not_encode(model: Any) -> None:
    from falcon_plan.recording.recorder import RunRecorder

    with LiveView(port=0) as live:
        assert not live.watched
        for watched in (False, True):
            client = Client(live.url, WATCH) if watched else None
            if client is not None:
                assert client.subscribed.wait(30)
                _wait(lambda: live.watched)
            recorder = RunRecorder(None, live)
            recorder.start({"rate_hz": "800"}, model)
            for k in range(100):
                recorder.row(k / 800, np.array([k, 0, 0]), np.zeros(3, int), np.zeros(3))
            recorder.close()
            if client is not None:
                client.close()
            assert recorder.rows == 100 and not recorder.failed
            # 100 rows at 800 Hz span 0.124 s: one row per 1/50 s is encoded for a watching client
            assert recorder.encoded == (7 if watched else 0)


def test_execute_live_says_where_to_connect(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from falcon_plan.cli import main

    assert main(["execute", "--device", "sim", "--planner", "quintic", "--to", "0.02,0,0.13", "--live",
                 "--live-port", "0", "--log", str(tmp_path / "run.mcap")]) == 0
    captured = capsys.readouterr()
    assert "live view at ws://127.0.0.1:" in captured.err and "log: " + str(tmp_path / "run.mcap") in captured.out
    assert len(read_log(tmp_path / "run.mcap")) > 100


def test_serve_takes_the_recording_options(tmp_path: Path) -> None:
    from service.main import build_service, serve_arguments

    folder = tmp_path / "goals"
    service = build_service(serve_arguments(["--device", "none", "--record", str(folder), "--foxglove",
                                             "--foxglove-port", "0"]))
    assert service.options.record_dir == str(folder) and folder.is_dir() and service.options.foxglove_port == 0
    plain = build_service(serve_arguments(["--device", "none"]))
    assert plain.options.record_dir is None and plain.options.foxglove_port is None


@pytest.mark.parametrize("argv", [["serve", "--foxglove", "--foxglove-port", "70000"],
                                  ["execute", "--live", "--live-port", "http"]])
def test_a_bad_live_port_is_refused_in_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    from falcon_plan.cli import main

    with pytest.raises(SystemExit) as exit_code:
        main(argv)
    assert exit_code.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"argument {argv[-2]}: a port is a whole number in 0..65535, got {argv[-1]!r}" in err
