"""The falcon log: a CSV of encoder counts and motor commands over time.

Format (MODEL-CONVENTIONS "Measured-data files"):

- optional metadata lines before the header, ``# key: value`` (e.g. ``# rate_hz: 800``,
  ``# controller: pd kp=10 kd=0.1``, ``# params: acra2009``); readers ignore unknown keys;
- the header ``t,enc0,enc1,enc2,tc0,tc1,tc2``, optionally followed by ``,ref0,ref1,ref2``
  and then optionally by ``,sent_us,read_us,skipped``;
- one row per sample: ``t`` [s], integer encoder counts ``enc*`` read at that sample, the
  integer command ``tc*`` sent at that sample, the encoder-space setpoint ``ref*``
  [counts, may be fractional], and what really happened in that tick (written by a host
  that runs in real time, :class:`TickTiming`): ``sent_us`` when the command was handed to
  the driver and ``read_us`` when the reading whose counts the row holds arrived, both on
  the host's monotonic clock [integer microseconds, arbitrary origin], and ``skipped``, the
  control slots the loop skipped just before this row because it was late (0 normally).

Rows are in strictly increasing time: a lost sample is a gap in ``t``, never a repeated row.
``t`` is the row's slot on the nominal grid (k / rate); the timing columns say when the tick
really ran. Logs without them (older logs, simulated runs) read as before.
:class:`LogWriter` streams rows, writing each as one whole line and flushing it, so a run cut
short (crash, kill) leaves a complete, readable file. A run's log ends with the end line
``# end: STATUS`` (:data:`END_KEY`: ``completed``, ``cancelled``, ``safety_stop``,
``device_error``, or ``interrupted`` when the process was stopped mid-run), the only metadata
line allowed after the rows; a log without it (older logs, a killed process) has no ``end``.
"""
from __future__ import annotations

import logging
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Iterator

import numpy as np

from falcon_plan.errors import InvalidParameterError, LogFormatError
from falcon_plan.fileio import check_writable, write_text

_log = logging.getLogger(__name__)

BASE_COLUMNS = ("t", "enc0", "enc1", "enc2", "tc0", "tc1", "tc2")
REF_COLUMNS = ("ref0", "ref1", "ref2")
TIMING_COLUMNS = ("sent_us", "read_us", "skipped")
"""The optional per-tick timing columns (see :class:`TickTiming`)."""
HEADERS = (BASE_COLUMNS, BASE_COLUMNS + REF_COLUMNS, BASE_COLUMNS + TIMING_COLUMNS,
           BASE_COLUMNS + REF_COLUMNS + TIMING_COLUMNS)
"""The headers a falcon log may have."""


@dataclass(frozen=True)
class TickTiming:
    """What really happened in one loop tick (one falcon-log row).

    ``sent_us`` : when the row's command was handed to the driver [us, host monotonic clock].
    ``read_us`` : when the reading whose counts the row holds arrived at the host [us, same
        clock] (the driver's arrival time where it knows it, e.g. the threaded USB reader).
    ``skipped`` : control slots the loop skipped just before this row (it started more than
        one period late; the row's ``t`` then jumps by ``skipped + 1`` periods).
    """

    sent_us: int
    read_us: int
    skipped: int = 0


