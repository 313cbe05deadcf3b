"""Compile a CasADi Function to C once per machine and call it with almost no overhead.

A Python call to a CasADi Function costs tens of microseconds, more than the simulated
plant's whole control period is allowed (25 us at 800 Hz for 50x real time). So the plant
generates C code for its per-period Function (``casadi.CodeGenerator``), compiles it with
``cc -O2 -shared`` and calls the generated entry point through :mod:`ctypes`, with
argument pointers and work arrays set up once; inputs and outputs are numpy buffers that the
caller fills and reads in place.

Cache: the shared object lives in ``$FALCON_PLAN_CACHE`` (default
``$XDG_CACHE_HOME/falcon-plan`` or ``~/.cache/falcon-plan``), named by a SHA-256 of the
generated source, the compiler command and the CasADi version, so it is built once per
machine and a changed model can never load a stale binary. Concurrent builders write to a
temporary name and ``os.replace`` it, under a lock file so that only one of them compiles.
Compilation is bounded by
:data:`COMPILE_TIMEOUT_S`. Without a compiler (or with ``FALCON_PLAN_NO_COMPILE=1``) the
same interface evaluates the uncompiled Function (slow but correct).
"""
from __future__ import annotations

import ctypes
import fcntl
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import casadi as ca
import numpy as np

log = logging.getLogger(__name__)

COMPILE_TIMEOUT_S = 60.0
"""Upper bound on one compilation [s]."""
COMPILER_FLAGS = ("-O2", "-shared", "-fPIC")


def cache_dir() -> Path:
    """Where compiled functions are kept (created on demand); never inside the repository."""
    env = os.environ.get("FALCON_PLAN_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "falcon-plan"


def compiler() -> str | None:
    """The C compiler to use (``$CC``, cc or gcc), or None if none is found or compilation is
    disabled with FALCON_PLAN_NO_COMPILE=1."""
    if os.environ.get("FALCON_PLAN_NO_COMPILE", "") not in ("", "0"):
        return None
    for name in (os.environ.get("CC"), "cc", "gcc"):
        if name and shutil.which(name):
            return name
    return None


class BufferedFunction:
    """A CasADi Function evaluated in place on numpy buffers.

    ``inputs[i]`` and ``outputs[j]`` are float64 arrays laid out column-major like the
    Function's i-th input and j-th output (shape (rows, cols) in Fortran order, or (rows,)
    for column vectors). Fill ``inputs``, call the object, read ``outputs``. With
    ``library`` (from :func:`build_library`) it runs the compiled C, else the CasADi
    virtual machine (the fallback); ``compiled`` says which.
    """

    def __init__(self, fn: ca.Function, library: Path | None = None) -> None:
        self.name = fn.name()
        self.function = fn
        self.inputs = [_buffer(fn.size_in(i)) for i in range(fn.n_in())]
        self.outputs = [_buffer(fn.size_out(j)) for j in range(fn.n_out())]
        self._entry = None
        if library is not None:
            self._bind(library, fn)

    @property
    def compiled(self) -> bool:
        """True when calls run the compiled C code."""
        return self._entry is not None

    def _bind(self, library: Path, fn: ca.Function) -> None:
        self._lib = ctypes.CDLL(str(library))
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

    def __call__(self) -> None:
        """Evaluate: read ``inputs``, overwrite ``outputs``."""
        if self._entry is not None:
            if self._entry(self._arg, self._res, self._iw_ptr, self._w_ptr, 0) != 0:
                raise RuntimeError(f"compiled CasADi function {self.name} failed")
            return
        results = self.function(*[ca.DM(b.reshape(b.shape[0], -1, order="F")) for b in self.inputs])
        if self.function.n_out() == 1:
            results = [results]
        for buf, value in zip(self.outputs, results):
            buf[...] = np.asarray(value).reshape(buf.shape, order="F")


def _buffer(shape: tuple[int, int]) -> np.ndarray:
    rows, cols = shape
    return np.zeros(rows) if cols == 1 else np.zeros((rows, cols), order="F")


def _compile(cc: str, source: Path, target: Path) -> None:
    """cc source -> target, through a temporary file renamed into place."""
    fd, name = tempfile.mkstemp(prefix=target.name, suffix=".part", dir=target.parent)
    os.close(fd)
    partial = Path(name)
    try:
        log.info("compiling %s into %s", source.name, target)
        subprocess.run([cc, *COMPILER_FLAGS, str(source), "-o", str(partial), "-lm"], check=True,
                       capture_output=True, timeout=COMPILE_TIMEOUT_S)
        os.replace(partial, target)
    finally:
        partial.unlink(missing_ok=True)


def build_library(fn: ca.Function) -> Path | None:
    """Generate C for ``fn``, compile it (once per machine) and return the shared object's
    path; None (with a warning) if there is no compiler or compilation fails."""
    cc = compiler()
    if cc is None:
        log.info("no C compiler (or FALCON_PLAN_NO_COMPILE set): %s runs uncompiled", fn.name())
        return None
    with tempfile.TemporaryDirectory(prefix="falcon-plan-cg-") as tmp:
        gen = ca.CodeGenerator(f"{fn.name()}.c", {"with_header": False})
        gen.add(fn)
        gen.generate(tmp + os.sep)
        source = Path(tmp, f"{fn.name()}.c").read_text()
        key = hashlib.sha256("\n".join([source, cc, *COMPILER_FLAGS, ca.__version__]).encode())
        target_dir = cache_dir()
        target = target_dir / f"{fn.name()}-{key.hexdigest()[:20]}.so"
        if target.exists():
            return target
        try:
            target_dir.mkdir(parents=True, exist_ok=True)
            # One builder per target at a time: others wait for it, then find the result.
            with open(target.with_suffix(".lock"), "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                if not target.exists():
                    _compile(cc, Path(tmp, f"{fn.name()}.c"), target)
        except (OSError, subprocess.SubprocessError) as exc:
            detail = getattr(exc, "stderr", None) or b""
            log.warning("compiling %s failed (%s %s); running it uncompiled", fn.name(), exc,
                        detail.decode(errors="replace")[:500])
            return None
    return target


__all__ = ["BufferedFunction", "build_library", "cache_dir", "compiler", "COMPILE_TIMEOUT_S"]
