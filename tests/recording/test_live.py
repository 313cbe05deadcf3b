"""The live view: a Foxglove WebSocket client on loopback subscribes and gets the run's rows."""
from __future__ import annotations

import asyncio
import json
import struct
import threading
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

websockets = pytest.importorskip("websockets", reason="the test extra (websockets) is needed for the live view test")

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # what the Foxglove app offers
WATCH = ("/falcon/legs", "/falcon/scene", "/tf")


class Client:
    """A Foxglove WebSocket client in a thread: reads the advertisements, subscribes to
    ``topics`` and keeps every message (topic, log time [ns], JSON body)."""

    def __init__(self, url: str, topics: tuple[str, ...]) -> None:
        self.url, self.topics = url, topics
        self.server_info: dict[str, Any] = {}
        self.advertised: dict[str, dict[str, Any]] = {}
        self.messages: list[tuple[str, int, Any]] = []
        self.subprotocol: str | None = None
        self.subscribed = threading.Event()
        self.stop = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            self.error = exc
            self.subscribed.set()

    async def _main(self) -> None:
        async with websockets.connect(self.url, subprotocols=SUBPROTOCOLS, max_size=None) as ws:
            self.subprotocol = ws.subprotocol
            by_subscription: dict[int, str] = {}
            while not self.stop.is_set():
                try:
                    raw = await asyncio.wait_for(ws.recv(), 0.1)
                except asyncio.TimeoutError:
                    continue
                if isinstance(raw, str):
                    body = json.loads(raw)
                    if body["op"] == "serverInfo":
                        self.server_info = body
                    elif body["op"] == "advertise":
                        self.advertised.update({c["topic"]: c for c in body["channels"]})
                        if all(t in self.advertised for t in self.topics) and not by_subscription:
                            subs = [{"id": k + 1, "channelId": self.advertised[t]["id"]} for k, t in enumerate(self.topics)]
                            by_subscription = {s["id"]: t for s, t in zip(subs, self.topics)}
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                            self.subscribed.set()
                elif raw[0] == 1:  # message data: opcode, subscription id (u32), log time (u64), payload
                    sub, log_time = struct.unpack_from("<IQ", raw, 1)
                    self.messages.append((by_subscription[sub], log_time, json.loads(raw[13:])))

    def of(self, topic: str) -> list[tuple[int, Any]]:
        return [(t, body) for name, t, body in self.messages if name == topic]

    def close(self) -> None:
        self.stop.set()
        self.thread.join(10)


def _wait(condition: Any, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


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
            _wait(lambda: len(client.of("/falcon/legs")) >= len(log))
        finally:
            client.close()
        assert client.error is None, client.error
    legs = client.of("/falcon/legs")
    assert [body["t_s"] for _, body in legs] == log.t_s.tolist()
    assert [body["counts"] for _, body in legs] == log.enc.tolist()
    times = np.array([t for t, _ in legs])
    # wall-clock log times: from the run's start, one period apart (the run was paced)
    assert t0 <= times[0] <= time.time_ns() and np.all(np.diff(times) > 0)
    np.testing.assert_allclose(np.diff(times) * 1e-9, np.diff(log.t_s), atol=1e-6)
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
            assert recorder.rows == 100 and recorder.encoded == (100 if watched else 0)
