"""The live view: a Foxglove WebSocket server on loopback (``foxglove-sdk``) showing the same
channels as a recording while the device moves, at 50 Hz (the recorder publishes one row per
1/50 s; a recording keeps every tick).

Every topic of :data:`~falcon_plan.recording.channels.TOPICS` is advertised when the server
starts, so a Foxglove layout finds its topics before the first run. Messages carry wall-clock
log times (live data in Foxglove is on the wall clock); their ``t_s`` fields keep the run's
own time. Connect Foxglove to ``ws://127.0.0.1:PORT`` (Open connection -> Foxglove WebSocket);
the server speaks the Foxglove WebSocket protocol under the subprotocol name
``foxglove.sdk.v1`` (the same protocol as ``foxglove.websocket.v1``; viewers too old to offer
the new name are refused at the handshake).
"""
from __future__ import annotations

import threading
from typing import Any

from falcon_plan.errors import InvalidParameterError
from falcon_plan.recording.channels import TOPICS, schema_bytes

DEFAULT_PORT = 8765
"""Foxglove's usual WebSocket port."""
HOST = "127.0.0.1"
"""The live view listens on loopback only."""


class LiveView:
    """A Foxglove WebSocket server on :data:`HOST` (a context manager).

    Parameters
    ----------
    port : TCP port (0: any free port; :attr:`port` says which).
    name : the server's name shown in Foxglove.
    """

    def __init__(self, port: int = DEFAULT_PORT, name: str = "falcon-plan") -> None:
        import foxglove

        if not (isinstance(port, int) and 0 <= port <= 65535):
            raise InvalidParameterError(f"the Foxglove port must be a whole number in 0..65535, got {port!r}")
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name=name, host=HOST, port=port, context=self._context)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types
            raise InvalidParameterError(f"cannot start the Foxglove server on {HOST}:{port} ({exc}); "
                                        "choose another port with --foxglove-port") from None
        self._lock = threading.Lock()
        self._channels: dict[str, Any] = {}
        for topic in TOPICS:
            self._channel(topic)

    @property
    def port(self) -> int:
        """The TCP port the server listens on."""
        return int(self._server.port)

    @property
    def url(self) -> str:
        """The address to open in Foxglove."""
        return f"ws://{HOST}:{self.port}"

    def _channel(self, topic: str) -> Any:
        import foxglove

        with self._lock:
            if topic not in self._channels:
                name = TOPICS[topic]
                schema = foxglove.Schema(name=name, encoding="jsonschema", data=schema_bytes(name))
                self._channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="json",
                                                         context=self._context)
            return self._channels[topic]

    @property
    def watched(self) -> bool:
        """True when a client is subscribed to at least one channel."""
        with self._lock:
            channels = list(self._channels.values())
        return any(channel.has_sinks() for channel in channels)

    def publish(self, topic: str, wall_ns: int, data: bytes) -> None:
        """Send the JSON message ``data`` on ``topic`` with log time ``wall_ns`` [ns since the
        UNIX epoch] to every subscribed client (nothing when none is)."""
        channel = self._channels.get(topic) or self._channel(topic)
        channel.log(data, log_time=int(wall_ns))

    def close(self) -> None:
        """Stop the server (idempotent)."""
        server, self._server = getattr(self, "_server", None), None
        if server is not None:
            server.stop()

    def __enter__(self) -> "LiveView":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


__all__ = ["DEFAULT_PORT", "HOST", "LiveView"]
