"""Compiled Functions that stay differentiable inside CasADi graphs: ``casadi.external``.

The planner evaluates the closed-chain inverse dynamics and its Jacobian at 2N points per
iteration. CasADi's virtual machine runs the (common-subexpression-merged) Jacobian in about
90 us a point; the same code compiled with ``gcc -O1`` runs in about 7 us and compiles in
about 5 s. So: generate C for the Function and its ``jac_<name>`` companion (the symbol
CasADi's ``external`` looks for to differentiate it), compile once, keep the shared library
in a cache directory keyed by a hash of the C source, and load it with ``ca.external``; it
maps and differentiates like the original inside MX graphs.

Compilation and the on-disk cache are :mod:`falcon_plan.compiled.build`'s. Set
``FALCON_PLAN_NO_COMPILE=1`` (or have no C compiler) to use the virtual machine instead;
the result is the same, only slower.
"""
from __future__ import annotations

import threading

import casadi as ca

from falcon_plan.compiled.build import build_shared_library

_lock = threading.Lock()
_loaded: dict[str, ca.Function] = {}


def compile_with_jacobian(fn: ca.Function, *, flags: tuple[str, ...] = ("-O1",)) -> ca.Function:
    """``fn`` compiled to C together with its Jacobian, or ``fn`` itself when compiling is
    disabled or fails (logged). Same inputs, outputs and values as ``fn``. ``flags``: the C
    compiler's options (part of the cache key).

    (Second derivatives are not compiled: the Jacobian's Jacobian took 150 s to compile on
    a loaded machine and the exact-Hessian solve with it was 3x slower than L-BFGS.)"""
    with _lock:
        library = build_shared_library(fn.name(), [fn], flags, companions=("jacobian",))
        if library is None:
            return fn
        key = str(library)
        if key not in _loaded:
            _loaded[key] = ca.external(fn.name(), key)
        return _loaded[key]


__all__ = ["compile_with_jacobian"]
