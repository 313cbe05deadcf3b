"""Call a compiled CasADi Function with almost no overhead (the plant's hot path).

A Python call to a CasADi Function costs tens of microseconds, more than the simulated
plant's whole control period is allowed (25 us at 800 Hz for 50x real time). So the plant's
per-period Function is compiled to C (:mod:`falcon_plan.compiled.build`: once per machine, cached)
and its generated entry point is called through :mod:`ctypes`, with argument pointers and
work arrays set up once; inputs and outputs are numpy buffers that the caller fills and reads
in place. Without a compiler the same interface evaluates the uncompiled Function.
"""
from __future__ import annotations

import ctypes
from pathlib import Path

import casadi as ca
import numpy as np

from falcon_plan.compiled.build import build_shared_library
from falcon_plan.timing import give_way


class BufferedFunction:
    """A CasADi Function evaluated in place on numpy buffers.

    ``inputs[i]`` and ``outputs[j]`` are float64 arrays laid out column-major like the
    Function's i-th input and j-th output (shape (rows, cols) in Fortran order, or (rows,)
    for column vectors). Fill ``inputs``, call the object, read ``outputs``. With
    ``library`` (from :func:`build_library`) it runs the compiled C, else the CasADi
    virtual machine (the fallback); ``compiled`` says which. ``fn`` is the CasADi Function.
    A compiled call lets other threads run meanwhile (it releases the interpreter lock), unless
    ``hold_gil``: for calls of a few microseconds on a real-time loop's thread, which would
    otherwise wait up to a switch interval to get the lock back from a busy thread.
    """

    def __init__(self, fn: ca.Function, library: Path | None = None, hold_gil: bool = False) -> None:
        self.name = fn.name()
        self.function = fn
        self.inputs = [_buffer(fn.size_in(i)) for i in range(fn.n_in())]
        self.outputs = [_buffer(fn.size_out(j)) for j in range(fn.n_out())]
        self._entry = None
        self._hold_gil = hold_gil
        self._fed: dict[int, int] = {}          # uncompiled: input -> address it reads from
        if library is not None:
            self._bind(library, fn)

    @property
    def compiled(self) -> bool:
        """True when calls run the compiled C code."""
        return self._entry is not None

    def _bind(self, library: Path, fn: ca.Function) -> None:
        self._lib = (ctypes.PyDLL if self._hold_gil else ctypes.CDLL)(str(library))
        entry = getattr(self._lib, fn.name())
        entry.restype = ctypes.c_int
        entry.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                          ctypes.c_int]
        n_arg, n_res = fn.sz_arg(), fn.sz_res()
        self._arg = (ctypes.c_void_p * n_arg)(*([b.ctypes.data for b in self.inputs]
                                                + [None] * (n_arg - len(self.inputs))))
        self._res = (ctypes.c_void_p * n_res)(*([b.ctypes.data for b in self.outputs]
                                                + [None] * (n_res - len(self.outputs))))
        # casadi_int is 64-bit in the Python wheels (long long)
        self._iw = np.zeros(max(fn.sz_iw(), 1), dtype=np.int64)
        self._w = np.zeros(max(fn.sz_w(), 1))
        self._iw_ptr, self._w_ptr = self._iw.ctypes.data, self._w.ctypes.data
        self._entry = entry

    def feed(self, i: int, address: int) -> None:
        """Let input ``i`` read from the float64 memory at ``address`` (laid out as
        :attr:`inputs` ``[i]`` would be) instead of its own buffer, until fed again: a caller
        that picks one of many stored matrices per call passes its address and copies nothing.
        The caller keeps that memory alive. Uncompiled, each call copies it into the input's
        buffer first (the same results, for the fallback and for tests)."""
        if self._entry is None:
            self._fed[i] = address
        else:
            self._arg[i] = address

    def map_columns(self, columns: list[np.ndarray]) -> list[np.ndarray]:
        """Evaluate a Function mapped over C columns (points) on any number n of them.

        ``columns[i]`` (rows_i, n) feeds input i, C columns per call (the last call padded
        with a copy of its first column, any valid point); the inputs after them keep what the
        caller put there (e.g. the effect vector). Returns every output, (rows_j, n)."""
        n = columns[0].shape[1]
        chunk = self.inputs[0].shape[1]
        out = [np.empty((buf.shape[0], n)) for buf in self.outputs]
        for start in range(0, n, chunk):
            give_way()
            used = min(chunk, n - start)
            for buf, x in zip(self.inputs, columns):
                buf[:, :used] = x[:, start:start + used]
                buf[:, used:] = x[:, start:start + 1]
            self()
            for dest, buf in zip(out, self.outputs):
                dest[:, start:start + used] = buf.reshape(buf.shape[0], -1)[:, :used]
        return out

    def __call__(self) -> None:
        """Evaluate: read ``inputs``, overwrite ``outputs``."""
        if self._entry is not None:
            if self._entry(self._arg, self._res, self._iw_ptr, self._w_ptr, 0) != 0:
                raise RuntimeError(f"compiled CasADi function {self.name} failed")
            return
        for i, address in self._fed.items():
            ctypes.memmove(self.inputs[i].ctypes.data, address, self.inputs[i].nbytes)
        results = self.function(*[ca.DM(b.reshape(b.shape[0], -1, order="F")) for b in self.inputs])
        if self.function.n_out() == 1:
            results = [results]
        for buf, value in zip(self.outputs, results):
            buf[...] = np.asarray(value).reshape(buf.shape, order="F")


def _buffer(shape: tuple[int, int]) -> np.ndarray:
    rows, cols = shape
    return np.zeros(rows) if cols == 1 else np.zeros((rows, cols), order="F")


def compiled_points(fn: ca.Function, name: str, chunk: int, flags: tuple[str, ...]) -> BufferedFunction | None:
    """``fn`` (inputs of one point each, a parameter vector last, one column output) with its
    common subexpressions eliminated, mapped over ``chunk`` points (the parameter vector
    shared) and compiled to C once per machine with ``flags``, as the Function
    ``falcon_batch_{name}_{chunk}`` (call it with :meth:`BufferedFunction.map_columns`); None
    without a compiler. The merge is done only when compiling (it took 0.2-0.4 s for the
    LQR's linearisation in every process that loaded the cached library): the cache key is
    that of the unmerged map, and the library's own Function (its work sizes are the merged
    code's) is loaded back with ``casadi.external``."""
    syms = [ca.SX.sym(f"in{i}", fn.size1_in(i)) for i in range(fn.n_in())]

    def mapped_over_chunk(merge: bool) -> ca.Function:
        one = ca.Function(f"{name}_cse", syms, [fn(*syms)], {"cse": merge})
        mapped = one.map(f"{name}_map", "serial", chunk, [fn.n_in() - 1], [])
        ins = mapped.mx_in()
        return ca.Function(f"falcon_batch_{name}_{chunk}", ins, mapped.call(ins))

    whole = mapped_over_chunk(False)
    library = build_shared_library(whole.name(), [whole], flags=flags, cse=lambda: [mapped_over_chunk(True)])
    return BufferedFunction(ca.external(whole.name(), str(library)), library) if library is not None else None


def build_library(fn: ca.Function) -> Path | None:
    """The compiled shared object of ``fn`` (built once per machine, -O2), or None if there is
    no compiler or compilation fails (then :class:`BufferedFunction` runs it uncompiled)."""
    return build_shared_library(fn.name(), [fn], flags=("-O2",))

