"""``serve --record DIR --foxglove``: every goal is recorded as an MCAP file and shown live."""
from __future__ import annotations

import importlib.util
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from falcon_plan.falconlog import read_log
from falcon_plan.recording.mcapfile import scan
from service.options import ServiceOptions
from service.testing import GOAL_A_M, HOME_M, client_for, running_service

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


@pytest.mark.slow
def test_a_goal_spliced_into_a_recorded_execution_is_in_its_recording(model: Any, tmp_path: Path) -> None:
    """A preempting goal spliced into the running motion continues that goal's recording (the
    same run, the same file): the preempted goal's end, the new goal's start and its plan (a
    second /falcon/plan and path, at the splice's time in the run's clock) are recorded."""
    options = ServiceOptions(record_dir=str(tmp_path))
    second_goal = np.array(HOME_M) + [0.01, -0.01, 0.0]
    with running_service("rec2", "sim", model, options=options) as service, client_for(service, "rec2") as c:
        assert c.wait_result(c.submit_goal(list(HOME_M), goal_id="rec-home")["id"], timeout_s=60)["status"] == "done"
        in_motion = threading.Event()

        def on_progress(body: dict[str, Any]) -> None:  # past the pre-roll (0.5 s, 400 samples): in motion
            if body["phase"] == "executing" and body.get("detail", {}).get("samples_done", 0) > 400:
                in_motion.set()

        results: dict[str, Any] = {}
        c.submit_goal([0.03, -0.02, 0.135], goal_id="rec-1", via_m=[(0.03, 0.025, 0.125), (-0.03, 0.02, 0.135)],
                      options={"tc_max": 1200})
        waiter = threading.Thread(target=lambda: results.update(one=c.wait_result("rec-1", timeout_s=60,
                                                                                   on_progress=on_progress)))
        waiter.start()
        assert in_motion.wait(60), "the first goal never moved"
        c.submit_goal(list(second_goal), goal_id="rec-2", preempt=True)
        second = c.wait_result("rec-2", timeout_s=60)
        waiter.join(60)
        one = results["one"]
    assert one["status"] == "preempted" and second["status"] == "done", (one["status"], second.get("error"))
    path = tmp_path / "rec-1.mcap"
    contents = scan(path)
    assert contents.complete and not (tmp_path / "rec-2.mcap").exists()
    events = [(ns, json.loads(data)) for ns, data in contents.topic("/falcon/goal")]
    assert [(e["goal_id"], e["event"], e.get("status")) for _, e in events] == [
        ("rec-1", "started", "running"), ("rec-1", "planned", "running"), ("rec-1", "finished", "preempted"),
        ("rec-2", "started", "running"), ("rec-2", "planned", "running"), ("rec-2", "finished", "done")]
    (splice,) = [s for s in second["splices"] if s.get("goal") == "rec-2" and s["taken"]]
    log = read_log(path)
    rate = float(log.meta["rate_hz"])
    preempted_ns = events[2][0]
    assert events[2][1]["detail"]["preempted_by"] == "rec-2" and events[3][1]["detail"]["spliced_at_tick"] == splice["tick"]
    plans = [(ns, json.loads(data)) for ns, data in contents.topic("/falcon/plan")]
    paths = [json.loads(data) for _, data in contents.topic("/falcon/plan/path")]
    assert len(plans) == len(paths) == 2
    # in the run's clock, in order: the splice once the loop took it at its tick (the row of the
    # tick before it may be the last one written), the new plan after it, all within the run
    times = [ns * 1e-9 for ns, _ in events]
    assert times == sorted(times) and times[2] <= plans[1][0] * 1e-9 <= log.t_s[-1]
    assert (splice["tick"] - 1) / rate - 1e-9 <= preempted_ns * 1e-9
    assert plans[1][1]["report"]["goal_id"] == "rec-2" and plans[1][1]["report"]["tick"] == splice["tick"]
    end = paths[1]["poses"][-1]["position"]
    np.testing.assert_allclose([end[k] for k in "xyz"], second_goal, atol=1e-4)
    assert len(log) == second["tracking_report"]["samples"]  # one run: both goals' rows


def test_a_goal_id_recorded_by_an_earlier_run_is_refused(model: Any, tmp_path: Path) -> None:
    """A restarted service forgets the goal ids it served, but its recordings stay: a goal
    reusing the id of one is refused (it used to replace that recording silently, the only
    record of a run cut short by a crash), and the recording is kept as it was."""
    from service.client import ServiceError

    earlier = tmp_path / "killme.mcap"
    earlier.write_bytes(b"an earlier run's recording")
    options = ServiceOptions(record_dir=str(tmp_path))
    with running_service("rec2", "sim", model, options=options) as service, client_for(service, "rec2") as c:
        with pytest.raises(ServiceError) as err:
            c.submit_goal(GOAL_A_M, goal_id="killme")
        assert err.value.code == "duplicate_goal_id" and "killme.mcap exists" in str(err.value)
        assert c.wait_result(c.submit_goal(GOAL_A_M, goal_id="fresh")["id"], timeout_s=60)["status"] == "done"
    assert earlier.read_bytes() == b"an earlier run's recording"
