"""Compile CasADi Functions to C shared libraries, once per machine, cached on disk.

Every compiled path uses it: the Functions called in place through ctypes
(:mod:`falcon_plan.compiled.inplace`: the plant's per-period step, batched inverse dynamics and
forward kinematics) and the planner's per-point kernels (loaded with ``casadi.external``, see
:mod:`falcon_plan.compiled.external`).

Cache: ``$FALCON_PLAN_CACHE``, else ``$XDG_CACHE_HOME/falcon-plan`` or
``~/.cache/falcon-plan`` (never inside the repository). A library is named by a SHA-256 of
the generated source, the compiler, its flags and the CasADi version, so a changed model can
never load a stale binary. Concurrent builders (the benchmark runs one process per core) take
a lock file so only one compiles; the library is written under a temporary name and renamed
into place. A compilation is bounded by :data:`COMPILE_TIMEOUT_S`. Without a compiler, or
with ``FALCON_PLAN_NO_COMPILE=1``, callers get None and evaluate the Function uncompiled
(slower, same results).
"""
from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import casadi as ca

log = logging.getLogger("falcon_plan.compiled")
"""Says (at INFO) when a library is compiled; the command line always shows those lines."""

COMPILE_TIMEOUT_S = 300.0
"""Upper bound on one compilation [s] (the largest kernel takes ~15 s on a loaded machine)."""


def cache_dir() -> Path:
    """Where compiled libraries are kept (created on demand)."""
    env = os.environ.get("FALCON_PLAN_CACHE")
    if env:
        path = Path(env)
    else:
        base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        path = Path(base) / "falcon-plan"
    path.mkdir(parents=True, exist_ok=True)
    return path


def compiler() -> str | None:
    """The C compiler to use (``$CC``, cc, gcc or clang), or None if there is none or
    compilation is disabled with FALCON_PLAN_NO_COMPILE=1."""
    if os.environ.get("FALCON_PLAN_NO_COMPILE", "") not in ("", "0"):
        return None
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    return None


def generate_source(name: str, functions: list[ca.Function]) -> str:
    """C source of ``functions`` (CasADi's code generator, no header), as text; ``name`` names
    the generated file."""
    with tempfile.TemporaryDirectory(prefix="falcon-plan-cg-") as tmp:
        gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        for fn in functions:
            gen.add(fn)
        gen.generate(tmp + os.sep)
        return Path(tmp, f"{name}.c").read_text()


def build_shared_library(name: str, functions: list[ca.Function], flags: tuple[str, ...] = ("-O2",)) -> Path | None:
    """The cached shared library holding ``functions`` (compiled now if it is not cached), or
    None (logged) when there is no compiler or the build fails. ``name`` labels the library
    and its log lines; ``flags`` are the compiler's options (part of the cache key)."""
    cc = compiler()
    if cc is None:
        log.info("no C compiler (or FALCON_PLAN_NO_COMPILE set): %s runs uncompiled", name)
        return None
    source = generate_source(name, functions)
    key = hashlib.sha256("\n".join([source, cc, *flags, ca.__version__]).encode()).hexdigest()[:20]
    target = cache_dir() / f"{name}-{key}.so"
    if target.exists():
        return target
    try:
        with open(target.with_suffix(".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not target.exists():
                _compile(cc, source, target, flags)
    except (OSError, subprocess.SubprocessError) as exc:
        detail = getattr(exc, "stderr", None) or b""
        log.warning("compiling %s failed (%s %s); running it uncompiled", name, exc,
                    detail.decode(errors="replace")[:500])
        return None
    return target


def _compile(cc: str, source: str, target: Path, flags: tuple[str, ...]) -> None:
    """Compile ``source`` into ``target`` through a temporary file renamed into place."""
    log.info("compiling %s (once; cached in %s)", target.name, target.parent)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        c_file = Path(tmp) / "kernel.c"
        c_file.write_text(source)
        partial = Path(tmp) / target.name
        subprocess.run([cc, *flags, "-shared", "-fPIC", "-o", str(partial), str(c_file), "-lm"],
                       check=True, capture_output=True, timeout=COMPILE_TIMEOUT_S)
        os.replace(partial, target)


