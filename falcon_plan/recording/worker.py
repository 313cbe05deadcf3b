"""The recording process: where rows become MCAP messages and live-view messages, away from the
control loop's interpreter (``python -m falcon_plan.recording.worker``, started by
:class:`~falcon_plan.recording.recorder.RecorderProcess`; not meant to be run by hand).

It reads the loop's rows from the shared :class:`~falcon_plan.recording.ring.RowRing` every
1/60 s, and the recorders' other items (open, start, plan, messages, finish, close) from the
control pipe; an item carries the ring's head when it was sent, and the rows before it are
handled first (a drain handles the items already in the pipe before the rows, and never hands a
row over twice), so everything a recording gets stays in the order it was sent. Each recorder
is a session here: its MCAP file (:class:`~falcon_plan.recording.mcapfile.McapRecording`,
chunked every 0.5 s of log time) and/or the live view (:class:`~falcon_plan.recording.live.FoxgloveServer`).

It runs at a low priority (nice 10), ignores SIGINT and SIGHUP (a Ctrl-C or a closed
terminal reaches the whole process group; the parent handles them, or its end ends this), and
finishes every open file and exits when it is told to stop, when the parent goes away by any
means, SIGKILL included (the control pipe reaches end-of-file or the parent id changes), and
2 s after SIGTERM (time for a parent stopped with it to close its recordings first). The rows
already in the ring are written first, so a parent killed outright still leaves a complete
recording.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import sys
import time
from multiprocessing.connection import Connection
from typing import Any

from falcon_plan.recording.channels import LOG_META_NAME, RUN_TOPIC, Message, RowEncoder, dumps, plan_messages
from falcon_plan.recording.ring import Row, RowRing

_log = logging.getLogger("falcon_plan.recording")

DRAIN_RATE_HZ = 60.0
"""How often the rows in the ring are handled [Hz] (the live view's batches: at most 60 Hz)."""
NICE = 10
"""The recording process's priority below the loop's (os.nice increment): a waking loop takes the
core from it at once, while it keeps about a tenth of a core against a busy process at the
default priority (what a 1 kHz recording needs; at 19 it would get 1.5 % and fall behind on a
loaded machine). The ring holds what it has not yet taken."""
SIGTERM_GRACE_S = 2.0
"""After SIGTERM the process goes on this long for its parent to close the recordings (a whole
process group is often stopped at once), then finishes them itself [s]."""
CONTROLLER_KEYS = ("rate_hz", "controller", "feedforward_effects")
"""The falcon-log metadata that describe the controller (recorded again as metadata record
``controller``)."""


class Session:
    """One recorder's recording (``recording``, an McapRecording or None) and/or its share of
    the live view (``live``, a FoxgloveServer or None). ``rows`` counts the rows received,
    ``encoded`` those turned into messages (a live view alone encodes one row per 1/50 s, and
    nothing while no client is subscribed); ``failed`` turns True when a message could not be
    made or written (the first failure is logged with its traceback)."""

    def __init__(self, recording: Any, live: Any) -> None:
        self.recording, self.live = recording, live
        self.rows = self.encoded = 0
        self.failed = False
        self._encoder: RowEncoder | None = None
        self._t_s = 0.0
        self._wall0_ns: int | None = None

    def handle(self, what: str, call: Any, *args: Any) -> None:
        """``call(*args)`` -> (messages, live too?), emitted; a failure (of the step named
        ``what``) is noted, never raised."""
        try:
            self._emit(*call(*args))
        except Exception:  # noqa: BLE001 - a recording problem must not stop the others
            if not self.failed:
                _log.exception("recording failed on %s; later failures are not logged", what)
            self.failed = True

    def row(self, row: Row) -> tuple[list[Message], bool]:
        self._t_s = row.t_s
        if self._wall0_ns is None:
            self._wall0_ns = time.time_ns() - int(row.t_s * 1e9)
        self.rows += 1
        if self._encoder is None:
            return [], False
        live = self.live is not None and self._encoder.view_due(row.t_s) and self.live.watched
        if self.recording is None and not live:
            self._encoder.skip(row.t_s, row.enc)
            return [], False
        self.encoded += 1
        return self._encoder.encode(row.t_s, row.enc, row.tc, row.ref, row.measured_m, row.planned_m, row.timing), live

    def start(self, meta: dict[str, str], params: Any, command_limit: int,
              model_meta: dict[str, str]) -> tuple[list[Message], bool]:
        """A run starts: its falcon-log ``meta``, the model's ``params`` and ``model_meta`` and
        the device's ``command_limit`` [command units]; the metadata records and messages."""
        self._encoder = RowEncoder(params, command_limit)
        if self.recording is not None:
            self.recording.metadata(LOG_META_NAME, meta)
            self.recording.metadata("model", model_meta)
            self.recording.metadata("controller", {k: meta[k] for k in CONTROLLER_KEYS if k in meta})
        return [], False

    def plan(self, trajectory: Any, report: dict[str, Any] | None) -> tuple[list[Message], bool]:
        """The messages of a plan: its ``trajectory`` and the planner's ``report`` (or None)."""
        return plan_messages(self._t_s, trajectory, report), True

    def message(self, topic: str, body: dict[str, Any]) -> tuple[list[Message], bool]:
        """One JSON message ``body`` on ``topic``, at the run's current time."""
        return [(topic, self._t_s, dumps(body))], True

    def finish(self, report: dict[str, Any] | None) -> tuple[list[Message], bool]:
        """The run's end: its execution ``report`` as the run message; a run cut short by an
        exception (``report`` None) gets one with status ``interrupted``, as the CSV log's end
        line."""
        from falcon_plan.falconlog import INTERRUPTED

        return [(RUN_TOPIC, self._t_s, dumps(report if report is not None else {"status": INTERRUPTED}))], True

    def _emit(self, messages: list[Message], live: bool) -> None:
        if self.recording is not None and messages:
            self.recording.write_all(messages)
        if self.live is not None and live and messages:
            wall0 = self._wall0_ns if self._wall0_ns is not None else time.time_ns() - int(self._t_s * 1e9)
            for topic, t_s, data in messages:
                self.live.publish(topic, wall0 + int(t_s * 1e9), data)

    def close(self) -> None:
        """Finish the recording (the live view stays up)."""
        if self.recording is not None:
            try:
                self.recording.close()
            except Exception:  # noqa: BLE001 - close logs its own errors; never stop the others
                _log.exception("finishing the recording failed")
                self.failed = True


class Worker:
    """The sessions of one recording process, fed from ``ring`` and the control items; ``live``
    is the process's FoxgloveServer (or None)."""

    def __init__(self, ring: RowRing, live: Any) -> None:
        self.ring, self.live = ring, live
        self.sessions: dict[int, Session] = {}
        self.lost = 0

    def drain(self, upto: int | None = None) -> None:
        """Handle the rows in the ring (up to ring index ``upto``; default all)."""
        rows, lost = self.ring.take(upto)
        if lost:
            if not self.lost:
                _log.error("the recording process fell %d rows behind the loop; they are lost", lost)
            self.lost += lost
            for session in self.sessions.values():
                session.failed = True
        for row in rows:
            session = self.sessions.get(row.session)
            if session is not None:
                session.handle("a row", session.row, row)

    def item(self, item: tuple[Any, ...]) -> Any:
        """Handle one control item (its rows before it); returns the reply of a request."""
        kind, head, *args = item
        self.drain(head)
        if kind == "watched":
            return self.live is not None and self.live.watched
        if kind == "open":
            session_id, path, metadata, live = args
            recording = None
            if path is not None:
                from falcon_plan.recording.mcapfile import McapRecording

                recording = McapRecording(path, metadata=metadata)
            self.sessions[session_id] = Session(recording, self.live if live else None)
            return session_id
        session = self.sessions[args[0]]
        if kind == "close":
            del self.sessions[args[0]]
            session.close()
            return {"rows": session.rows, "encoded": session.encoded, "failed": session.failed}
        call = {"start": session.start, "plan": session.plan, "message": session.message,
                "finish": session.finish}[kind]
        session.handle(kind, call, *args[1:])
        return None

    def close(self) -> None:
        """Handle the rows left and finish every recording."""
        self.drain()
        for session in self.sessions.values():
            session.close()
        self.sessions.clear()


def serve(worker: Worker, control: Connection, reply: Connection, parent: int, stop_at: list[float]) -> None:
    """``worker`` handles the items arriving on ``control`` (answered on ``reply``) and the
    ring's rows until told to stop, the end of process ``parent``, or ``stop_at[0]``
    (monotonic time [s]; SIGTERM sets it :data:`SIGTERM_GRACE_S` ahead)."""
    period = 1.0 / DRAIN_RATE_HZ
    next_drain = time.monotonic() + period
    while time.monotonic() < stop_at[0]:
        try:
            ready = control.poll(max(0.0, next_drain - time.monotonic()))
            item = control.recv() if ready else None
        except (EOFError, OSError):  # the parent closed its end or went away
            return
        if item is not None and not handle(worker, item, reply):
            return
        if time.monotonic() >= next_drain:
            if not drain_in_order(worker, control, reply):
                return
            next_drain = time.monotonic() + period
            if os.getppid() != parent:
                return


def drain_in_order(worker: Worker, control: Connection, reply: Connection) -> bool:
    """The periodic drain of ``worker``: the ring's head is read first, then every item already
    on ``control`` is handled (answered on ``reply``; a recorder's ``start`` sent before rows
    now in the ring must come before them: rows of a session not yet started are not recorded),
    then the rows up to that head. False when the parent is gone or said stop."""
    head = worker.ring.head
    try:
        while control.poll(0):
            if not handle(worker, control.recv(), reply):
                return False
    except (EOFError, OSError):
        return False
    worker.drain(head)
    return True


def handle(worker: Worker, item: tuple[Any, ...], reply: Connection) -> bool:
    """Have ``worker`` handle one control ``item`` (a request answered on ``reply``); False
    when it says stop (every recording finished then)."""
    if item[0] == "stop":
        worker.close()
        _answer(reply, ("ok", None))
        return False
    try:
        answer = ("ok", worker.item(item))
    except Exception as exc:  # noqa: BLE001 - the request's own failure, reported to its caller
        answer = ("error", type(exc).__name__, str(exc))
    if item[0] in REQUESTS:
        _answer(reply, answer)
    elif answer[0] == "error":
        _log.error("recording item %r failed: %s", item[0], answer[2])
    return True


def _answer(reply: Connection, answer: tuple[Any, ...]) -> None:
    """Send ``answer``; a parent that stopped waiting (gone, or gave up) is not an error here."""
    try:
        reply.send(answer)
    except OSError:
        pass


REQUESTS = frozenset({"open", "close", "watched", "stop"})
"""The control items the parent waits an answer for."""


def main(argv: list[str] | None = None) -> int:
    """The recording process's entry point; ``argv`` as RecorderProcess passes it (default:
    sys.argv)."""
    parser = argparse.ArgumentParser(description="falcon-plan's recording process (started by RecorderProcess)")
    parser.add_argument("ring_fd", type=int)
    parser.add_argument("capacity", type=int)
    parser.add_argument("control_fd", type=int)
    parser.add_argument("reply_fd", type=int)
    parser.add_argument("parent", type=int)
    parser.add_argument("--live", nargs=2, metavar=("PORT", "NAME"), default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="falcon-plan recorder: %(levelname)s %(message)s")
    stop_at = [math.inf]
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent's to handle (a Ctrl-C reaches the whole group)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # a closed terminal ends the parent; its end ends this
    signal.signal(signal.SIGTERM, lambda *_: stop_at.__setitem__(0, min(stop_at[0], time.monotonic() + SIGTERM_GRACE_S)))
    try:
        os.nice(NICE)
    except OSError:
        pass
    control = Connection(args.control_fd, writable=False)
    reply = Connection(args.reply_fd, readable=False)
    ring = RowRing(args.ring_fd, args.capacity)
    live = None
    try:
        if args.live is not None:
            from falcon_plan.recording.live import FoxgloveServer

            live = FoxgloveServer(int(args.live[0]), args.live[1])
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which raises it
        reply.send(("error", type(exc).__name__, str(exc)))
        return 1
    reply.send(("ok", None if live is None else live.port))
    worker = Worker(ring, live)
    try:
        serve(worker, control, reply, args.parent, stop_at)
    finally:
        worker.close()
        if live is not None:
            live.close()
        ring.close()
    return 0


__all__ = ["CONTROLLER_KEYS", "DRAIN_RATE_HZ", "Session", "Worker", "drain_in_order", "handle", "main", "serve"]

if __name__ == "__main__":
    sys.exit(main())