@dataclass(frozen=True, eq=False)
class FalconLog:
    """One falcon log in memory.

    Attributes
    ----------
    t_s : (N,) float, sample times [s], strictly increasing.
    enc : (N, 3) int64, encoder counts of legs 0, 1, 2.
    tc : (N, 3) int64, commands sent at each sample.
    ref : (N, 3) float or None, encoder-space setpoint [counts].
    meta : metadata ``key -> value`` (strings).
    sent_us, read_us : (N,) int64 or None, when each row's command was handed to the driver
        and when its reading arrived [us, host monotonic clock] (:class:`TickTiming`).
    skipped : (N,) int64 or None, control slots skipped just before each row (>= 0).
    The three timing columns are all given or all None.
    """

    t_s: np.ndarray
    enc: np.ndarray
    tc: np.ndarray
    ref: np.ndarray | None = None
    meta: dict[str, str] = field(default_factory=dict)
    sent_us: np.ndarray | None = None
    read_us: np.ndarray | None = None
    skipped: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=float).reshape(-1)
        n = t.shape[0]
        enc = _as_int_columns(self.enc, n, "enc")
        tc = _as_int_columns(self.tc, n, "tc")
        ref = None
        if self.ref is not None:
            ref = np.asarray(self.ref, dtype=float)
            if ref.shape != (n, 3):
                raise LogFormatError(f"ref must have shape ({n}, 3), got {ref.shape}")
            if not np.isfinite(ref).all():
                raise LogFormatError("ref holds NaN or infinite values")
        if not np.isfinite(t).all():
            raise LogFormatError("t_s holds NaN or infinite values")
        if n > 1 and not (np.diff(t) > 0).all():
            k = int(np.argmin(np.diff(t) > 0)) + 1
            raise LogFormatError(f"t_s must be strictly increasing; sample {k} has t = {t[k]} "
                                 f"after {t[k - 1]}")
        for key, value in self.meta.items():
            _check_meta(str(key), str(value))
        timing = _timing_columns(self.sent_us, self.read_us, self.skipped, n)
        for name, arr in (("t_s", t), ("enc", enc), ("tc", tc), ("ref", ref), *zip(TIMING_COLUMNS, timing)):
            if arr is not None:
                arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "meta", {str(k): str(v) for k, v in self.meta.items()})

    def __len__(self) -> int:
        return int(self.t_s.shape[0])

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, FalconLog):
            return NotImplemented
        same_ref = (self.ref is None and other.ref is None) or (
            self.ref is not None and other.ref is not None and np.array_equal(self.ref, other.ref))
        same_timing = all((a is None and b is None) or (a is not None and b is not None and np.array_equal(a, b))
                          for a, b in zip(self.timing_columns, other.timing_columns))
        return (np.array_equal(self.t_s, other.t_s) and np.array_equal(self.enc, other.enc)
                and np.array_equal(self.tc, other.tc) and same_ref and same_timing and self.meta == other.meta)

    @property
    def timing_columns(self) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
        """(sent_us, read_us, skipped), each None when the log has no timing columns."""
        return self.sent_us, self.read_us, self.skipped

    @property
    def has_timing(self) -> bool:
        """True when the rows say when each tick really ran (:class:`TickTiming`)."""
        return self.sent_us is not None

    def timing(self, k: int) -> TickTiming | None:
        """Row ``k``'s :class:`TickTiming`, None without timing columns."""
        if self.sent_us is None or self.read_us is None or self.skipped is None:
            return None
        return TickTiming(int(self.sent_us[k]), int(self.read_us[k]), int(self.skipped[k]))

    def rows(self, start: int | None = None, stop: int | None = None) -> "FalconLog":
        """The rows ``start:stop`` (every column, the same metadata)."""
        cut = slice(start, stop)
        pick = lambda a: None if a is None else a[cut]  # noqa: E731
        return FalconLog(self.t_s[cut], self.enc[cut], self.tc[cut], pick(self.ref), self.meta,
                         *(pick(a) for a in self.timing_columns))

    @property
    def rate_hz(self) -> float | None:
        """The ``rate_hz`` metadata [Hz], or None if absent."""
        return parse_rate_hz(self.meta)

    @property
    def notes(self) -> list[str]:
        """Remarks a reader should see: samples missing (gaps in ``t``, against ``rate_hz`` or
        else the median period)."""
        if len(self) < 3:
            return []
        dt = np.diff(self.t_s)
        period = 1.0 / self.rate_hz if self.rate_hz else float(np.median(dt))
        lost = np.rint(dt / period).astype(int) - 1
        gaps = np.flatnonzero(lost > 0)
        if not len(gaps):
            return []
        k = int(gaps[np.argmax(dt[gaps])])
        return [f"{int(lost[gaps].sum())} sample(s) missing in {len(gaps)} gap(s) of t (longest "
                f"{1e3 * dt[k]:.1f} ms after t = {self.t_s[k]:.4f} s, period {1e3 * period:.3f} ms)"]

    @property
    def controller(self) -> "ControllerSpec | None":
        """The ``controller`` metadata parsed, or None if absent."""
        text = self.meta.get("controller")
        return None if text is None else parse_controller(text)


