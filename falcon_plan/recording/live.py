"""The live view: a Foxglove WebSocket server on loopback (``foxglove-sdk``) showing the same
channels as a recording while the device moves, at 50 Hz (one row per 1/50 s; a recording
keeps every tick).

The server runs in the recording process (:mod:`~falcon_plan.recording.worker`), where the
messages are made, so the control loop's process holds neither the server nor the encoder:
:class:`LiveView` is the handle the loop's process keeps, :class:`FoxgloveServer` the server
in the recording process.

Every topic of :data:`~falcon_plan.recording.channels.TOPICS` is advertised when the server
starts, so a Foxglove layout finds its topics before the first run. Messages carry wall-clock
log times (live data in Foxglove is on the wall clock); their ``t_s`` fields keep the run's
own time. Connect Foxglove to ``ws://127.0.0.1:PORT`` (Open connection -> Foxglove WebSocket);
the server speaks the Foxglove WebSocket protocol under the subprotocol name
``foxglove.sdk.v1`` (the same protocol as ``foxglove.websocket.v1``; viewers too old to offer
the new name are refused at the handshake).
"""
from __future__ import annotations

from typing import Any

from falcon_plan.errors import InvalidParameterError

DEFAULT_PORT = 8765
"""Foxglove's usual WebSocket port."""
HOST = "127.0.0.1"
"""The live view listens on loopback only."""


def check_port(port: Any) -> int:
    """``port`` if it is a TCP port number (0: any free port), else InvalidParameterError."""
    if not (isinstance(port, int) and not isinstance(port, bool) and 0 <= port <= 65535):
        raise InvalidParameterError(f"the Foxglove port must be a whole number in 0..65535, got {port!r}")
    return port


class LiveView:
    """A Foxglove WebSocket server on :data:`HOST`, in a recording process of its own (a
    context manager). Recorders given this view (:class:`~falcon_plan.recording.RunRecorder`)
    send their rows to that process, and write their MCAP recordings there too.

    Parameters
    ----------
    port : TCP port (0: any free port; :attr:`port` says which).
    name : the server's name shown in Foxglove.
    """

    def __init__(self, port: int = DEFAULT_PORT, name: str = "falcon-plan") -> None:
        from falcon_plan.recording.recorder import RecorderProcess

        self.process = RecorderProcess(live=(check_port(port), name))
        self.port = int(self.process.live_port or 0)
        """The TCP port the server listens on."""

    @property
    def url(self) -> str:
        """The address to open in Foxglove."""
        return f"ws://{HOST}:{self.port}"

    @property
    def watched(self) -> bool:
        """True when a client is subscribed to at least one channel."""
        return bool(self.process.request("watched"))

    def close(self) -> None:
        """Finish what the recorders sent, stop the server and its process (idempotent)."""
        self.process.close()

    def __enter__(self) -> "LiveView":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class FoxgloveServer:
    """The Foxglove WebSocket server itself (in the recording process), named ``name``, on the
    loopback ``port``: every topic advertised with its JSON Schema; :meth:`publish` sends a
    message to the subscribed clients."""

    def __init__(self, port: int, name: str) -> None:
        import foxglove

        from falcon_plan.recording.channels import TOPICS, schema_bytes

        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name=name, host=HOST, port=check_port(port), context=self._context)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types
            raise InvalidParameterError(f"cannot start the Foxglove server on {HOST}:{port} ({exc}); "
                                        "choose another port with --live-port / --foxglove-port") from None
        self._channels = {topic: foxglove.Channel(topic, schema=foxglove.Schema(name=schema, encoding="jsonschema",
                                                                                 data=schema_bytes(schema)),
                                                  message_encoding="json", context=self._context)
                          for topic, schema in TOPICS.items()}

    @property
    def port(self) -> int:
        """The TCP port the server listens on."""
        return int(self._server.port)

    @property
    def watched(self) -> bool:
        """True when a client is subscribed to at least one channel."""
        return any(channel.has_sinks() for channel in self._channels.values())

    def publish(self, topic: str, wall_ns: int, data: bytes) -> None:
        """Send the JSON message ``data`` on ``topic`` (one of TOPICS) with log time ``wall_ns``
        [ns since the UNIX epoch] to every subscribed client (nothing when none is)."""
        self._channels[topic].log(data, log_time=int(wall_ns))

    def close(self) -> None:
        """Stop the server (idempotent)."""
        server, self._server = getattr(self, "_server", None), None
        if server is not None:
            server.stop()


__all__ = ["DEFAULT_PORT", "HOST", "FoxgloveServer", "LiveView", "check_port"]
