"""The run recorder: the executor's row sink, writing an MCAP recording and feeding the live view
from a process of its own.

The control loop pays one row written into a shared-memory ring per tick
(:meth:`RunRecorder.row`: one ``struct.pack_into``; 2 us in a tight loop, 5 to 10 us in a paced
one whose caches others have used; no system call, no thread). Everything else happens in the recording process (:mod:`~falcon_plan.recording.worker`): it
reads the ring at 60 Hz, turns the rows into messages
(:class:`~falcon_plan.recording.channels.RowEncoder`), writes them all to the recording and
publishes those of one row per 1/50 s live (with no client subscribed and no recording nothing
is encoded at all). The loop's process holds no encoder thread, so the encoder never competes
with the loop for the interpreter lock.

:class:`RecorderProcess` is that process seen from the loop's side. A
:class:`~falcon_plan.recording.live.LiveView` has one (it hosts the Foxglove server), and every
recorder given that view uses it; a recorder without a view starts its own and stops it when
it closes. The process finishes its files however the loop's process ends: told to (``close``,
on exceptions and Ctrl-C through ``with`` blocks, and at interpreter exit), on SIGTERM, and when
the loop's process dies outright (SIGKILL): then it writes the rows already handed off and the
footer, and exits.

Everything a recording gets stays in order: the run's start (metadata), its rows, the plan,
goal events, the run's report. Log times are the run's clock (the rows' ``t``); what happens
before the first row is stamped 0, what happens after it at the latest row's time.
"""
from __future__ import annotations

import atexit
import itertools
import logging
import os
import subprocess
import sys
import threading
import time
import weakref
from multiprocessing.connection import Connection
from pathlib import Path
from typing import TYPE_CHECKING, Any

from falcon_plan import errors
from falcon_plan.errors import FalconPlanError
from falcon_plan.recording.channels import GOAL_TOPIC, command_limit_of, model_metadata
from falcon_plan.recording.ring import DEFAULT_CAPACITY, RowRing

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.recording.live import LiveView
    from falcon_plan.trajectory import Trajectory

_log = logging.getLogger(__name__)

START_TIMEOUT_S = 60.0
"""Longest wait for the recording process to start (imports on a crowded machine) [s]."""
ANSWER_TIMEOUT_S = 60.0
"""Longest wait for an answer of the recording process while it takes no rows from the ring [s]
(a close first writes every row left, however long that takes)."""


class RecordingProcessError(FalconPlanError, RuntimeError):
    """The recording process did not answer (it died or hung)."""


_processes: "weakref.WeakSet[RecorderProcess]" = weakref.WeakSet()


@atexit.register
def _close_processes() -> None:
    for process in list(_processes):
        process.close()