def _timing_columns(sent_us: Any, read_us: Any, skipped: Any, n: int) -> tuple[np.ndarray | None, ...]:
    """The timing columns checked: all None, or three (n,) whole-number columns with
    ``skipped`` >= 0."""
    given = [a is not None for a in (sent_us, read_us, skipped)]
    if not any(given):
        return None, None, None
    if not all(given):
        raise LogFormatError(f"the timing columns {', '.join(TIMING_COLUMNS)} go together: give all or none")
    out = []
    for name, values in zip(TIMING_COLUMNS, (sent_us, read_us, skipped)):
        arr = _as_int_columns(np.asarray(values).reshape(-1, 1), n, name, width=1).reshape(n)
        out.append(arr)
    if (out[2] < 0).any():
        raise LogFormatError("skipped must be >= 0 (slots skipped before a row)")
    return tuple(out)


def _as_int_columns(values: Any, n: int, name: str, width: int = 3) -> np.ndarray:
    arr = np.asarray(values)
    if arr.shape != (n, width):
        shape = f"({n}, {width})" if width != 1 else f"({n},)"
        raise LogFormatError(f"{name} must have shape {shape}, got {arr.shape}")
    if arr.dtype.kind == "f":
        if not np.isfinite(arr).all() or not np.array_equal(arr, np.round(arr)):
            raise LogFormatError(f"{name} must hold whole numbers")
    elif arr.dtype.kind not in "iu":
        raise LogFormatError(f"{name} must be integers, got dtype {arr.dtype}")
    return arr.astype(np.int64)


_META_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")


def _check_meta(key: str, value: str) -> None:
    if not _META_KEY.match(key):
        raise LogFormatError(f"metadata key {key!r} must be a word (letters, digits, _ . -)")
    if "\n" in value or "\r" in value:
        raise LogFormatError(f"metadata value of {key!r} must be one line")


# --- metadata helpers ------------------------------------------------------------------------

@dataclass(frozen=True)
class ControllerSpec:
    """A parsed ``controller`` metadata value, e.g. ``pd kp=10 kd=0.1``.

    ``kind`` is the first word (``pd``); ``gains`` maps each ``name=value`` to a float.
    """

    kind: str
    gains: dict[str, float]

    def __str__(self) -> str:
        return " ".join([self.kind] + [f"{k}={_fmt(v)}" for k, v in self.gains.items()])


def _fmt(value: float) -> str:
    return f"{value:g}" if value == float(f"{value:g}") else repr(float(value))


def parse_controller(text: str) -> ControllerSpec:
    """Parse ``text``, a ``controller`` metadata value such as ``"pd kp=10 kd=0.1"`` (a kind,
    then name=number words), into a :class:`ControllerSpec`; LogFormatError if malformed."""
    words = text.split()
    if not words or "=" in words[0]:
        raise LogFormatError(f"controller metadata {text!r} must start with a kind, e.g. 'pd kp=10 kd=0.1'")
    gains: dict[str, float] = {}
    for word in words[1:]:
        name, sep, value = word.partition("=")
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not sep or not name or not math.isfinite(number):
            raise LogFormatError(f"controller metadata {text!r}: {word!r} is not name=number")
        gains[name] = number
    return ControllerSpec(words[0], gains)


