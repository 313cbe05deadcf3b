"""The run recorder: the executor's row sink, writing an MCAP recording and feeding the live view.

The control loop pays one deque append per row (:meth:`RunRecorder.row`, well under a
microsecond). A background thread wakes at :data:`~falcon_plan.recording.channels.VIEW_RATE_HZ`
(50 Hz), turns the rows that arrived into messages (:class:`~falcon_plan.recording.channels.RowEncoder`: leg angles and speeds, the
device's limit, the 3D scene, JSON), writes them all to the recording and publishes those of one row per 1/50 s live (the
live view shows every channel at 50 Hz; with no client subscribed and no recording nothing is
encoded at all). After every row it lets go of
the interpreter lock (``time.sleep(0)``): pure-Python work in another thread would otherwise
hold the lock for up to the switch interval (5 ms) and make a 1 kHz loop miss deadlines.

Everything a recording gets goes through the same queue in order: the run's start (metadata),
its rows, the plan, goal events, the run's report. Log times are the run's clock (the rows'
``t``); what happens before the first row is stamped 0, what happens after it at the latest
row's time.
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import os
import threading
import time
from typing import TYPE_CHECKING, Any

from falcon_plan.recording.channels import (GOAL_TOPIC, LOG_META_NAME, RUN_TOPIC, VIEW_RATE_HZ, Message,
                                            RowEncoder, command_limit_of, dumps, model_metadata, plan_messages)

if TYPE_CHECKING:
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.recording.live import LiveView
    from falcon_plan.recording.mcapfile import McapRecording
    from falcon_plan.trajectory import Trajectory

_log = logging.getLogger(__name__)


CONTROLLER_KEYS = ("rate_hz", "controller", "feedforward_effects")
"""The falcon-log metadata that describe the controller (recorded again as metadata record
``controller``)."""


def _columns(timing: Any) -> dict[str, int] | None:
    """A row's further columns (name -> whole number) from ``timing``: None, a mapping or a
    dataclass (e.g. the falcon log's per-tick timing)."""
    if timing is None:
        return None
    values = dataclasses.asdict(timing) if dataclasses.is_dataclass(timing) else dict(timing)
    return {str(k): int(v) for k, v in values.items()}


class RunRecorder:
    """Records runs into an MCAP ``recording`` and/or shows them on a ``live`` view (either may
    be None); implements the executor's :class:`~falcon_plan.execution.executor.RowSink`.

    Use it as a context manager (or call :meth:`close`): closing drains the queue, stops the
    thread and finishes the recording (the live view belongs to the caller and stays up).
    ``rows`` counts the rows received, ``encoded`` those turned into messages (a live view
    alone encodes one row per 1/50 s, and nothing while no client is subscribed); ``failed``
    turns True when a message could not be made or written (the run goes on; the first
    failure is logged with its traceback).
    """

    def __init__(self, recording: McapRecording | None = None, live: LiveView | None = None) -> None:
        self.recording = recording
        self.live = live
        self.rows = 0
        self.encoded = 0
        self._queue: collections.deque[Any] = collections.deque()
        self._encoder: RowEncoder | None = None
        self._t_s = 0.0
        self._wall0_ns: int | None = None
        self.failed = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._work, name="run-recorder", daemon=True)
        self._thread.start()

    # --- the executor's sink ----------------------------------------------------------------
    def start(self, meta: dict[str, str], model: FalconModel) -> None:
        """A run starts: ``meta`` is its falcon-log metadata, ``model`` the model it runs with
        (parameters, encoder offset)."""
        self._queue.append(("start", dict(meta), model))

    def row(self, t_s: float, enc: Any, tc: Any, ref: Any = None, measured_m: Any = None, planned_m: Any = None,
            timing: Any = None) -> None:
        """One falcon-log row, as the executor logs it (``t_s`` [s], counts ``enc``, commands
        ``tc``, planned counts ``ref``), with the measured and planned end-effector positions
        ``measured_m``, ``planned_m`` [m, base frame] (None: unknown) and ``timing``, the row's further integer columns (a
        dataclass or a mapping, e.g. per-tick timing; None). The arrays must not change
        afterwards. Called in the control loop: only a queue append."""
        self._queue.append((t_s, enc, tc, ref, measured_m, planned_m, timing))

    def finish(self, report: Any) -> None:
        """The run ended with ``report`` (an ExecutionReport, or None when it was cut short by an
        exception)."""
        self._queue.append(("finish", None if report is None else report.to_dict()))

    # --- what callers add ---------------------------------------------------------------------
    def plan(self, trajectory: Trajectory, report: dict[str, Any] | None = None) -> None:
        """Record the ``trajectory`` a run follows and the planner's ``report`` (dict or None)."""
        self._queue.append(("plan", trajectory, report))

    def goal_event(self, goal_id: str, event: str, status: str | None = None,
                   detail: dict[str, Any] | None = None) -> None:
        """Record an ``event`` of the service goal ``goal_id`` (its ``status`` and a JSON-ready
        ``detail``)."""
        body: dict[str, Any] = {"goal_id": goal_id, "event": event}
        if status is not None:
            body["status"] = str(status)
        if detail is not None:
            body["detail"] = detail
        self._queue.append(("message", GOAL_TOPIC, body))

    # --- the thread ---------------------------------------------------------------------------
    def _work(self) -> None:
        period = 1.0 / VIEW_RATE_HZ
        while not self._stop.wait(period):
            self._drain()
        self._drain()

    def _drain(self) -> None:
        queue = self._queue
        while queue:
            item = queue.popleft()
            try:
                self._emit(*self._handle(item))
            except Exception:  # noqa: BLE001 - a recording problem must not stop the run
                if not self.failed:
                    _log.exception("recording failed on %r; later failures are not logged", item[0])
                self.failed = True
            time.sleep(0)  # let a waiting control loop have the interpreter lock

    def _handle(self, item: tuple[Any, ...]) -> tuple[list[Message], bool]:
        """The messages of a queue item, and whether they go to the live view too (a row's only
        at the view rate)."""
        kind = item[0]
        if not isinstance(kind, str):
            t_s, enc, tc, ref, measured_m, planned_m, timing = item
            self._t_s = float(t_s)
            if self._wall0_ns is None:
                self._wall0_ns = time.time_ns() - int(self._t_s * 1e9)
            self.rows += 1
            if self._encoder is None:
                return [], False
            live = self.live is not None and self._encoder.view_due(self._t_s) and self.live.watched
            if self.recording is None and not live:
                self._encoder.skip(self._t_s, enc)
                return [], False
            self.encoded += 1
            return self._encoder.encode(t_s, enc, tc, ref, measured_m, planned_m, _columns(timing)), live
        if kind == "start":
            _, meta, model = item
            params = model.effects.encoder_params(model.params)
            self._encoder = RowEncoder(params, command_limit_of(meta, model.params))
            if self.recording is not None:
                self.recording.metadata(LOG_META_NAME, meta)
                self.recording.metadata("model", model_metadata(model))
                self.recording.metadata("controller", {k: meta[k] for k in CONTROLLER_KEYS if k in meta})
            return [], False
        if kind == "plan":
            return plan_messages(self._t_s, item[1], item[2]), True
        if kind == "finish":
            return ([] if item[1] is None else [(RUN_TOPIC, self._t_s, dumps(item[1]))]), True
        if kind == "message":
            return [(item[1], self._t_s, dumps(item[2]))], True
        raise ValueError(f"unknown recorder item {kind!r}")

    def _emit(self, messages: list[Message], live: bool) -> None:
        if self.recording is not None:
            self.recording.write_all(messages)
        if self.live is not None and live and messages:
            wall0 = self._wall0_ns if self._wall0_ns is not None else time.time_ns() - int(self._t_s * 1e9)
            for topic, t_s, data in messages:
                self.live.publish(topic, wall0 + int(t_s * 1e9), data)

    def close(self) -> None:
        """Write everything queued, stop the thread, finish the recording (idempotent)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()
        self._drain()
        if self.recording is not None:
            self.recording.close()

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
    from falcon_plan.recording.mcapfile import McapRecording

    recording = None if mcap_path is None else McapRecording(mcap_path, metadata=metadata)
    return RunRecorder(recording, live)


__all__ = ["CONTROLLER_KEYS", "RunRecorder", "open_recorder"]
