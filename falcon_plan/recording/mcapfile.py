"""MCAP files: the one writer (:class:`McapRecording`) and the one reader (:func:`read_mcap`).

**Never an unreadable file.** A recording is written in place and in chunks: every
``chunk_period_s`` of log time (0.5 s) the chunk in progress is compressed (zstd), written
with its message index and handed to the operating system, so a process killed outright
(SIGKILL, power loss of the process) leaves every finished chunk readable and loses at most
the last one. :meth:`McapRecording.close` writes the summary and footer; it runs on every exit
the process sees: ``with`` blocks and ``finally`` on exceptions and Ctrl-C (KeyboardInterrupt),
SIGTERM (while a recording is open in the main thread and nobody else handles SIGTERM, it
raises SystemExit(143) so that the same blocks run) and interpreter exit (atexit, for a
recording nobody closed).

The reader reads records in file order (:class:`mcap.stream_reader.StreamReader`), so a file
cut short (no footer: a killed writer) reads up to its last complete chunk, with a warning;
:func:`copy_recording` rewrites such a file as a complete one (``falcon-plan convert``).
"""
from __future__ import annotations

import atexit
import contextlib
import json
import logging
import os
import signal
import struct
import threading
import weakref
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

from falcon_plan.errors import LogFormatError, OutputError
from falcon_plan.fileio import FILE_MODE, check_writable
from falcon_plan.recording.channels import (COMMANDS_TOPIC, LEGS_TOPIC, LOG_META_NAME, REFERENCE_TOPIC, RUN_TOPIC,
                                            TIMING_TOPIC, TOPICS, schema_bytes)

_log = logging.getLogger(__name__)

MCAP_MAGIC = b"\x89MCAP0\r\n"
"""The first (and last) 8 bytes of an MCAP file."""
CHUNK_PERIOD_S = 0.5
"""A chunk is closed and handed to the OS after this much log time [s]: the most a SIGKILL loses."""
CHUNK_SIZE_BYTES = 4 * 1024 * 1024
"""...or once it holds this much uncompressed data."""


def is_mcap(path: str | os.PathLike[str]) -> bool:
    """True when the file at ``path`` starts with the MCAP magic (False if it cannot be read)."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


def versions() -> dict[str, str]:
    """Versions of falcon-plan and of the libraries a recording depends on (name -> version)."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    out = {"python": platform.python_version()}
    for dist in ("falcon-plan", "numpy", "casadi", "mcap", "foxglove-sdk"):
        try:
            out[dist] = version(dist)
        except PackageNotFoundError:
            out[dist] = "not installed"
    return out


# --- exit paths -------------------------------------------------------------------------------

_open_recordings: "weakref.WeakSet[McapRecording]" = weakref.WeakSet()
_signal_lock = threading.Lock()
_installed_sigterm: Any = None  # the handler this module installed, while installed


def _raise_on_sigterm(signum: int, _frame: Any) -> None:
    raise SystemExit(128 + signum)


def _take_sigterm() -> None:
    """While recordings are open: SIGTERM -> SystemExit in the main thread, if SIGTERM has no
    handler of its own (the service has one: it stops and closes its recordings itself)."""
    global _installed_sigterm
    if threading.current_thread() is not threading.main_thread():
        return
    with _signal_lock:
        if _installed_sigterm is None and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            signal.signal(signal.SIGTERM, _raise_on_sigterm)
            _installed_sigterm = _raise_on_sigterm


def _release_sigterm() -> None:
    global _installed_sigterm
    if threading.current_thread() is not threading.main_thread():
        return
    with _signal_lock:
        if _installed_sigterm is not None and not len(_open_recordings):
            if signal.getsignal(signal.SIGTERM) is _installed_sigterm:
                signal.signal(signal.SIGTERM, signal.SIG_DFL)
            _installed_sigterm = None


@atexit.register
def _close_open_recordings() -> None:
    for recording in list(_open_recordings):
        recording.close()


# --- writing ----------------------------------------------------------------------------------

