"""Every public function, method and class of the package (and of the service built on it)
documents each of its parameters:
the docstring names it (in a sentence or a Parameters section). Checked by inspection of the
signatures, so a new parameter without a word in the docstring fails here."""
from __future__ import annotations

import importlib
import inspect
import pkgutil
import re

import falcon_plan
import service

SKIPPED_PARAMETERS = {"self", "cls", "args", "kwargs"}


def _modules() -> list:
    names = {package.__name__ for package in (falcon_plan, service)}
    for package in (falcon_plan, service):
        names |= {m.name for m in pkgutil.walk_packages(package.__path__, package.__name__ + ".")}
    return [importlib.import_module(n) for n in sorted(names)]


def _public_callables(module) -> list[tuple[str, object, str]]:
    """(qualified name, callable, docstring text to search) of the module's own public
    functions, classes (their __init__ / dataclass fields) and public methods."""
    out = []
    for name, obj in vars(module).items():
        if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__:
            continue
        if inspect.isfunction(obj):
            out.append((f"{module.__name__}.{name}", obj, inspect.getdoc(obj) or ""))
        elif inspect.isclass(obj):
            class_doc = inspect.getdoc(obj) or ""
            init = obj.__dict__.get("__init__")
            if init is not None and inspect.isfunction(init):
                out.append((f"{module.__name__}.{name}", init, class_doc + "\n" + (inspect.getdoc(init) or "")))
            for attr, member in vars(obj).items():
                if attr.startswith("_"):
                    continue
                func = member.__func__ if isinstance(member, (classmethod, staticmethod)) else member
                if inspect.isfunction(func):
                    out.append((f"{module.__name__}.{name}.{attr}", func,
                                (inspect.getdoc(func) or "") + "\n" + class_doc))
    return out


def _undocumented(func, doc: str) -> list[str]:
    try:
        params = inspect.signature(func).parameters
    except (TypeError, ValueError):
        return []
    return [p for p in params if p not in SKIPPED_PARAMETERS
            and not re.search(rf"(?<![A-Za-z0-9_]){re.escape(p)}(?![A-Za-z0-9_])", doc)]


def _gaps_by_module() -> dict[str, list[str]]:
    gaps: dict[str, list[str]] = {}
    for module in _modules():
        for qualname, func, doc in _public_callables(module):
            lacking = _undocumented(func, doc)
            if lacking:
                gaps.setdefault(module.__name__, []).append(f"{qualname}: {', '.join(lacking)}")
    return gaps


def test_every_public_parameter_is_documented() -> None:
    missing = [line for lines in _gaps_by_module().values() for line in lines]
    assert not missing, f"{len(missing)} public callables do not name these parameters in their " \
                        "docstring:\n" + "\n".join(missing)


def test_the_check_finds_an_undocumented_parameter() -> None:
    def documented(a: int, b: int) -> int:
        """Sum of ``a`` and b."""
        return a + b

    def lacking(a: int, width: int) -> int:
        """Twice a."""
        return 2 * a

    assert _undocumented(documented, inspect.getdoc(documented)) == []
    assert _undocumented(lacking, inspect.getdoc(lacking)) == ["width"]
