"""Checks shared by the value types that are read from JSON (parameters, effects, problems)."""
from __future__ import annotations

import dataclasses
from typing import Any


def require_known_fields(cls: type, data: Any, error: type[Exception]) -> None:
    """Raise ``error`` unless ``data`` is a dict whose keys are all fields of the dataclass
    ``cls``; the message names the unknown keys and lists the allowed ones."""
    if not isinstance(data, dict):
        raise error(f"{cls.__name__} JSON must be an object, got {type(data).__name__}")
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise error(f"unknown {cls.__name__} field(s) {unknown}; allowed: {sorted(known)}")
