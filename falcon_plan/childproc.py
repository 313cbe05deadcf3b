"""Worker processes that talk to their parent over a socket pair: started as
``python -m MODULE FD ARGS...`` (FD: the child's end, a :class:`multiprocessing.connection.Connection`),
with SIGINT blocked from birth until the child ignores it (:func:`child_ignores_sigint`), so a
terminal's Ctrl-C stops the parent, which decides when its children end."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from multiprocessing.connection import Connection
from pathlib import Path


def spawn_module(module: str, *args: str) -> tuple[subprocess.Popen, Connection]:
    """Start ``python -m module FD *args`` (this interpreter, this checkout first on its path);
    returns (the process, the parent's end of the socket pair)."""
    parent, child = socket.socketpair()
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (root, os.environ.get("PYTHONPATH"))))}
    # the child inherits this thread's signal mask: with SIGINT blocked it cannot die of a
    # terminal's Ctrl-C while Python starts, before it ignores SIGINT (child_ignores_sigint)
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        process = subprocess.Popen([sys.executable, "-m", module, str(child.fileno()), *args],
                                   pass_fds=(child.fileno(),), env=env, stdin=subprocess.DEVNULL)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        child.close()
    return process, Connection(parent.detach())


def child_ignores_sigint() -> None:
    """In a child of :func:`spawn_module`: SIGINT, blocked since birth, is ignored from here on
    (a Ctrl-C pending meanwhile is dropped); the parent decides when this process ends."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


__all__ = ["spawn_module", "child_ignores_sigint"]