class McapRecording:
    """An MCAP file being written: JSON messages on topics, chunked, finished on every exit path
    (module docstring). Thread-safe; a context manager.

    Parameters
    ----------
    path : the file to create (replaced if it exists); OutputError when it cannot be written.
    chunk_period_s : log time per chunk [s] (the most a SIGKILL loses).
    metadata : MCAP metadata records to write at once (name -> {key: value}); the versions of
        falcon-plan and its libraries are always written (record ``versions``).
    """

    def __init__(self, path: str | os.PathLike[str], *, chunk_period_s: float = CHUNK_PERIOD_S,
                 metadata: dict[str, dict[str, str]] | None = None) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = check_writable(path, "MCAP recording")
        self.chunk_period_s = float(chunk_period_s)
        self.messages = 0
        self._lock = threading.RLock()
        try:
            self._file: BinaryIO | None = open(self.path, "wb")
            os.fchmod(self._file.fileno(), FILE_MODE)
        except OSError as exc:
            raise OutputError(f"cannot write MCAP recording {self.path}: {exc.strerror or exc}") from exc
        self._writer = Writer(self._file, chunk_size=CHUNK_SIZE_BYTES, compression=CompressionType.ZSTD)
        found = versions()
        self._writer.start(profile="", library=f"falcon-plan {found['falcon-plan']}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._chunk_start_s: float | None = None
        _open_recordings.add(self)
        _take_sigterm()
        self.metadata("versions", found)
        for name, values in (metadata or {}).items():
            self.metadata(name, values)
        self._flush()

    @property
    def closed(self) -> bool:
        """True once the footer is written."""
        return self._file is None

    def metadata(self, name: str, values: dict[str, str]) -> None:
        """Write a metadata record ``name`` holding ``values`` (strings), at once (it survives a
        kill)."""
        with self._lock:
            self._require_open()
            self._writer.add_metadata(name, {str(k): str(v) for k, v in values.items()})
            self._flush()

    def channel(self, topic: str, schema_name: str | None = None, schema_data: bytes | None = None) -> int:
        """The channel id of ``topic`` (registered on first use): its schema is ``schema_name``
        (default: the topic's in :data:`~falcon_plan.recording.channels.TOPICS`) with the JSON
        Schema ``schema_data`` (default: the one in SCHEMAS)."""
        with self._lock:
            if topic not in self._channels:
                self._require_open()
                name = schema_name or TOPICS[topic]
                if name not in self._schemas:
                    data = schema_data if schema_data is not None else schema_bytes(name)
                    self._schemas[name] = self._writer.register_schema(name, "jsonschema", data)
                self._channels[topic] = self._writer.register_channel(topic, "json", self._schemas[name])
            return self._channels[topic]

    def write(self, topic: str, t_s: float, data: bytes) -> None:
        """Add the JSON message ``data`` on ``topic`` at log time ``t_s`` [s, >= 0]; closes the
        chunk when it spans ``chunk_period_s``."""
        self.write_all([(topic, t_s, data)])

    def write_all(self, messages: Any) -> None:
        """Add every (topic, log time [s], JSON data) of ``messages`` (e.g. one row's), then
        close the chunk if it spans ``chunk_period_s`` (so a row's messages share a chunk)."""
        with self._lock:
            t_s = None
            for topic, t_s, data in messages:
                ns = int(round(max(0.0, t_s) * 1e9))
                self._writer.add_message(self.channel(topic), log_time=ns, data=data, publish_time=ns)
                self.messages += 1
            if t_s is None:
                return
            if self._chunk_start_s is None:
                self._chunk_start_s = t_s
            elif abs(t_s - self._chunk_start_s) >= self.chunk_period_s:
                self._flush()

    def _flush(self) -> None:
        """Close the chunk in progress and hand everything to the OS."""
        self._writer.flush()
        self._chunk_start_s = None

    def _require_open(self) -> None:
        if self._file is None:
            raise OutputError(f"MCAP recording {self.path} is already closed")

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent; never raises over an
        error already on its way: a failure is logged)."""
        with self._lock:
            if self._file is None:
                return
            handle, self._file = self._file, None
            try:
                self._writer.finish()
                handle.flush()
            except (OSError, ValueError) as exc:
                _log.error("finishing MCAP recording %s failed: %s", self.path, exc)
            finally:
                handle.close()
                _open_recordings.discard(self)
        _release_sigterm()

    def __enter__(self) -> "McapRecording":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# --- reading ----------------------------------------------------------------------------------

@dataclass
class McapContents:
    """What a file holds, read in file order: ``schemas`` (name -> (encoding, data)),
    ``channels`` (topic -> schema name), ``messages`` ((topic, log time [ns], data) in file
    order), ``metadata`` (name -> values) and whether the file is ``complete`` (it has its
    footer; False: cut short, read up to its last complete chunk)."""

    schemas: dict[str, tuple[str, bytes]] = field(default_factory=dict)
    channels: dict[str, str] = field(default_factory=dict)
    messages: list[tuple[str, int, bytes]] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = False

    def topic(self, name: str) -> Iterator[tuple[int, bytes]]:
        """(log time [ns], data) of the messages on topic ``name``, in file order."""
        return ((t, data) for topic, t, data in self.messages if topic == name)


def scan(path: str | os.PathLike[str], topics: set[str] | None = None) -> McapContents:
    """Read the MCAP file at ``path`` (only the messages of ``topics`` if given). A file cut
    short is read up to its last complete chunk (``complete`` False); LogFormatError when it is
    not an MCAP file or cannot be opened."""
    import zstandard
    from mcap.exceptions import McapError
    from mcap.records import Channel, Footer, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    path = Path(path)
    if not is_mcap(path):
        if not path.exists():
            raise LogFormatError(f"{path}: no such file")
        if path.stat().st_size < len(MCAP_MAGIC):
            raise LogFormatError(f"{path}: empty, or cut short before its first bytes (not yet an MCAP file)")
        raise LogFormatError(f"{path}: not an MCAP file (it does not start with the MCAP magic bytes)")
    out = McapContents()
    schema_names: dict[int, str] = {}
    topic_of: dict[int, str] = {}
    with open(path, "rb") as handle:
        size = os.fstat(handle.fileno()).st_size
        reader = StreamReader(handle, record_size_limit=max(size, 1 << 20))
        try:
            for record in reader.records:
                if isinstance(record, Message):
                    topic = topic_of.get(record.channel_id)
                    if topic is not None and (topics is None or topic in topics):
                        out.messages.append((topic, record.log_time, record.data))
                elif isinstance(record, Channel):
                    topic_of[record.id] = record.topic
                    out.channels[record.topic] = schema_names.get(record.schema_id, "")
                elif isinstance(record, Schema):
                    schema_names[record.id] = record.name
                    out.schemas[record.name] = (record.encoding, record.data)
                elif isinstance(record, Metadata):
                    out.metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Footer):
                    out.complete = True
        except (McapError, struct.error, EOFError, zstandard.ZstdError, ValueError, MemoryError) as exc:
            if out.complete:
                raise LogFormatError(f"{path}: damaged MCAP file ({exc})") from None
    return out


def _require_channels(contents: McapContents, path: str | os.PathLike[str]) -> None:
    """LogFormatError when the file at ``path`` (read into ``contents`` by :func:`scan`) was cut
    short before its first channel: no footer and no channel, nothing to read or copy. (Not in
    :func:`scan` itself: a recording being written is scanned while it has none yet.)"""
    if not contents.complete and not contents.channels:
        raise LogFormatError(f"{path}: this MCAP file was cut short before its first channel (no footer, no "
                             "channels): it holds nothing to read or copy")


def read_mcap(path: str | os.PathLike[str]) -> Any:
    """The :class:`~falcon_plan.falconlog.FalconLog` recorded in the MCAP file at ``path``: its
    rows from the per-row channels (counts from /falcon/legs, commands from /falcon/commands,
    planned counts from /falcon/reference, further columns that FalconLog has from
    /falcon/timing) and its metadata from the ``falcon_log`` metadata record (with the run's
    status from /falcon/run as its ``end``, as a CSV log's end line, when that has none). A recording cut
    short reads up to its last complete chunk, with a warning. LogFormatError (naming the
    file) when it is not an MCAP file or holds no falcon log."""
    from falcon_plan.falconlog import END_KEY, FalconLog

    path = Path(path)
    per_row = (LEGS_TOPIC, COMMANDS_TOPIC, REFERENCE_TOPIC, TIMING_TOPIC)
    contents = scan(path, set(per_row) | {RUN_TOPIC})
    _require_channels(contents, path)
    if LEGS_TOPIC not in contents.channels or COMMANDS_TOPIC not in contents.channels:
        raise LogFormatError(f"{path}: this MCAP file has no {LEGS_TOPIC} and {COMMANDS_TOPIC} channels (it was "
                             "not recorded by falcon-plan); topics: " + (", ".join(sorted(contents.channels)) or "none"))
    legs, commands, reference, timing = ([json.loads(data) for _, data in contents.topic(topic)] for topic in per_row)
    n = min(len(legs), len(commands))  # a chunk boundary may fall between a row's messages
    legs, commands = legs[:n], commands[:n]
    reference = reference[:n] if len(reference) >= n else []
    timing = timing[:n] if len(timing) >= n else []
    meta = contents.metadata.get(LOG_META_NAME, {})
    runs = [json.loads(data) for _, data in contents.topic(RUN_TOPIC)]
    if END_KEY not in meta and runs and "status" in runs[-1]:   # how the recorded run ended, as the CSV's end line
        meta = {**meta, END_KEY: str(runs[-1]["status"])}
    if not contents.complete:
        _log.warning("%s: the recording was cut short (no footer): read %d rows up to its last complete chunk; "
                     "`falcon-plan convert` writes a complete copy", path, n)
    try:
        t = np.array([m["t_s"] for m in legs], dtype=float)
        for name, messages in (("commands", commands), ("reference", reference), ("timing", timing)):
            if messages and any(m["t_s"] != x for m, x in zip(messages, t)):
                raise ValueError(f"the {name} messages do not follow the legs messages row by row")
        enc = np.array([m["counts"] for m in legs], dtype=np.int64).reshape(n, 3)
        tc = np.array([m["command"] for m in commands], dtype=np.int64).reshape(n, 3)
        ref = np.array([m["counts"] for m in reference], dtype=float).reshape(n, 3) if reference and n else None
        known = {f.name for f in fields(FalconLog)} - {"t_s", "enc", "tc", "ref", "meta"}
        extra = {name: np.array([m[name] for m in timing], dtype=np.int64)
                 for name in known if timing and n and name in timing[0]}
        log = FalconLog(t, enc, tc, ref, meta, **extra)
    except (KeyError, TypeError, ValueError) as exc:
        raise LogFormatError(f"{path}: bad per-row messages ({type(exc).__name__}: {exc})") from None
    for note in log.notes:
        _log.warning("%s: %s", path, note)
    return log


def positions_of(counts: Any, params: Any) -> np.ndarray:
    """End-effector positions [m] (n, 3) of encoder ``counts`` (n, 3) for the parameter set
    ``params`` (batch forward kinematics); NaN rows where it has no solution."""
    from falcon_plan.errors import KinematicsError
    from falcon_plan.model.kinematics import PositionTracker, counts_to_angles, forward_kinematics

    counts = np.asarray(counts, dtype=float).reshape(-1, 3)
    try:
        return forward_kinematics(counts_to_angles(counts, params), params)
    except KinematicsError:  # some rows have no solution: point by point
        tracker, out = PositionTracker(params), np.full(counts.shape, np.nan)
        for k, row in enumerate(counts):
            try:
                out[k] = tracker.position(row)
            except KinematicsError:
                pass
        return out


def write_mcap_log(path: str | os.PathLike[str], log: Any, params: Any = None) -> Path:
    """Write the falcon log ``log`` (a :class:`~falcon_plan.falconlog.FalconLog`) as an MCAP
    recording at ``path``, with the channels a run records (the converter; atomic: a temporary
    file renamed into place). ``params``: the parameter set to turn counts into angles and
    positions (default: the one the log's metadata names, with its encoder offset)."""
    from falcon_plan.recording.channels import RowEncoder, command_limit_of, encoder_params_of

    params = params if params is not None else encoder_params_of(log.meta)
    encoder = RowEncoder(params, command_limit_of(log.meta, params))
    columns = [f.name for f in fields(log) if f.name not in ("t_s", "enc", "tc", "ref", "meta")
               and getattr(log, f.name) is not None]
    measured = positions_of(log.enc, params)
    planned = None if log.ref is None else positions_of(log.ref, params)
    model = {"params": params.name, "effects": log.meta.get("feedforward_effects", "{}")}
    with _whole(path) as tmp, McapRecording(tmp, metadata={LOG_META_NAME: log.meta, "model": model}) as recording:
        for k in range(len(log)):
            extra = {name: int(getattr(log, name)[k]) for name in columns}
            recording.write_all(encoder.encode(
                log.t_s[k], log.enc[k], log.tc[k], None if log.ref is None else log.ref[k], measured[k],
                None if planned is None else planned[k], extra or None))
    return Path(path)


@contextlib.contextmanager
def _whole(path: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path next to ``path``, renamed to it when the block succeeds (removed when it
    fails): a converted file appears whole or not at all."""
    import tempfile

    target = check_writable(path, "MCAP recording")
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, target)
    finally:
        Path(tmp).unlink(missing_ok=True)


def copy_recording(source: str | os.PathLike[str], target: str | os.PathLike[str]) -> McapContents:
    """Rewrite the MCAP recording ``source`` (possibly cut short) as the complete file
    ``target`` (whole: a temporary file renamed into place): every schema, channel, message and
    metadata record it holds. Returns what was read; LogFormatError when it was cut short
    before its first channel (nothing to copy)."""
    contents = scan(source)
    _require_channels(contents, source)
    with _whole(target) as tmp, McapRecording(tmp) as out:
        for name, values in contents.metadata.items():
            if name != "versions":
                out.metadata(name, values)
        for topic, schema in contents.channels.items():
            _, data = contents.schemas.get(schema, ("jsonschema", b""))
            out.channel(topic, schema or "unnamed", data)
        for topic, ns, data in contents.messages:
            out.write(topic, ns * 1e-9, data)
    return contents


__all__ = ["CHUNK_PERIOD_S", "MCAP_MAGIC", "McapContents", "McapRecording", "copy_recording", "is_mcap",
           "positions_of", "read_mcap", "scan", "versions", "write_mcap_log"]
