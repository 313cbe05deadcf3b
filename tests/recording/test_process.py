"""The recording process: the row ring hands rows over whole and in order (and counts what a
consumer that fell behind lost); the process finishes its files when the parent exits without
closing, reports its errors in the parent, and is never left behind."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from falcon_plan.errors import InvalidParameterError, OutputError
from falcon_plan.falconlog import TickTiming, read_log
from falcon_plan.recording.ring import RowRing

ROOT = Path(__file__).resolve().parents[2]


def _running(pid: int) -> bool:
    """True while process ``pid`` exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _gone(pid: int, timeout_s: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while _running(pid):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def test_the_ring_hands_rows_over_whole_and_counts_what_was_lost() -> None:
    producer = RowRing.create(capacity=8)
    consumer = RowRing(os.dup(producer.fd), capacity=8)  # the other process's view of the same memory
    try:
        for k in range(5):
            producer.put(3, k * 1e-3, np.array([k, -k, 2**40 + k]), np.array([1, 2, 3]),
                         None if k == 1 else np.array([k + 0.5, 0.0, -1.0]), np.array([0.0, np.nan, 0.1]),
                         np.array([0.0, 0.0, 0.12]), None if k == 2 else TickTiming(10**12 + k, 10**12 - k, k))
        rows, lost = consumer.take()
        assert lost == 0 and [r.t_s for r in rows] == [k * 1e-3 for k in range(5)]
        assert rows[4].session == 3 and rows[4].enc == (4, -4, 2**40 + 4) and rows[4].tc == (1, 2, 3)
        assert rows[4].ref == (4.5, 0.0, -1.0) and rows[1].ref is None
        assert rows[4].timing == {"sent_us": 10**12 + 4, "read_us": 10**12 - 4, "skipped": 4} and rows[2].timing is None
        assert rows[0].measured_m[1] != rows[0].measured_m[1] and rows[0].planned_m == (0.0, 0.0, 0.12)  # NaN kept
        for k in range(5, 25):  # 20 rows into 8 slots: the 12 oldest are overwritten before they are read
            producer.put(3, k * 1e-3, np.array([k, 0, 0]), np.zeros(3, np.int64), None, None, None, None)
        rows, lost = consumer.take()
        assert lost == 12 and [r.enc[0] for r in rows] == list(range(17, 25))
        assert consumer.take() == ([], 0) and producer.taken == 25  # the producer sees the consumer's progress
        # an item that read the head (25) before rows 25..27 came and a drain took them: up to 25
        # is taken already; the tail stays, so the next drain hands over only the rows after it
        for k in range(25, 30):
            producer.put(3, k * 1e-3, np.array([k, 0, 0]), np.zeros(3, np.int64), None, None, None, None)
            if k == 27:
                assert [r.enc[0] for r in consumer.take()[0]] == [25, 26, 27]
        assert consumer.take(25) == ([], 0) and producer.taken == 28
        assert [r.enc[0] for r in consumer.take()[0]] == [28, 29]
    finally:
        producer.close()
        consumer.close()


_UNCLOSED = """
import sys
import numpy as np
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.recording.recorder import RunRecorder

recorder = RunRecorder(sys.argv[1])  # never closed: the interpreter's exit finishes the file
recorder.start({"rate_hz": "1000"}, FalconModel())
for k in range(1500):
    recorder.row(k * 1e-3, np.array([k, 0, -k]), np.array([1, 2, 3]), np.array([k, 0.0, -k]))
print(recorder._process.pid, flush=True)
"""


@pytest.mark.slow
def test_a_recording_nobody_closed_is_finished_at_exit_and_its_process_ends(tmp_path: Path) -> None:
    path = tmp_path / "unclosed.mcap"
    done = subprocess.run([sys.executable, "-c", _UNCLOSED, str(path)], env={**os.environ, "PYTHONPATH": str(ROOT)},
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert _gone(int(done.stdout.split()[0]))
    from falcon_plan.recording.mcapfile import scan

    assert scan(path).complete
    log = read_log(path)
    assert len(log) == 1500 and log.enc[-1].tolist() == [1499, 0, -1499] and log.ref[-1].tolist() == [1499, 0, -1499]


def test_errors_of_the_recording_process_are_raised_in_the_caller(tmp_path: Path,
                                                                  caplog: pytest.LogCaptureFixture) -> None:
    from falcon_plan.recording.live import LiveView
    from falcon_plan.recording.recorder import RecorderProcess, RecordingProcessError, RunRecorder

    with pytest.raises(OutputError, match="folder .* does not exist"):
        RunRecorder(tmp_path / "missing" / "run.mcap")
    with socket.socket() as taken:  # a port in use: the server cannot start in the recording process
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        with pytest.raises(InvalidParameterError, match="cannot start the Foxglove server on 127.0.0.1:"):
            LiveView(port=taken.getsockname()[1])
    with pytest.raises(InvalidParameterError, match="0..65535"):
        LiveView(port=70000)
    assert not caplog.records  # one error, said once
    with RecorderProcess() as process:
        pid = process.pid
        assert pid is not None and _running(pid)
        # an unknown recorder: the process's error comes back here, and the process goes on
        with pytest.raises(RecordingProcessError, match="7777"):
            process.request("close", 7777)
        assert process.request("watched") is False
    assert _gone(pid, 5.0)


def test_the_loop_process_gets_no_thread_from_recording_or_the_live_view(model: Any, tmp_path: Path) -> None:
    from falcon_plan.recording.live import LiveView
    from falcon_plan.recording.recorder import RunRecorder

    def threads() -> int:  # the process's threads, Python's and native ones (e.g. a server's runtime)
        return len(os.listdir("/proc/self/task"))

    before = threads()
    with LiveView(port=0) as live, RunRecorder(tmp_path / "run.mcap", live) as recorder:
        recorder.start({"rate_hz": "1000"}, model)
        for k in range(100):
            recorder.row(k * 1e-3, np.array([k, 0, 0]), np.zeros(3, np.int64))
        assert threads() == before and live.watched is False
    assert len(read_log(tmp_path / "run.mcap")) == 100


def test_a_recorder_whose_process_died_notes_it_and_goes_on(model: Any, tmp_path: Path) -> None:
    from falcon_plan.recording.recorder import RunRecorder

    recorder = RunRecorder(tmp_path / "run.mcap")
    recorder.start({"rate_hz": "1000"}, model)
    os.kill(recorder._process.pid, 9)
    assert _gone(recorder._process.pid, 10.0)
    for k in range(10):
        recorder.row(k * 1e-3, np.zeros(3, np.int64), np.zeros(3, np.int64))
    recorder.finish(None)
    recorder.close()
    assert recorder.failed and recorder.rows == 10


def test_a_drain_handles_the_items_sent_before_its_rows_first(model: Any, tmp_path: Path) -> None:
    """A recorder's ``start`` waiting in the pipe when a drain comes, with rows written after it
    in the ring (a busy machine let the loop run on before the recording process read the pipe):
    the drain handles the start first, so those rows are recorded, each once."""
    from multiprocessing.connection import Connection

    from falcon_plan.recording.worker import Worker, drain_in_order

    ring = RowRing.create(capacity=64)
    (control_read, control_write), (reply_read, reply_write) = os.pipe(), os.pipe()
    parent, control = Connection(control_write, readable=False), Connection(control_read, writable=False)
    reply, replies = Connection(reply_write, readable=False), Connection(reply_read, writable=False)
    worker = Worker(ring, None)
    try:
        parent.send(("open", ring.head, 1, str(tmp_path / "run.mcap"), None, False))
        parent.send(("start", ring.head, 1, {"rate_hz": "1000"}, model.params, 4096, {}))
        for k in range(10):  # the loop went on after sending its start
            ring.put(1, k * 1e-3, np.array([k, 0, 0]), np.zeros(3, np.int64), None, None, None, None)
        assert drain_in_order(worker, control, reply)
        answer = worker.item(("close", ring.head, 1))
        assert replies.recv() == ("ok", 1)  # the open's answer
    finally:
        for connection in (parent, control, reply, replies):
            connection.close()
        worker.close()
        ring.close()
    assert answer == {"rows": 10, "encoded": 10, "failed": False}
    assert read_log(tmp_path / "run.mcap").enc[:, 0].tolist() == list(range(10))
