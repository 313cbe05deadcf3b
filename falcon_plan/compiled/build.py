"""Compile CasADi Functions to C shared libraries, once per machine, cached on disk.

Every compiled path uses it: the Functions called in place through ctypes
(:mod:`falcon_plan.compiled.inplace`: the plant's per-period step, batched inverse dynamics and
forward kinematics) and the planner's per-point kernels (loaded with ``casadi.external``, see
:mod:`falcon_plan.compiled.external`).

Cache: ``$FALCON_PLAN_CACHE``, else ``$XDG_CACHE_HOME/falcon-plan`` or
``~/.cache/falcon-plan`` (never inside the repository). A library is named by a SHA-256 of
the Functions' serialisation (CasADi's exact text of every expression node, which changes
whenever the model does), the companions derived from them, the compiler, its flags, the
processor (:func:`processor`: several kernels are built for this machine's instruction set,
``-march=native``) and the CasADi version, so a changed model can never load a stale binary,
nor a cache shared between machines one built for another processor. The key is cheap: C is
generated only when a library is really compiled, and companions (Jacobians, adjoints) are
derived only then (:func:`load_functions` reads them back from the library). Concurrent builders (the benchmark runs one process per core) take
a lock file so only one compiles; the library is written under a temporary name and renamed
into place. A compilation is bounded by :data:`COMPILE_TIMEOUT_S`. Without a compiler, or
with ``FALCON_PLAN_NO_COMPILE=1``, callers get None and evaluate the Function uncompiled
(slower, same results).
"""
from __future__ import annotations

import fcntl
import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import casadi as ca

log = logging.getLogger("falcon_plan.compiled")
"""Says (at INFO) when a library is compiled; the command line always shows those lines."""

COMPILE_TIMEOUT_S = 1200.0
"""Upper bound on one compilation [s]: a bound for a compiler that hangs. The largest kernel,
the planner's switching-time step with its adjoint under the device's limit, takes about 48 s
at ``-O1`` on this 2-core machine when it is quiet (with the step's AD Jacobian, since dropped,
the constant rule's alone took about 155 s, up to about 330 s with the other core busy: gcc
spends most of it in register allocation)."""

KEY_FORMAT = "serialized-v1"
"""Part of every cache key: names how the key is made (a change of scheme never meets old files)."""

COMPANIONS: dict[str, tuple[str, Callable[[ca.Function], ca.Function]]] = {
    "jacobian": ("jac_", lambda fn: fn.jacobian()),   # what casadi.external differentiates with
    "reverse": ("adj1_", lambda fn: fn.reverse(1)),   # one adjoint (reverse-mode) sweep
}
"""Functions a library can hold besides the ones given, derived from the first of them: name
-> (CasADi's prefix of the derived Function's name, how it is derived). Each is part of the
cache key by name, and derived only when the library is compiled."""

compilations = 0
"""Libraries compiled by this process so far (the command line says "compiled" only when this grows)."""


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


@functools.lru_cache(maxsize=None)
def processor() -> str:
    """What identifies this machine's processor for the cache keys: the architecture, and on
    Linux the model name and a hash of the instruction-set flags from ``/proc/cpuinfo`` (a
    library compiled with ``-march=native`` runs only where they match)."""
    fields: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as info:
            for line in info:
                name, _, value = line.partition(":")
                fields.setdefault(name.strip(), value.strip())
                if not line.strip():
                    break              # the first processor's block is enough
    except OSError:
        pass
    flags = fields.get("flags") or fields.get("Features") or ""
    return "|".join([platform.machine(), fields.get("model name", ""),
                     hashlib.sha256(flags.encode()).hexdigest()[:12]])


def generate_source(name: str, functions: list[ca.Function]) -> str:
    """C source of ``functions`` (CasADi's code generator, no header), as text; ``name`` names
    the generated file."""
    with tempfile.TemporaryDirectory(prefix="falcon-plan-cg-") as tmp:
        gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        for fn in functions:
            gen.add(fn)
        gen.generate(tmp + os.sep)
        return Path(tmp, f"{name}.c").read_text()


def merged(fn: ca.Function) -> ca.Function:
    """``fn`` (an SX Function) with the common subexpressions of its outputs merged (same name,
    inputs, outputs and values; fewer operations: the RK4 stages share most of the dynamics)."""
    ins = fn.sx_in()
    return ca.Function(fn.name(), ins, ca.cse(fn.call(ins)), fn.name_in(), fn.name_out())


def with_companions(functions: Sequence[ca.Function], companions: Sequence[str] = ()) -> list[ca.Function]:
    """``functions`` followed by the ``companions`` (names in :data:`COMPANIONS`) of the first."""
    return [*functions, *(COMPANIONS[c][1](functions[0]) for c in companions)]


def companion_names(functions: Sequence[ca.Function], companions: Sequence[str] = ()) -> list[str]:
    """The symbol names of :func:`with_companions` for ``functions`` and the ``companions`` of
    the first (``jac_<name>``, ``adj1_<name>``), without deriving anything."""
    return [fn.name() for fn in functions] + [COMPANIONS[c][0] + functions[0].name() for c in companions]


def cache_key(functions: Sequence[ca.Function], companions: Sequence[str], cc: str, flags: Sequence[str],
              cse: Any = False) -> str:
    """The 20-hex-digit key of a library: SHA-256 of the serialisation of ``functions``, the
    names of the ``companions``, whether they are ``cse`` merged (:func:`merged`), the compiler
    ``cc``, its ``flags``, the :func:`processor`, the CasADi version and :data:`KEY_FORMAT` (no C
    is generated: a few ms where generating the planner's step took ~0.4 s)."""
    digest = hashlib.sha256()
    for part in [KEY_FORMAT, ca.__version__, cc, *flags, processor(), *companions, f"cse={bool(cse)}"]:
        digest.update(part.encode() + b"\0")
    for fn in functions:
        digest.update(fn.serialize().encode() + b"\0")
    return digest.hexdigest()[:20]