class RecorderProcess:
    """The recording process, seen from the loop's side: the row ring (:attr:`ring`, written
    under :attr:`row_lock`), the control pipe (:meth:`send`, :meth:`request`) and the child
    itself (:meth:`close`).

    Parameters
    ----------
    live : (port, name) of a Foxglove server to run in the process (None: none); its port is
        then :attr:`live_port`.
    capacity : rows the ring holds (how far the process may fall behind the loop).
    """

    def __init__(self, live: tuple[int, str] | None = None, capacity: int = DEFAULT_CAPACITY) -> None:
        self.ring = RowRing.create(capacity)
        control_read, control_write = os.pipe()
        reply_read, reply_write = os.pipe()
        argv = [sys.executable, "-m", "falcon_plan.recording.worker", str(self.ring.fd), str(capacity),
                str(control_read), str(reply_write), str(os.getpid())]
        if live is not None:
            argv += ["--live", str(int(live[0])), str(live[1])]
        root = str(Path(__file__).resolve().parents[2])  # where falcon_plan is imported from
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
        try:
            self._child: subprocess.Popen[bytes] | None = subprocess.Popen(
                argv, pass_fds=(self.ring.fd, control_read, reply_write), env=env, stdin=subprocess.DEVNULL)
        finally:
            os.close(control_read)
            os.close(reply_write)
        self._control = Connection(control_write, readable=False)
        self._reply = Connection(reply_read, writable=False)
        self._lock = threading.Lock()  # one item at a time on the pipe, one request at a time
        self.row_lock = threading.Lock()
        """Held while a row is written into :attr:`ring` (the recorders sharing the process may
        write from different threads)."""
        self.failed = False
        """True once the process stopped answering (items are then dropped)."""
        _processes.add(self)
        try:
            self.live_port: int | None = self._answer(START_TIMEOUT_S)
        except BaseException:
            self.close()
            raise
        """The Foxglove server's port (None: no server)."""

    @property
    def pid(self) -> int | None:
        """The recording process's id (None once it is gone)."""
        return None if self._child is None else self._child.pid

    def send(self, kind: str, *args: Any) -> bool:
        """Send the item ``kind`` (after the rows handed off so far); False when the process is
        gone (the item is dropped)."""
        with self._lock:
            return self._send(kind, args)

    def request(self, kind: str, *args: Any) -> Any:
        """Send the item ``kind`` and return the process's answer; the error it raised is
        raised here (RecordingProcessError when it does not answer)."""
        with self._lock:
            if not self._send(kind, args):
                raise RecordingProcessError("the recording process has stopped")
            return self._answer(ANSWER_TIMEOUT_S)

    def _send(self, kind: str, args: tuple[Any, ...]) -> bool:
        if self.failed or self._child is None:
            return False
        try:
            self._control.send((kind, self.ring.head, *args))
            return True
        except OSError as exc:
            self._lost(f"it stopped taking items ({exc})")
            return False

    def _answer(self, timeout_s: float) -> Any:
        """The answer to the last request: waits while the process works through the ring (a
        busy machine may leave it far behind), up to ``timeout_s`` [s] without progress."""
        try:
            taken, deadline = self.ring.taken, time.monotonic() + timeout_s
            while not self._reply.poll(min(1.0, timeout_s)):
                if self.ring.taken != taken:
                    taken, deadline = self.ring.taken, time.monotonic() + timeout_s
                elif time.monotonic() > deadline:
                    self._lost(f"it did not answer in {timeout_s:g} s")
                    raise RecordingProcessError(f"the recording process did not answer in {timeout_s:g} s")
            answer = self._reply.recv()
        except (EOFError, OSError):
            self._lost("it exited")
            raise RecordingProcessError("the recording process exited (its messages are above)") from None
        if answer[0] == "error":
            raise getattr(errors, answer[1], RecordingProcessError)(answer[2])
        return answer[1]

    def _lost(self, why: str) -> None:
        if not self.failed:
            _log.error("the recording process (pid %s) is lost: %s", self.pid, why)
        self.failed = True

    def close(self) -> None:
        """Have the process finish every recording and exit; wait for it (idempotent)."""
        with self._lock:
            child, self._child = self._child, None
            if child is None:
                return
            try:
                if not self.failed and child.poll() is None:
                    self.failed = True  # no more items; an end without an answer is not reported
                    self._control.send(("stop", self.ring.head))
                    self._answer(ANSWER_TIMEOUT_S)
            except (OSError, RecordingProcessError):
                pass
            finally:
                self._control.close()
                self._reply.close()
                try:
                    child.wait(ANSWER_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    _log.error("the recording process (pid %d) did not exit; killed", child.pid)
                    child.kill()
                    child.wait()
                self.ring.close()
                _processes.discard(self)

    def __enter__(self) -> "RecorderProcess":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


_session_ids = itertools.count(1)


class RunRecorder:
    """Records runs into the MCAP file ``mcap_path`` and/or shows them on ``live`` (either may
    be None); implements the executor's :class:`~falcon_plan.execution.executor.RowSink`.

    ``metadata``: MCAP metadata records written at once (name -> {key: value}). OutputError
    when the file cannot be written. Use it as a context manager (or call :meth:`close`):
    closing waits until the recording process has written everything sent and finished the
    file (the live view belongs to the caller and stays up). ``rows`` counts the rows
    received; after closing, ``encoded`` counts those turned into messages (a live view alone
    encodes one row per 1/50 s, and nothing while no client is subscribed) and ``failed`` says
    whether a message could not be made or written (the run went on; the recording process
    logged the first failure with its traceback).
    """

    def __init__(self, mcap_path: str | os.PathLike[str] | None = None, live: LiveView | None = None,
                 metadata: dict[str, dict[str, str]] | None = None) -> None:
        from falcon_plan.fileio import check_writable

        path = None if mcap_path is None else str(check_writable(mcap_path, "MCAP recording").resolve())
        self.path, self.live = path, live
        self.rows = self.encoded = 0
        self.failed = False
        self._session = next(_session_ids)
        self._process = live.process if live is not None else RecorderProcess()
        self._owns_process = live is None
        self._ring, self._row_lock = self._process.ring, self._process.row_lock
        try:
            self._process.request("open", self._session, path, metadata, live is not None)
        except BaseException:
            if self._owns_process:
                self._process.close()
            raise
        self._closed = False

    # --- the executor's sink ----------------------------------------------------------------
    def start(self, meta: dict[str, str], model: FalconModel) -> None:
        """A run starts: ``meta`` is its falcon-log metadata, ``model`` the model it runs with
        (parameters, encoder offset)."""
        self._send("start", dict(meta), model.effects.encoder_params(model.params),
                   command_limit_of(meta, model.params), model_metadata(model))

    def row(self, t_s: float, enc: Any, tc: Any, ref: Any = None, measured_m: Any = None, planned_m: Any = None,
            timing: Any = None) -> None:
        """One falcon-log row, as the executor logs it (``t_s`` [s], counts ``enc``, commands
        ``tc``, planned counts ``ref``; arrays of 3), with the measured and planned end-effector
        positions ``measured_m``, ``planned_m`` [m, base frame] (None: unknown) and the tick's
        ``timing`` (a :class:`~falcon_plan.falconlog.TickTiming`, or None). Called in the
        control loop: one row into the shared ring."""
        self.rows += 1
        with self._row_lock:
            self._ring.put(self._session, t_s, enc, tc, ref, measured_m, planned_m, timing)

    def finish(self, report: Any) -> None:
        """The run ended with ``report`` (an ExecutionReport, or None when it was cut short by an
        exception)."""
        self._send("finish", None if report is None else report.to_dict())

    # --- what callers add ---------------------------------------------------------------------
    def plan(self, trajectory: Trajectory, report: dict[str, Any] | None = None) -> None:
        """Record the ``trajectory`` a run follows and the planner's ``report`` (dict or None)."""
        self._send("plan", trajectory, report)

    def goal_event(self, goal_id: str, event: str, status: str | None = None,
                   detail: dict[str, Any] | None = None) -> None:
        """Record an ``event`` of the service goal ``goal_id`` (its ``status`` and a JSON-ready
        ``detail``)."""
        body: dict[str, Any] = {"goal_id": goal_id, "event": event}
        if status is not None:
            body["status"] = str(status)
        if detail is not None:
            body["detail"] = detail
        self._send("message", GOAL_TOPIC, body)

    def _send(self, kind: str, *args: Any) -> None:
        if not self._closed and not self._process.send(kind, self._session, *args):
            self.failed = True

    def close(self) -> None:
        """Have everything sent written and the recording finished (idempotent; a recording
        process that stopped answering is noted in ``failed``, not raised)."""
        if self._closed:
            return
        self._closed = True
        try:
            answer = self._process.request("close", self._session)
            self.encoded, self.failed = answer["encoded"], self.failed or answer["failed"]
        except RecordingProcessError:
            self.failed = True
        finally:
            if self._owns_process:
                self._process.close()

    def __enter__(self) -> "RunRecorder":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def open_recorder(mcap_path: str | os.PathLike[str] | None = None, live: LiveView | None = None,
                  metadata: dict[str, dict[str, str]] | None = None) -> RunRecorder | None:
    """A recorder writing the MCAP recording ``mcap_path`` (with the metadata records
    ``metadata``) and/or showing on ``live``; None when neither is asked for."""
    if mcap_path is None and live is None:
        return None
    return RunRecorder(mcap_path, live, metadata)


__all__ = ["RecorderProcess", "RecordingProcessError", "RunRecorder", "open_recorder"]
