"""Checks shared by the value types that are read from JSON (parameters, effects, problems)."""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from falcon_plan.errors import InputError


def require_known_fields(cls: type, data: Any, error: type[InputError]) -> None:
    """Raise ``error`` unless ``data`` is a dict whose keys are all fields of the dataclass
    ``cls``; the message names the unknown keys and lists the allowed ones."""
    if not isinstance(data, dict):
        raise error(f"{cls.__name__} JSON must be an object, got {type(data).__name__}", allowed="an object")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise error(f"unknown {cls.__name__} field(s) {unknown}; allowed: {sorted(known)}", field=unknown[0],
                    allowed=sorted(known))


def _range_text(low: float, high: float, low_open: bool, high_open: bool) -> str:
    """How an allowed interval reads in a message: "in (0, 4096]", ">= 0", "< 1"."""
    if math.isfinite(low) and math.isfinite(high):
        return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    if math.isfinite(low):
        return f"{'>' if low_open else '>='} {low:g}"
    return f"{'<' if high_open else '<='} {high:g}"


def require_number(name: str, value: Any, error: type[InputError], low: float = -math.inf,
                   high: float = math.inf, *, low_open: bool = False, high_open: bool = False) -> float:
    """``value`` as a finite float within [low, high] (an end excluded when ``low_open`` /
    ``high_open``), else ``error`` naming ``name``, what is allowed and what was given
    (``bool`` is not a number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(f"{name} must be a number, got {value!r}", field=name, allowed="a number")
    x = float(value)
    if not math.isfinite(x):
        raise error(f"{name} must be finite, got {value!r}", field=name, allowed="a finite number")
    if (x <= low if low_open else x < low) or (x >= high if high_open else x > high):
        allowed = _range_text(low, high, low_open, high_open)
        raise error(f"{name} must be {allowed}, got {value!r}", field=name, allowed=allowed)
    return x


def require_whole_number(name: str, value: Any, error: type[InputError], low: int, high: int) -> int:
    """``value`` as an int in [low, high] (Python or numpy integer, not bool), else ``error``
    naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not low <= value <= high:
        allowed = f"a whole number in [{low}, {high}]"
        raise error(f"{name} must be {allowed}, got {value!r}", field=name, allowed=allowed)
    return int(value)


VEC3_ALLOWED = "3 finite numbers (x, y, z)"
"""What a 3-vector field allows (the ``allowed`` of its errors)."""


def require_vec3(name: str, value: Any, error: type[InputError]) -> tuple[float, float, float]:
    """``value``, a finite 3-vector (any sequence or array), as a tuple of floats, else
    ``error`` naming ``name``."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise error(f"{name} must be 3 numbers, got {value!r}", field=name, allowed=VEC3_ALLOWED) from exc
    if arr.shape != (3,):
        raise error(f"{name} must be 3 numbers (x, y, z), got shape {arr.shape}", field=name, allowed=VEC3_ALLOWED)
    if not np.all(np.isfinite(arr)):
        raise error(f"{name} must be finite, got {arr.tolist()}", field=name, allowed=VEC3_ALLOWED)
    return (float(arr[0]), float(arr[1]), float(arr[2]))