def build_shared_library(name: str, functions: Sequence[ca.Function], flags: tuple[str, ...] = ("-O2",),
                         companions: Sequence[str] = (),
                         cse: bool | Callable[[], Sequence[ca.Function]] = False) -> Path | None:
    """The cached shared library holding ``functions`` and the ``companions`` of the first
    (names in :data:`COMPANIONS`; compiled now if it is not cached), or None (logged) when there
    is no compiler or the build fails. ``name`` labels the library and its log lines;
    ``flags`` are the compiler's options (part of the cache key). With ``cse`` the compiled
    code is that of the :func:`merged` Functions (merging takes ~0.1 s for the planner's
    step: done only when compiling); ``cse`` may also be a function giving the merged
    Functions to compile (same names and signatures as ``functions``: for MX Functions built
    around merged SX ones, e.g. the plant's chunks)."""
    cc = compiler()
    if cc is None:
        log.info("no C compiler (or FALCON_PLAN_NO_COMPILE set): %s runs uncompiled", name)
        return None
    target = cache_dir() / f"{name}-{cache_key(functions, companions, cc, flags, cse)}.so"
    if target.exists():
        return target
    try:
        with open(target.with_suffix(".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not target.exists():
                if callable(cse):
                    functions = list(cse())
                elif cse:
                    functions = [merged(fn) for fn in functions]
                _compile(cc, generate_source(name, with_companions(functions, companions)), target, flags)
    except (OSError, subprocess.SubprocessError) as exc:
        detail = getattr(exc, "stderr", None) or b""
        log.warning("compiling %s failed (%s %s); running it uncompiled", name, exc,
                    detail.decode(errors="replace")[:500])
        return None
    return target


def _compile(cc: str, source: str, target: Path, flags: tuple[str, ...]) -> None:
    """Compile ``source`` into ``target`` through a temporary file renamed into place."""
    global compilations
    compilations += 1
    log.info("compiling %s (once; cached in %s)", target.name, target.parent)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        c_file = Path(tmp) / "kernel.c"
        c_file.write_text(source)
        partial = Path(tmp) / target.name
        subprocess.run([cc, *flags, "-shared", "-fPIC", "-o", str(partial), str(c_file), "-lm"],
                       check=True, capture_output=True, timeout=COMPILE_TIMEOUT_S)
        os.replace(partial, target)




def recipe_file(label: str, sources: Sequence[str], *parts: Any) -> Path:
    """Where the libraries built from a recipe are recorded (:func:`record_recipe`): a file in
    the cache named ``label`` and a hash of everything they are made from: the package files
    ``sources`` (paths relative to the package; a folder: every .py in it), the ``parts``
    (their repr: parameters, layouts, flags), the compiler and CasADi's version. A later
    process that finds it loads the libraries with ``casadi.external`` without building the
    Functions' symbolics (0.1-0.5 s each) only to name and key them."""
    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for source in sources:
        path = package / source
        for file in sorted(path.glob("*.py")) if path.is_dir() else [path]:
            digest.update(file.name.encode())
            digest.update(file.read_bytes())
    digest.update(repr((parts, compiler(), processor(), ca.__version__, KEY_FORMAT)).encode())
    return cache_dir() / f"{label}-{digest.hexdigest()[:20]}.recipe"


def recorded_recipe(recipe: Path, libraries: int, names: int = 0) -> list[str] | None:
    """What ``recipe`` records: ``libraries`` paths (each a file that still exists), then
    ``names`` more lines (e.g. symbol names); None when it does not exist, is short, or names
    a library that is gone."""
    try:
        lines = recipe.read_text().split("\n")[:libraries + names]
    except OSError:
        return None
    if len(lines) < libraries + names or not all(lines):
        return None
    return lines if all(Path(line).is_file() for line in lines[:libraries]) else None


def record_recipe(recipe: Path, lines: Sequence[str]) -> None:
    """Record ``lines`` (the built libraries' paths, then e.g. symbol names) for ``recipe``
    (atomically; a failure only costs the next process the symbolics again)."""
    try:
        part = recipe.with_suffix(f".{os.getpid()}.part")
        part.write_text("".join(f"{line}\n" for line in lines))
        part.replace(recipe)
    except OSError:
        pass


def library_by_recipe(recipe: Path, build: Callable[[], tuple[Path | None, str]]) -> tuple[Path, str] | None:
    """(library, symbol) of a one-Function library: the one ``recipe`` records
    (:func:`recipe_file`), else what ``build()`` returns (the compiled library, None without a
    compiler, and the Function's name), recorded for the next process. None without a
    compiler."""
    found = recorded_recipe(recipe, 1, 1)
    if found is not None:
        return Path(found[0]), found[1]
    library, symbol = build()
    if library is None:
        return None
    record_recipe(recipe, [str(library), symbol])
    return library, symbol


def load_functions(library: Path, functions: Sequence[ca.Function], companions: Sequence[str] = ()) -> list[ca.Function]:
    """The compiled ``functions`` and ``companions`` in ``library`` (from
    :func:`build_shared_library` with the same arguments), loaded with ``casadi.external``:
    same inputs, outputs, sizes and values as :func:`with_companions` would give, without
    deriving the companions."""
    return [ca.external(symbol, str(library)) for symbol in companion_names(functions, companions)]
