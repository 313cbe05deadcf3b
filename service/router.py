"""A Zenoh router in a Python process, for users without ``zenohd``: ``falcon-plan router``.

eclipse-zenoh opens a session in router mode (``mode: "router"``), which routes between the
client sessions (and peers) that connect to it: instances started with ``serve --mode client
--connect <router>`` on any machine add up behind it, and clients started the same way reach
them all. Defaults as everywhere in the service: loopback only, multicast scouting off.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Any, Iterator

from falcon_plan.errors import InvalidParameterError
from service.config import SessionSettings, open_session


@contextlib.contextmanager
def running_router(settings: SessionSettings) -> Iterator[Any]:
    """An open router session (``settings.mode`` must be ``router``); closed on exit."""
    if settings.mode != "router":
        raise InvalidParameterError(f"a router needs mode 'router', got {settings.mode!r}")
    session = open_session(settings)
    try:
        yield session
    finally:
        session.close()


def serve_router(settings: SessionSettings, stop: threading.Event | None = None) -> int:
    """Route with the session ``settings`` (mode router) until SIGINT/SIGTERM (or ``stop``
    is set); returns 0."""
    stop = stop or threading.Event()
    previous: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        with running_router(settings) as session:
            print(f"falcon-plan router {session.zid()} ready ({settings.describe()}); Ctrl-C stops it", flush=True)
            while not stop.wait(0.5):
                pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("falcon-plan router stopped", flush=True)
    return 0
