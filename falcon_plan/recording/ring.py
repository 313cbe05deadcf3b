"""The hand-off of falcon-log rows from the control loop to the recording process: a ring of
fixed-size rows in memory both processes map (an anonymous memory file passed to the child by
its descriptor: no name in the file system, nothing left behind however the processes end).

One producer (the loop's process, under its own lock) writes row ``i`` into slot ``i mod
capacity`` and then the count of rows written (the head); one consumer (the recording process)
reads the rows between its tail and the head, and then writes how many it has taken. Writing
a row is one ``struct.pack_into`` and no system call (2 us warm, 5 to 10 us with cold
caches). A consumer that falls more than ``capacity`` rows behind loses the oldest:
:meth:`RowRing.take` says how many.

A row holds, as float64: the session id, ``t_s`` [s], counts (3), commands (3), planned counts
(3), measured and planned end-effector positions [m] (3 + 3; NaN where unknown), the tick's
timing columns (:class:`~falcon_plan.falconlog.TickTiming`'s fields; NaN on unpaced runs) and
a flag word (bit 0: planned counts given). Whole numbers up to 2**53 are exact in float64.
"""
from __future__ import annotations

import dataclasses
import math
import mmap
import operator
import os
import struct
import tempfile
from typing import Any, NamedTuple

from falcon_plan.falconlog import TickTiming

TIMING_COLUMNS = tuple(f.name for f in dataclasses.fields(TickTiming))
"""The per-tick timing columns a row carries, in order."""
_TIMING_AT = 17
_FLAGS_AT = _TIMING_AT + len(TIMING_COLUMNS)
_ROW = struct.Struct(f"<{_FLAGS_AT + 1}d")
_timing_of = operator.attrgetter(*TIMING_COLUMNS)
_HEAD = struct.Struct("<q")
_TAKEN_AT = 8  # after the head: the rows the consumer has taken
_DATA_OFFSET = 64
DEFAULT_CAPACITY = 32768
"""Rows the ring holds (33 s at 1 kHz, 5.5 MB): how far the recording process, which runs at
a low priority, may fall behind while the machine is busy."""
_NAN3 = (math.nan, math.nan, math.nan)
_NO_TIMING = (math.nan,) * len(TIMING_COLUMNS)
_HAS_REF = 1


class Row(NamedTuple):
    """One row as the recording process reads it (arrays as tuples; positions NaN where unknown,
    ``ref`` and ``timing`` None where not given)."""

    session: int
    t_s: float
    enc: tuple[int, int, int]
    tc: tuple[int, int, int]
    ref: tuple[float, float, float] | None
    measured_m: tuple[float, float, float]
    planned_m: tuple[float, float, float]
    timing: dict[str, int] | None


class RowRing:
    """The ring of ``capacity`` rows in the memory file ``fd`` (:meth:`create` makes one)."""

    def __init__(self, fd: int, capacity: int = DEFAULT_CAPACITY) -> None:
        self.fd, self.capacity = fd, int(capacity)
        self._map = mmap.mmap(fd, _DATA_OFFSET + self.capacity * _ROW.size)
        self._head = _HEAD.unpack_from(self._map, 0)[0]  # rows written so far (producer's copy)
        self.tail = self._head  # rows read so far (consumer)

    @classmethod
    def create(cls, capacity: int = DEFAULT_CAPACITY) -> "RowRing":
        """A new ring of ``capacity`` rows in an anonymous memory file (memfd; a nameless
        temporary file elsewhere)."""
        if hasattr(os, "memfd_create"):
            fd = os.memfd_create("falcon-plan-rows")
        else:  # pragma: no cover - not Linux
            handle = tempfile.TemporaryFile()
            fd = os.dup(handle.fileno())
            handle.close()
        os.ftruncate(fd, _DATA_OFFSET + capacity * _ROW.size)
        ring = cls(fd, capacity)
        ring._map.write(bytes(len(ring._map)))  # every page in place now, not faulted in by the loop
        return ring

    # --- the producer (the control loop) ---------------------------------------------------
    def put(self, session: int, t_s: float, enc: Any, tc: Any, ref: Any, measured_m: Any, planned_m: Any,
            timing: Any) -> int:
        """Write one row of recorder ``session`` at ``t_s`` [s]: ``enc`` [counts], ``tc``
        [command units], ``ref`` [counts], ``measured_m`` and ``planned_m`` [m] (numpy arrays
        of 3; the last three may be None), ``timing`` a TickTiming or None; returns the head
        after it."""
        i = self._head
        _ROW.pack_into(self._map, _DATA_OFFSET + (i % self.capacity) * _ROW.size, session, t_s,
                       *enc.tolist(), *tc.tolist(), *(_NAN3 if ref is None else ref.tolist()),
                       *(_NAN3 if measured_m is None else measured_m.tolist()),
                       *(_NAN3 if planned_m is None else planned_m.tolist()),
                       *(_NO_TIMING if timing is None else _timing_of(timing)), 0 if ref is None else _HAS_REF)
        self._head = i + 1
        _HEAD.pack_into(self._map, 0, i + 1)  # after the row: the consumer never reads a row before it is whole
        return i + 1

    @property
    def head(self) -> int:
        """Rows written so far."""
        return _HEAD.unpack_from(self._map, 0)[0]

    # --- the consumer (the recording process) ----------------------------------------------
    def take(self, upto: int | None = None) -> tuple[list[Row], int]:
        """The rows from the tail up to ``upto`` (default: the head), and how many older ones
        were overwritten before they could be read (lost). An ``upto`` the tail has passed
        (an item sent from another thread while rows flowed, read after a drain took later
        rows) takes nothing: the tail never moves back, so no row is handed over twice."""
        head = self.head if upto is None else int(upto)
        if head <= self.tail:
            return [], 0
        lost = max(0, head - self.capacity - self.tail)
        first = self.tail + lost
        rows = [self._read(i) for i in range(first, head)]
        newest = self.head  # a slot read while the producer went on may have been overwritten
        torn = max(0, newest - self.capacity - first)
        self.tail = head
        _HEAD.pack_into(self._map, _TAKEN_AT, head)
        return rows[torn:], lost + torn

    @property
    def taken(self) -> int:
        """Rows the consumer has taken so far (how the producer sees it progress)."""
        return _HEAD.unpack_from(self._map, _TAKEN_AT)[0]

    def _read(self, i: int) -> Row:
        v = _ROW.unpack_from(self._map, _DATA_OFFSET + (i % self.capacity) * _ROW.size)
        times = v[_TIMING_AT:_FLAGS_AT]
        timing = None if math.isnan(times[0]) else dict(zip(TIMING_COLUMNS, map(int, times)))
        return Row(int(v[0]), v[1], (int(v[2]), int(v[3]), int(v[4])), (int(v[5]), int(v[6]), int(v[7])),
                   v[8:11] if int(v[_FLAGS_AT]) & _HAS_REF else None, v[11:14], v[14:17], timing)

    def close(self) -> None:
        """Unmap the ring and close its descriptor (idempotent)."""
        if not self._map.closed:
            self._map.close()
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


__all__ = ["DEFAULT_CAPACITY", "Row", "RowRing", "TIMING_COLUMNS"]
