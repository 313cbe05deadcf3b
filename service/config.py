"""The single place that builds a ``zenoh.Config`` for the service and its clients.

Defaults are safe for a lab machine: peer mode, multicast scouting off, and only loopback
endpoints. A server listens on ``tcp/127.0.0.1:7447``; a client listens nowhere and connects
there. Everything can be changed: ``mode`` (``peer`` or ``client`` of a router), listen and
connect endpoints, a JSON5 config file, and generic ``KEY:VALUE`` overrides applied last with
``Config.insert_json5`` (for example ``--cfg 'scouting/gossip/enabled:false'``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Sequence

from falcon_plan.errors import InvalidParameterError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
"""Where a server listens and a client connects by default (loopback only)."""

MODES = ("peer", "client")
"""Session modes of servers and clients (``client`` joins a router or a peer)."""

ALL_MODES = (*MODES, "router")
"""Also ``router``: a session that routes for client sessions (``falcon-plan router``, for
users without ``zenohd``)."""


def parse_override(text: str) -> tuple[str, str]:
    """Split ``text``, ``KEY:VALUE``, at the first colon (keys have none; JSON5 values may)."""
    key, sep, value = text.partition(":")
    if not sep or not key or not value:
        raise InvalidParameterError(f"config override {text!r} must look like KEY:VALUE, "
                                    "e.g. 'scouting/multicast/enabled:false'")
    return key.strip(), value.strip()


@dataclass(frozen=True)
class SessionSettings:
    """How to open a Zenoh session.

    Attributes
    ----------
    mode : "peer" (default), "client" (then ``connect`` names a router) or "router".
    listen : endpoints to listen on (ignored in client mode).
    connect : endpoints to connect to.
    config_file : a JSON5 zenoh config to start from.
    overrides : ``(key, json5 value)`` pairs applied last.
    """

    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    config_file: str | None = None
    overrides: tuple[tuple[str, str], ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if self.mode not in ALL_MODES:
            raise InvalidParameterError(f"mode must be one of {ALL_MODES}, got {self.mode!r}")
        for name in ("listen", "connect"):
            endpoints = tuple(getattr(self, name))
            bad = [e for e in endpoints if not isinstance(e, str) or "/" not in e]
            if bad:
                raise InvalidParameterError(f"{name} endpoints must look like tcp/127.0.0.1:7447, got {bad}")
            object.__setattr__(self, name, endpoints)
        if self.mode == "client" and not self.connect:
            raise InvalidParameterError("client mode needs at least one --connect endpoint (a router)")

    @classmethod
    def server(cls, listen: Sequence[str] | None = None, connect: Sequence[str] = (), mode: str = "peer",
               config_file: str | None = None, cfg: Sequence[str] = ()) -> "SessionSettings":
        """A server: listens on ``listen`` (default :data:`DEFAULT_ENDPOINT`), joins
        ``connect``, in ``mode``, from the zenoh ``config_file`` with the ``cfg`` overrides
        (``KEY:VALUE``)."""
        if listen is None:
            listen = () if mode == "client" else (DEFAULT_ENDPOINT,)
        return cls(mode, tuple(listen), tuple(connect), config_file, tuple(parse_override(c) for c in cfg))

    @classmethod
    def router(cls, listen: Sequence[str] | None = None, connect: Sequence[str] = (), config_file: str | None = None,
               cfg: Sequence[str] = ()) -> "SessionSettings":
        """A router: listens on ``listen`` (default :data:`DEFAULT_ENDPOINT`) and routes
        between the sessions that connect to it; ``connect``: other routers; ``config_file``
        and ``cfg`` as for :meth:`server`."""
        return cls("router", tuple(listen or (DEFAULT_ENDPOINT,)), tuple(connect), config_file,
                   tuple(parse_override(c) for c in cfg))

    @classmethod
    def client(cls, connect: Sequence[str] | None = None, listen: Sequence[str] = (), mode: str = "peer",
               config_file: str | None = None, cfg: Sequence[str] = ()) -> "SessionSettings":
        """A client: connects to ``connect`` (default :data:`DEFAULT_ENDPOINT`), listens nowhere
        unless ``listen``; ``mode``, ``config_file`` and ``cfg`` as for :meth:`server`."""
        return cls(mode, tuple(listen), tuple(connect or (DEFAULT_ENDPOINT,)), config_file,
                   tuple(parse_override(c) for c in cfg))

    def to_zenoh(self) -> Any:
        """The ``zenoh.Config``. Raises InvalidParameterError naming a rejected setting."""
        import zenoh

        try:
            conf = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        except (zenoh.ZError, OSError) as exc:
            raise InvalidParameterError(f"cannot read zenoh config file {self.config_file!r}: {exc}") from None
        settings: list[tuple[str, str]] = [
            ("mode", json.dumps(self.mode)),
            ("scouting/multicast/enabled", "false"),
            ("listen/endpoints", json.dumps(list(self.listen))),
            ("connect/endpoints", json.dumps(list(self.connect))),
            *self.overrides,
        ]
        for key, value in settings:
            try:
                conf.insert_json5(key, value)
            except zenoh.ZError as exc:
                raise InvalidParameterError(f"zenoh config rejected {key}={value}: {exc}") from None
        return conf

    def describe(self) -> str:
        """One line for logs."""
        return (f"mode={self.mode} listen={list(self.listen)} connect={list(self.connect)}"
                + (f" file={self.config_file}" if self.config_file else "")
                + (f" overrides={dict(self.overrides)}" if self.overrides else ""))


def open_session(settings: SessionSettings) -> Any:
    """Open a zenoh session (a context manager) with ``settings``."""
    import zenoh

    conf = settings.to_zenoh()
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        raise InvalidParameterError(f"cannot open a zenoh session ({settings.describe()}): {exc}") from None


def add_session_arguments(parser: Any, *, server: bool) -> None:
    """Add ``--mode --listen --connect --zenoh-config --cfg`` to the argparse ``parser``
    (defaults for a ``server`` or a client)."""
    parser.add_argument("--mode", choices=MODES, default="peer",
                        help="peer (default) or client of a router given by --connect")
    parser.add_argument("--listen", action="append", metavar="ENDPOINT",
                        help=f"endpoint to listen on, repeatable (default {DEFAULT_ENDPOINT})" if server
                        else "endpoint to listen on, repeatable (default: none)")
    parser.add_argument("--connect", action="append", metavar="ENDPOINT",
                        help="endpoint to connect to, repeatable (default: none)" if server
                        else f"endpoint to connect to, repeatable (default {DEFAULT_ENDPOINT})")
    parser.add_argument("--zenoh-config", metavar="FILE", help="JSON5 zenoh config file to start from")
    parser.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                        help="zenoh config override, JSON5 value, repeatable (e.g. 'scouting/gossip/enabled:false')")


def settings_from_args(args: Any, *, server: bool) -> SessionSettings:
    """SessionSettings from the arguments ``args`` added by :func:`add_session_arguments`
    (for a ``server`` or a client)."""
    if server:
        return SessionSettings.server(args.listen, args.connect or (), args.mode, args.zenoh_config, args.cfg)
    return SessionSettings.client(args.connect, args.listen or (), args.mode, args.zenoh_config, args.cfg)


def free_loopback_port() -> int:
    """A TCP port free on 127.0.0.1 right now (for demos and tests)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])
