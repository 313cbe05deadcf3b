"""A Foxglove WebSocket client for the tests and the recording benchmark (the ``websockets``
package of the test extra): it connects on loopback as the Foxglove app does, reads the
server's advertisements, subscribes and keeps what arrives.

As a program (``python tests/recording/foxglove_client.py URL``, the benchmark's watcher, in a
process of its own so that it takes nothing from the loop's process): subscribes to every
channel, prints ``subscribed`` once it has, and the number of messages received when its
standard input closes.
"""
from __future__ import annotations

import asyncio
import json
import struct
import sys
import threading
from typing import Any

import websockets

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # what the Foxglove app offers


class Client:
    """A Foxglove WebSocket client in a thread: reads the advertisements, subscribes to
    ``topics`` (None: every advertised topic) and keeps every message (topic, log time [ns],
    JSON body)."""

    def __init__(self, url: str, topics: tuple[str, ...] | None) -> None:
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
        async with websockets.connect(self.url, subprotocols=SUBPROTOCOLS, max_size=None, close_timeout=0.5) as ws:
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
                        topics = tuple(self.advertised) if self.topics is None else self.topics
                        if all(t in self.advertised for t in topics) and not by_subscription:
                            subs = [{"id": k + 1, "channelId": self.advertised[t]["id"]} for k, t in enumerate(topics)]
                            by_subscription = {s["id"]: t for s, t in zip(subs, topics)}
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


def main() -> int:
    client = Client(sys.argv[1], None)
    if not client.subscribed.wait(60) or client.error is not None:
        print(f"error {client.error}", flush=True)
        return 1
    print("subscribed", flush=True)
    sys.stdin.read()  # until the benchmark closes it
    client.close()
    print(len(client.messages), flush=True)
    return 0 if client.error is None else 1


if __name__ == "__main__":
    sys.exit(main())
