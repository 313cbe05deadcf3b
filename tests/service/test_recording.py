"""``serve --record DIR --foxglove``: every goal is recorded as an MCAP file and shown live."""
from __future__ import annotations

import importlib.util
import json
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from falcon_plan.falconlog import read_log
from falcon_plan.recording.mcapfile import scan
from service.options import ServiceOptions
from service.testing import GOAL_A_M, client_for, running_service

pytest.importorskip("websockets", reason="the test extra (websockets) is needed for the live view test")


def _client_module() -> Any:
    """tests/recording/foxglove_client.py, loaded by path (the Foxglove WebSocket test client)."""
    spec = importlib.util.spec_from_file_location(
        "falcon_foxglove_client", Path(__file__).resolve().parents[1] / "recording" / "foxglove_client.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


Client = _client_module().Client


@pytest.mark.slow
def test_goals_are_recorded_and_shown_live(model: Any, tmp_path: Path) -> None:
    options = ServiceOptions(record_dir=str(tmp_path), foxglove_port=0)
    with running_service("rec0", "sim", model, options=options) as service:
        assert service.live is not None and service.live.url.startswith("ws://127.0.0.1:")
        viewer = Client(service.live.url, ("/falcon/goal", "/falcon/legs", "/falcon/plan/path"))
        try:
            assert viewer.subscribed.wait(30) and viewer.error is None, viewer.error
            deadline = time.monotonic() + 30
            while not service.live.watched:
                assert time.monotonic() < deadline
                time.sleep(0.02)
            with client_for(service, "rec0") as c:
                ack = c.submit_goal(GOAL_A_M)
                result = c.wait_result(ack["id"], timeout_s=60)
            assert result["status"] == "done", result["error"]
            path = tmp_path / f"{ack['id']}.mcap"
            deadline = time.monotonic() + 30
            while not (path.exists() and scan(path).complete):  # the worker closes it after the result
                assert time.monotonic() < deadline, "the goal's recording was not finished"
                time.sleep(0.05)
            log = read_log(path)
            deadline = time.monotonic() + 30
            while len(viewer.of("/falcon/goal")) < 3:
                assert time.monotonic() < deadline, "the live view did not get the goal"
                time.sleep(0.05)
        finally:
            viewer.close()
    assert len(log) == result["tracking_report"]["samples"]
    contents = scan(path)
    events = [json.loads(data) for _, data in contents.topic("/falcon/goal")]
    assert [e["event"] for e in events] == ["started", "planned", "finished"]
    assert {e["goal_id"] for e in events} == {ack["id"]} and events[-1]["status"] == "done"
    plan = json.loads(next(contents.topic("/falcon/plan"))[1])
    assert plan["report"]["status"] == result["plan_report"]["status"]
    assert contents.metadata["service"] == {"instance": "falcontest/rec0", "goal_id": ack["id"]}
    live_events = [body["event"] for _, body in viewer.of("/falcon/goal")]
    assert live_events == ["started", "planned", "finished"]
    rows = {t: k for k, t in enumerate(log.t_s.tolist())}
    live_legs = viewer.of("/falcon/legs")  # at 50 Hz, each the log's row at its time
    assert abs(len(live_legs) - 50 * log.t_s[-1]) <= 2
    assert [body["counts"] for _, body in live_legs] == log.enc[[rows[b["t_s"]] for _, b in live_legs]].tolist()
    assert len(viewer.of("/falcon/plan/path")) == 1


@pytest.mark.slow
def test_sigterm_to_serve_finishes_the_running_goals_recording(tmp_path: Path) -> None:
    import os
    import signal
    import subprocess

    from service.client import FalconClient, wait_for_instance
    from service.config import SessionSettings
    from service.testing import endpoint

    ep, prefix = endpoint(), "falconrec"
    env = {**os.environ, "FALCON_PLAN_LOG": "WARNING", "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    server = subprocess.Popen([sys.executable, "-m", "falcon_plan.cli", "serve", "--device", "sim", "--instance", "rec1",
                               "--prefix", prefix, "--listen", ep, "--record", str(tmp_path), "--foxglove",
                               "--foxglove-port", "0", "--planning-workers", "1"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        with FalconClient(SessionSettings.client([ep]), prefix=prefix, instance="rec1") as client:
            wait_for_instance(client, "rec1", timeout_s=60)
            ack = client.submit_goal((0.03, -0.02, 0.12))
            path = tmp_path / f"{ack['id']}.mcap"
            deadline = time.monotonic() + 60
            while not path.exists():  # the recording opens when the goal starts, before it is planned
                assert time.monotonic() < deadline and server.poll() is None, "the goal did not start"
                time.sleep(0.01)
            server.send_signal(signal.SIGTERM)
            stdout, stderr = server.communicate(timeout=30)
        assert server.returncode == 0, stderr
        assert "live view at ws://127.0.0.1:" in stdout
    finally:
        if server.poll() is None:
            server.kill()
            server.communicate()
    contents = scan(path)
    assert contents.complete  # summary and footer written on the way out
    events = [json.loads(data) for _, data in contents.topic("/falcon/goal")]
    assert events[0]["event"] == "started" and events[-1]["event"] == "finished"
    assert events[-1]["status"] in ("cancelled", "done")