ZERO_FORCE_KEY = "zero_force_periods_before"
"""Log metadata: the periods of zero force the device had just before the first logged row
(the executor's first read sends zero force: 1; 0 when the run took the device over from a
:class:`~falcon_plan.execution.holding.HoldLoop`, whose last command its first read repeats),
so that a replay starts where the run did."""
DEVICE_CLOCK_KEY = "device_clock"
"""Log metadata: "wall" when the device lived through the time between ticks (a skipped slot
is time it moved on under the held command), "slots" when it lived the loop's slots exactly
(a simulated plant paced by the loop's deadlines: each row's command acts from its slot, held
through skipped ones), "ticks" when it stepped one period per tick (older simulated plants and
the emulated Falcon's packet clock: a skipped slot is time it never lived through): the
device's own ``device_clock`` ("wall" for a device that does not say, as real hardware)."""
END_KEY = "end"
"""Log metadata, written as the log's last line by the run that wrote it: how the run ended
(:class:`~falcon_plan.execution.executor.ExecutionStatus` values, or :data:`INTERRUPTED`); a
log whose ``end`` is not ``completed`` records less than the run was to do."""
INTERRUPTED = "interrupted"
"""The ``end`` of a run the process stopped mid-run (a second Ctrl-C, a signal, an unexpected
error): no status was reported."""
LINK_DELAY_KEY = "link_delay_samples"
"""Log metadata: the USB link's delay beyond the device's own command delay that the run
assumed [control periods, may be fractional, >= 0]: the model's measured one (``doctor``'s
model file) or the device's known one (:func:`~falcon_plan.control.link_delay_samples`);
0 for a device without a link (a simulated plant, blocking I/O). A replay delays the
commands by it (absent, in older logs: by the model's)."""


def parse_link_delay_samples(meta: dict[str, str]) -> float | None:
    """The :data:`LINK_DELAY_KEY` entry of ``meta`` (a log's metadata) [control periods], None
    if absent; LogFormatError if it is not a number in [0, 100]."""
    text = meta.get(LINK_DELAY_KEY)
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0.0 <= value <= 100.0):
        raise LogFormatError(f"{LINK_DELAY_KEY} metadata must be a number of periods in [0, 100], got {text!r}")
    return value


def parse_rate_hz(meta: dict[str, str]) -> float | None:
    """The ``rate_hz`` entry of ``meta`` (a log's metadata, name -> text) as a positive float
    [Hz], None if absent; LogFormatError if bad."""
    text = meta.get("rate_hz")
    if text is None:
        return None
    try:
        rate = float(text)
    except ValueError:
        rate = math.nan
    if not (math.isfinite(rate) and rate > 0):
        raise LogFormatError(f"rate_hz metadata must be a positive number, got {text!r}")
    return rate


def motion_start_s(meta: dict[str, str]) -> float:
    """When the move starts in a run's log [s from its first row], from its metadata ``meta``:
    ``motion_start_s`` (the approach and the hold at the start), else the executor's
    ``preroll_s``, else 0; LogFormatError if the entry is not a finite time >= 0."""
    text = meta.get("motion_start_s", meta.get("preroll_s", "0"))
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0.0):
        raise LogFormatError(f"motion_start_s / preroll_s metadata must be a finite time >= 0 s, got {text!r}")
    return value


# --- reading ---------------------------------------------------------------------------------


def _text_lines(handle: Any, path: Path) -> Iterator[str]:
    """The lines of the open text file ``handle``; LogFormatError naming ``path`` and the line
    when a byte is not UTF-8 (a binary file given as a falcon log)."""
    lineno = 0
    try:
        for lineno, line in enumerate(handle, start=1):
            yield line
    except UnicodeDecodeError:
        raise LogFormatError(f"{path}:{lineno + 1}: not text (a byte that is not UTF-8): is this a falcon log "
                             "CSV?") from None


