"""Compile per-point CasADi Functions (and their Jacobians) to C, cached on disk.

The planner evaluates the closed-chain inverse dynamics and its Jacobian at 2N points per
iteration. CasADi's virtual machine runs the (common-subexpression-merged) Jacobian in about
90 us a point; the same code compiled with ``gcc -O1`` runs in about 7 us and compiles in
about 5 s. So: generate C for the Function and its ``jac_<name>`` companion (the symbol
CasADi's ``external`` looks for to differentiate it), compile once, keep the shared library
in a cache directory keyed by a hash of the C source, and load it with ``ca.external``; it
maps and differentiates like the original inside MX graphs.

Cache directory: ``$FALCON_PLAN_CACHE`` or ``~/.cache/falcon-plan``. Set
``FALCON_PLAN_NO_COMPILE=1`` (or have no C compiler) to use the virtual machine instead;
the result is the same, only slower.
"""
from __future__ import annotations

import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import casadi as ca

log = logging.getLogger(__name__)

_lock = threading.Lock()
_loaded: dict[str, ca.Function] = {}


def cache_dir() -> Path:
    """Where compiled kernels live (created on demand)."""
    root = os.environ.get("FALCON_PLAN_CACHE") or str(Path.home() / ".cache" / "falcon-plan")
    path = Path(root) / f"kernels-casadi{ca.__version__}"
    path.mkdir(parents=True, exist_ok=True)
    return path


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "gcc", "cc", "clang"):
        if name and shutil.which(name):
            return name
    return None


def compile_with_jacobian(fn: ca.Function, *, flags: tuple[str, ...] = ("-O1",)) -> ca.Function:
    """``fn`` compiled to C together with its Jacobian, or ``fn`` itself when compiling is
    disabled or fails (logged). Same inputs, outputs and values as ``fn``.

    (Second derivatives are not compiled: the Jacobian's Jacobian took 150 s to compile on
    a loaded machine and the exact-Hessian solve with it was 3x slower than L-BFGS.)"""
    if os.environ.get("FALCON_PLAN_NO_COMPILE") == "1":
        return fn
    compiler = _compiler()
    if compiler is None:
        log.warning("no C compiler found; %s runs in CasADi's virtual machine", fn.name())
        return fn
    name = fn.name()
    with tempfile.TemporaryDirectory() as tmp:
        gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        gen.add(fn)
        gen.add(fn.jacobian())
        gen.generate(tmp + os.sep)
        source = (Path(tmp) / f"{name}.c").read_text()
    digest = hashlib.sha256((source + " ".join(flags) + compiler).encode()).hexdigest()[:16]
    with _lock:
        if digest in _loaded:
            return _loaded[digest]
        lib = cache_dir() / f"{name}-{digest}.so"
        if not lib.exists():
            try:
                _build(source, lib, compiler, flags)
            except (OSError, subprocess.CalledProcessError) as exc:
                log.warning("compiling %s failed (%s); using CasADi's virtual machine", name, exc)
                return fn
        compiled = ca.external(name, str(lib))
        _loaded[digest] = compiled
        return compiled


def _build(source: str, lib: Path, compiler: str, flags: tuple[str, ...]) -> None:
    """Compile ``source`` into ``lib`` atomically (temp file + rename: concurrent builders
    never see a half-written library)."""
    log.info("compiling %s (once; cached in %s)", lib.name, lib.parent)
    with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
        c_file = Path(tmp) / "kernel.c"
        c_file.write_text(source)
        out = Path(tmp) / lib.name
        subprocess.run([compiler, "-shared", "-fPIC", *flags, "-o", str(out), str(c_file)],
                       check=True, capture_output=True, timeout=600)
        os.replace(out, lib)


__all__ = ["compile_with_jacobian", "cache_dir"]