def read_log(path: str | os.PathLike[str]) -> FalconLog:
    """Read the falcon log at ``path``. Raises :class:`LogFormatError` naming the file, line
    and problem (bad header, wrong column count, non-integer counts or commands, NaN, time not
    strictly increasing). Unknown metadata keys are kept in ``meta`` and otherwise ignored.
    An MCAP recording (:mod:`falcon_plan.recording`; any name but ``.csv``, known by its magic
    bytes) reads as the falcon log it recorded."""
    path = Path(path)
    if path.suffix.lower() != ".csv":
        from falcon_plan.recording.mcapfile import is_mcap, read_mcap

        if path.suffix.lower() == ".mcap" or is_mcap(path):
            return read_mcap(path)
    meta: dict[str, str] = {}
    header: list[str] | None = None
    with_ref, n_real = False, 7
    rows: list[list[float]] = []
    ints: list[list[int]] = []
    last_t = -math.inf
    ended = 0   # the line of a metadata line after the rows (the end line), 0 while none

    def fail(lineno: int, problem: str) -> LogFormatError:
        return LogFormatError(f"{path}:{lineno}: {problem}")

    try:
        handle = path.open("r", encoding="utf-8", newline="")
    except OSError as exc:
        raise LogFormatError(f"{path}: cannot open falcon log ({exc.strerror})") from exc
    with handle:
        for lineno, raw in enumerate(_text_lines(handle, path), start=1):
            line = raw.rstrip("\r\n")
            if header is None:
                if not line.strip():
                    continue
                if line.startswith("#"):
                    key, sep, value = line[1:].partition(":")
                    if sep and key.strip():
                        meta[key.strip()] = value.strip()
                    continue
                header = [c.strip() for c in line.split(",")]
                if tuple(header) not in HEADERS:
                    shown = repr(line[:60]) + ("..." if len(line) > 60 else "")
                    raise fail(lineno, f"bad header {shown}; expected {','.join(BASE_COLUMNS)} optionally "
                                       f"followed by ,{','.join(REF_COLUMNS)} and then by "
                                       f",{','.join(TIMING_COLUMNS)} (is this a falcon log CSV?)")
                with_ref = REF_COLUMNS[0] in header
                n_real = 7 + 3 * with_ref
                continue
            if not line.strip():
                continue
            if line.startswith("#"):   # the end line, after the rows: nothing may follow it
                key, sep, value = line[1:].partition(":")
                if key.strip() != END_KEY or not sep or ended:
                    raise fail(lineno, f"comment/metadata line after the header (only the end line "
                                       f"'# {END_KEY}: ...' may follow the rows, once)")
                meta[END_KEY] = value.strip()
                ended = lineno
                continue
            if ended:
                raise fail(lineno, f"row after the end line (line {ended})")
            cells = line.split(",")
            if len(cells) != len(header):
                raise fail(lineno, f"expected {len(header)} columns, got {len(cells)}")
            try:
                t = float(cells[0])
            except ValueError:
                raise fail(lineno, f"time {cells[0]!r} is not a number") from None
            if not math.isfinite(t):
                raise fail(lineno, f"time is {cells[0]!r} (NaN or infinite)")
            if t <= last_t:
                problem = "repeated row" if t == last_t else f"time not increasing ({t} after {last_t})"
                raise fail(lineno, problem)
            last_t = t
            counts: list[int] = []
            for name, cell in zip(header[1:7], cells[1:7]):
                try:
                    counts.append(int(cell))
                except ValueError:
                    raise fail(lineno, f"{name} = {cell!r} is not an integer") from None
            refs: list[float] = []
            for name, cell in zip(header[7:n_real], cells[7:n_real]):
                try:
                    value = float(cell)
                except ValueError:
                    raise fail(lineno, f"{name} = {cell!r} is not a number") from None
                if not math.isfinite(value):
                    raise fail(lineno, f"{name} is {cell!r} (NaN or infinite)")
                refs.append(value)
            for name, cell in zip(header[n_real:], cells[n_real:]):
                try:
                    counts.append(int(cell))
                except ValueError:
                    raise fail(lineno, f"{name} = {cell!r} is not an integer") from None
            rows.append([t] + refs)
            ints.append(counts)
    if header is None:
        raise LogFormatError(f"{path}: no header line (expected {','.join(BASE_COLUMNS)})")
    n = len(rows)
    t_s = np.array([r[0] for r in rows], dtype=float)
    with_timing = len(header) > n_real
    counts_arr = np.array(ints, dtype=np.int64).reshape(n, 9 if with_timing else 6)
    ref = np.array([r[1:] for r in rows], dtype=float).reshape(n, 3) if with_ref else None
    timing = tuple(counts_arr[:, 6 + i] for i in range(3)) if with_timing else (None, None, None)
    try:
        log = FalconLog(t_s, counts_arr[:, :3], counts_arr[:, 3:6], ref, meta, *timing)
    except LogFormatError as exc:
        raise LogFormatError(f"{path}: {exc}") from None
    notes = log.notes
    key = (str(path.resolve()), path.stat().st_mtime_ns) if notes else None
    if key is not None and key not in _WARNED:   # once per file version and process (a command may read a log twice)
        _WARNED.add(key)
        for note in notes:
            _log.warning("%s: %s", path, note)
    return log


_WARNED: set[tuple[str, int]] = set()
"""The log files (path, modification time) whose notes were logged as warnings already."""


# --- writing ---------------------------------------------------------------------------------

def _preamble(meta: dict[str, str], with_ref: bool, with_timing: bool = False) -> str:
    lines = []
    for key, value in meta.items():
        _check_meta(str(key), str(value))
        lines.append(f"# {key}: {value}\n")
    header = BASE_COLUMNS + (REF_COLUMNS if with_ref else ()) + (TIMING_COLUMNS if with_timing else ())
    lines.append(",".join(header) + "\n")
    return "".join(lines)


def _row(t: float, enc: Any, tc: Any, ref: Any | None, timing: TickTiming | None = None) -> str:
    cells = [repr(float(t))] + [str(int(x)) for x in enc] + [str(int(x)) for x in tc]
    if ref is not None:
        cells += [repr(float(x)) for x in ref]
    if timing is not None:
        cells += [str(int(timing.sent_us)), str(int(timing.read_us)), str(int(timing.skipped))]
    return ",".join(cells) + "\n"


def write_log(path: str | os.PathLike[str], log: FalconLog) -> None:
    """Write ``log`` to ``path`` atomically (:func:`falcon_plan.fileio.write_text`: mode 0644,
    a reader never sees a partial file; OutputError when it cannot be written). A ``.mcap``
    path gets an MCAP recording of the log (:func:`falcon_plan.recording.write_mcap_log`)."""
    if Path(path).suffix.lower() == ".mcap":
        from falcon_plan.recording.mcapfile import write_mcap_log

        write_mcap_log(path, log)
        return
    meta = dict(log.meta)
    end = meta.pop(END_KEY, None)
    text = [_preamble(meta, log.ref is not None, log.has_timing)]
    for k in range(len(log)):
        text.append(_row(log.t_s[k], log.enc[k], log.tc[k], None if log.ref is None else log.ref[k],
                         log.timing(k)))
    if end is not None:   # where the run that wrote the log put it: after the rows
        _check_meta(END_KEY, str(end))
        text.append(f"# {END_KEY}: {end}\n")
    write_text(path, "".join(text), "falcon log")


def _three(values: Any) -> list[float] | None:
    """``values`` as 3 floats, or None if they are not 3 numbers."""
    try:
        numbers = [float(x) for x in (values.tolist() if isinstance(values, np.ndarray) else values)]
    except (TypeError, ValueError):
        return None
    return numbers if len(numbers) == 3 else None


class LogWriter:
    """Streaming falcon-log writer (a context manager).

    The metadata and header are written when it opens; :meth:`write` checks and formats one
    row, and every ``flush_rows`` rows (and on :meth:`flush` and :meth:`close`) the rows so far
    go to the OS in one whole ``write`` call, so a process killed mid-run leaves a file that
    :func:`read_log` reads (every complete row, never half a row; at most the last
    ``flush_rows - 1`` rows lost). Rows must come in strictly increasing time (a gap is fine, a
    repeat is a :class:`LogFormatError`).

    Parameters
    ----------
    path : the file to create (replaced if it exists); OutputError when it cannot be written.
    meta : metadata ``key -> value`` written as ``# key: value`` lines (keys are words, values
        one line); None: none.
    with_ref : whether the log has the ``ref0..ref2`` setpoint columns (then every row needs
        a ``ref``, else none may have one).
    with_timing : whether the log has the timing columns (then every row needs a
        :class:`TickTiming`, else none may have one).
    flush_rows : rows per write to the OS, >= 1 (1: each row at once). A real-time loop passes
        more: a write call lets other threads take the interpreter lock, which the loop then
        waits for (the executor: 50 ms of rows).
    """

    def __init__(self, path: str | os.PathLike[str], meta: dict[str, str] | None = None,
                 with_ref: bool = False, with_timing: bool = False, flush_rows: int = 1) -> None:
        if isinstance(flush_rows, bool) or not isinstance(flush_rows, int) or flush_rows < 1:
            raise InvalidParameterError(f"flush_rows must be a whole number >= 1, got {flush_rows!r}")
        self.path = Path(path)
        self.flush_rows = flush_rows
        self._pending: list[str] = []
        self.with_ref = with_ref
        self.with_timing = with_timing
        self.rows = 0
        self._last_t = -math.inf
        preamble = _preamble(dict(meta or {}), with_ref, with_timing)
        check_writable(self.path, "falcon log")
        # Unbuffered binary: each flush goes to the OS in one write(2) call.
        self._file: Any = self.path.open("wb", buffering=0)
        self._file.write(preamble.encode("utf-8"))

    def write(self, t: float, enc: Any, tc: Any, ref: Any | None = None,
              timing: TickTiming | None = None) -> None:
        """Append one sample: time ``t`` [s] (after the previous row's), encoder counts ``enc``
        (3 whole numbers), commands ``tc`` (3 whole numbers) [command units], if the log
        has ref columns the setpoint ``ref`` (3 finite numbers) [counts], and if it has timing
        columns the tick's :class:`TickTiming`."""
        if self._file is None:
            raise LogFormatError(f"{self.path}: writer is closed")
        if (ref is None) == self.with_ref:
            raise LogFormatError(f"{self.path}: this log {'needs' if self.with_ref else 'has no'} "
                                 "ref columns")
        if (timing is None) == self.with_timing:
            raise LogFormatError(f"{self.path}: this log {'needs' if self.with_timing else 'has no'} "
                                 "timing columns")
        if timing is not None and timing.skipped < 0:
            raise LogFormatError(f"{self.path}: skipped must be >= 0, got {timing.skipped}")
        t = float(t)
        if not math.isfinite(t) or t <= self._last_t:
            raise LogFormatError(f"{self.path}: row time {t} must be finite and after {self._last_t}")
        # plain Python on 3 numbers: numpy's per-call overhead would dominate a 1 kHz loop
        enc_v, tc_v = self._whole("enc", enc), self._whole("tc", tc)
        ref_v = None if ref is None else _three(ref)
        if ref is not None and (ref_v is None or not all(math.isfinite(x) for x in ref_v)):
            raise LogFormatError(f"{self.path}: ref must be 3 finite numbers, got {ref!r}")
        self._pending.append(_row(t, enc_v, tc_v, ref_v, timing))
        self._last_t = t
        self.rows += 1
        if len(self._pending) >= self.flush_rows:
            self.flush()

    def flush(self) -> None:
        """Hand the rows written since the last flush to the OS, in one write call."""
        if self._pending and self._file is not None:
            text, self._pending = "".join(self._pending), []
            self._file.write(text.encode("utf-8"))

    def _whole(self, name: str, values: Any) -> list[float]:
        """``values`` as 3 whole numbers; LogFormatError naming ``name`` otherwise."""
        numbers = _three(values)
        if numbers is None or not all(math.isfinite(x) and x == int(x) for x in numbers):
            raise LogFormatError(f"{self.path}: {name} must be 3 whole numbers, got {values!r}")
        return numbers

    def close(self, end: str | None = None) -> None:
        """Write the rows not yet flushed, then with ``end`` the end line ``# end: END`` (how
        the run ended, :data:`END_KEY`), and close the file (idempotent; the file is closed
        even when that write fails, whose error is raised)."""
        if self._file is not None:
            try:
                if end is not None:
                    _check_meta(END_KEY, end)
                    self._pending.append(f"# {END_KEY}: {end}\n")
                self.flush()
            finally:
                self._file.close()
                self._file = None

    def __enter__(self) -> "LogWriter":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


__all__ = ["FalconLog", "TickTiming", "ControllerSpec", "LogWriter", "read_log", "write_log",
           "parse_controller", "parse_rate_hz", "parse_link_delay_samples", "motion_start_s", "END_KEY", "INTERRUPTED", "LINK_DELAY_KEY",
           "ZERO_FORCE_KEY", "DEVICE_CLOCK_KEY", "BASE_COLUMNS", "REF_COLUMNS", "TIMING_COLUMNS", "HEADERS"]
