"""JSON in and out of the service: strict decoding, schema checks, error bodies.

Payloads are plain UTF-8 JSON objects (encoding ``application/json``), never pickles. Decoding
is strict: at most :data:`MAX_PAYLOAD_BYTES`, UTF-8, one JSON object, no NaN or infinite
numbers (Python's parser accepts ``NaN``, ``Infinity`` and ``1e999``; we do not), no
duplicate field names. The object is then checked against the published JSON schema of the
request (``service/schemas/<name>.json``), which is the single statement of what is allowed.

The schema checker implements the subset of JSON Schema (2020-12) the schemas use: ``type``,
``properties``, ``required``, ``additionalProperties`` (boolean), ``items``, ``minItems``,
``maxItems``, ``minimum``, ``maximum``, ``minLength``, ``maxLength``, ``pattern``, ``enum``,
``const`` and local ``$ref`` (``#/$defs/<name>``). Any other keyword in a schema file is an
error when the schema is loaded, so a schema can never silently promise more than is checked.
"""
from __future__ import annotations

import functools
import json
import math
import re
from pathlib import Path
from typing import Any

from falcon_plan.errors import FalconPlanError
from falcon_plan.model.workspace import MM_HINT_LIMIT_M

SCHEMA_VERSION = 1
"""Version of every request and reply body (field ``schema_version``)."""

MAX_PAYLOAD_BYTES = 64 * 1024
"""Largest request payload the service reads [bytes]; larger ones get ``payload_too_large``."""

ACCEPTED_ENCODINGS = ("application/json", "text/json", "text/plain", "zenoh/bytes", "zenoh/string")
"""Request encodings read as JSON text (``zenoh/bytes`` is what a client sends by default)."""

SCHEMA_DIR = Path(__file__).resolve().parent / "schemas"

ERROR_CODES = (
    "unsupported_encoding", "payload_too_large", "malformed_json", "invalid_request",
    "non_finite_number", "outside_workspace", "invalid_problem", "planning_failed",
    "unknown_key", "unknown_goal", "duplicate_goal_id", "queue_full", "no_device",
    "overloaded", "start_mismatch", "device_error", "deadline_exceeded", "cancelled",
    "internal_error",
)
"""Every ``error.code`` the service sends (the ``error`` schema lists the same)."""
INPUT_ERROR_CODES = frozenset({
    "unsupported_encoding", "payload_too_large", "malformed_json", "invalid_request",
    "non_finite_number", "outside_workspace", "invalid_problem", "unknown_key", "unknown_goal",
    "duplicate_goal_id", "start_mismatch"})
"""The codes that refuse the request's own content (the sender can fix it); the others say the
service could not do what was asked (planning failed, busy, device, deadline, cancelled)."""


class RequestError(FalconPlanError, ValueError):
    """A request the service refuses. ``code`` is one of :data:`ERROR_CODES`, ``field`` the
    JSON path of the offending field (``None`` for the whole request), ``message`` the one
    line for the client, ``allowed`` what would have been accepted and ``detail`` extra data
    (e.g. a failed plan's report)."""

    def __init__(self, code: str, message: str, field: str | None = None, allowed: Any = None,
                 detail: dict[str, Any] | None = None) -> None:
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}")
        super().__init__(message)
        self.code = code
        self.field = field
        self.allowed = allowed
        self.detail = detail

    def to_dict(self) -> dict[str, Any]:
        """The ``error`` object of an error reply."""
        out: dict[str, Any] = {"code": self.code, "message": str(self), "field": self.field}
        if self.allowed is not None:
            out["allowed"] = self.allowed
        if self.detail is not None:
            out["detail"] = self.detail
        return out


# --- decoding --------------------------------------------------------------------------------
def _reject_constant(name: str) -> Any:
    raise RequestError("non_finite_number", f"{name} is not a number JSON allows; send finite numbers",
                       allowed="finite numbers")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise RequestError("non_finite_number", f"number {text} overflows to infinity; send finite numbers",
                           allowed="finite numbers")
    return value


def _unique_object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise RequestError("malformed_json", f"field {key!r} appears twice in one object", field=key)
        out[key] = value
    return out


def check_encoding(encoding: str | None) -> None:
    """Raise ``unsupported_encoding`` unless ``encoding`` (its MIME part) is read as JSON."""
    if encoding is None:
        return
    mime = encoding.split(";", 1)[0]
    if mime not in ACCEPTED_ENCODINGS:
        raise RequestError("unsupported_encoding", f"payload encoding {encoding!r} is not accepted",
                           allowed=list(ACCEPTED_ENCODINGS))


def decode_json(payload: bytes | None, *, required: bool = True,
                limit: int = MAX_PAYLOAD_BYTES) -> dict[str, Any] | None:
    """Parse a request payload into a dict, strictly (see the module docstring).

    An empty or absent payload gives ``None`` if not ``required``; a payload longer than
    ``limit`` bytes is refused. Raises
    :class:`RequestError` saying what is wrong.
    """
    if not payload:
        if required:
            raise RequestError("invalid_request", "the request has no payload; send a JSON object",
                               allowed="a JSON object")
        return None
    if len(payload) > limit:
        raise RequestError("payload_too_large", f"payload of {len(payload)} bytes exceeds the limit of {limit} bytes",
                           allowed=f"at most {limit} bytes")
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RequestError("malformed_json", f"payload is not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        data = json.loads(text, parse_constant=_reject_constant, parse_float=_finite_float,
                          object_pairs_hook=_unique_object)
    except RequestError:
        raise
    except (ValueError, RecursionError) as exc:
        detail = exc.msg if isinstance(exc, json.JSONDecodeError) else str(exc)
        where = f" at line {exc.lineno} column {exc.colno}" if isinstance(exc, json.JSONDecodeError) else ""
        raise RequestError("malformed_json", f"payload is not valid JSON: {detail}{where}") from None
    if not isinstance(data, dict):
        raise RequestError("invalid_request", f"payload must be a JSON object, got {type(data).__name__}",
                           allowed="a JSON object")
    return data


def _json_default(value: Any) -> Any:
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        return value.tolist()
    if hasattr(value, "to_dict"):
        return value.to_dict()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def sanitise(value: Any) -> Any:
    """``value`` with non-finite floats replaced by None (JSON has no NaN), numpy values and
    objects with ``to_dict`` as JSON values; recurses into containers."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): sanitise(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [sanitise(v) for v in value]
    if hasattr(value, "tolist") or hasattr(value, "to_dict"):
        return sanitise(_json_default(value))
    return value


def encode_json(body: dict[str, Any]) -> bytes:
    """Encode a reply body as compact UTF-8 JSON. Non-finite floats become ``null``
    (strict JSON); numpy values become lists and numbers."""
    return json.dumps(sanitise(body), separators=(",", ":"), allow_nan=False).encode("utf-8")


def error_body(error: RequestError, instance: str, request_id: Any = None) -> dict[str, Any]:
    """The body of an error reply (schema ``error``) for ``error``, from ``instance``,
    echoing the request's ``request_id`` (None: the request had none)."""
    body: dict[str, Any] = {"schema_version": SCHEMA_VERSION, "instance": instance, "error": error.to_dict()}
    if isinstance(request_id, str):
        body["request_id"] = request_id
    return body


# --- schemas ---------------------------------------------------------------------------------
_KNOWN_KEYWORDS = frozenset({
    "$schema", "$id", "$defs", "$ref", "title", "description", "examples", "type", "properties",
    "required", "additionalProperties", "items", "minItems", "maxItems", "minimum", "maximum",
    "minLength", "maxLength", "pattern", "enum", "const",
})
_ANNOTATION_KEYWORDS = frozenset({"properties", "$defs"})


def _check_keywords(schema: Any, where: str) -> None:
    if not isinstance(schema, dict):
        raise ValueError(f"schema {where} is not an object")
    unknown = set(schema) - _KNOWN_KEYWORDS
    if unknown:
        raise ValueError(f"schema {where} uses keyword(s) {sorted(unknown)} the checker does not implement")
    for key in _ANNOTATION_KEYWORDS & set(schema):
        for name, sub in schema[key].items():
            _check_keywords(sub, f"{where}/{key}/{name}")
    if isinstance(schema.get("items"), dict):
        _check_keywords(schema["items"], f"{where}/items")
    if isinstance(schema.get("additionalProperties"), dict):
        raise ValueError(f"schema {where}: additionalProperties must be a boolean here")


@functools.lru_cache(maxsize=None)
def load_schema(name: str) -> dict[str, Any]:
    """The JSON schema ``name`` (a dict, cached; see :data:`service.keys.SCHEMA_NAMES`)."""
    path = SCHEMA_DIR / f"{name}.json"
    if not re.fullmatch(r"[a-z_]+", name) or not path.is_file():
        raise KeyError(name)
    schema = json.loads(path.read_text(encoding="utf-8"))
    _check_keywords(schema, name)
    return schema


def schema_bytes(name: str) -> bytes:
    """The schema ``name`` as served over Zenoh (compact JSON)."""
    return encode_json(load_schema(name))


_TYPES: dict[str, Any] = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
}


def _type_name(value: Any) -> str:
    for name in ("null", "boolean", "integer", "number", "string", "array", "object"):
        if _TYPES[name](value):
            return name
    return type(value).__name__


def _describe(schema: dict[str, Any]) -> str:
    """A short human statement of what a schema allows (for error messages)."""
    if "const" in schema:
        return json.dumps(schema["const"])
    if "enum" in schema:
        return "one of " + ", ".join(json.dumps(v) for v in schema["enum"])
    types = schema.get("type", "any value")
    text = " or ".join(types) if isinstance(types, list) else types
    if schema.get("type") == "array" and "minItems" in schema and schema.get("minItems") == schema.get("maxItems"):
        item = schema.get("items", {}).get("type", "value")
        text = f"an array of {schema['minItems']} {item}s"
    if "description" in schema:
        text += f" ({schema['description']})"
    return text


def _resolve(schema: dict[str, Any], root: dict[str, Any]) -> dict[str, Any]:
    """Follow a local ``$ref`` (``#/$defs/<name>``)."""
    if "$ref" not in schema:
        return schema
    ref = schema["$ref"]
    if not ref.startswith("#/$defs/"):
        raise ValueError(f"only local $ref is supported, got {ref}")
    return root["$defs"][ref[len("#/$defs/"):]]


def validate(value: Any, schema: dict[str, Any], root: dict[str, Any] | None = None, path: str = "") -> None:
    """Check ``value`` against ``schema``; raise ``invalid_request`` naming the first field
    that is wrong (``path`` like ``goal_m[2]``), what it is and what is allowed. ``root`` is
    the whole schema document (for ``$ref``; default ``schema`` itself)."""
    root = root if root is not None else schema
    schema = _resolve(schema, root)
    field = path or None
    label = f"field {path!r}" if path else "the request"

    def fail(message: str) -> None:
        raise RequestError("invalid_request", f"{label} {message}; allowed: {_describe(schema)}",
                           field=field, allowed=_describe(schema))

    if "const" in schema and value != schema["const"]:
        fail(f"is {json.dumps(value)}")
    if "enum" in schema and value not in schema["enum"]:
        fail(f"is {json.dumps(value)}")
    if "type" in schema:
        types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_TYPES[t](value) for t in types):
            fail(f"has type {_type_name(value)}")
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        metres = re.match(r"(start|goal|via)_m(\[\d+\])*\[\d\]$", path or "") and abs(value) > MM_HINT_LIMIT_M
        hint = f" (points are in metres: did you mean {round(value / 1000.0, 4):g}?)" if metres else ""
        if "minimum" in schema and value < schema["minimum"]:
            fail(f"is {value}, below the minimum {schema['minimum']}{hint}")
        if "maximum" in schema and value > schema["maximum"]:
            fail(f"is {value}, above the maximum {schema['maximum']}{hint}")
    if isinstance(value, str):
        if len(value) < schema.get("minLength", 0):
            fail("is too short")
        if "maxLength" in schema and len(value) > schema["maxLength"]:
            fail(f"is longer than {schema['maxLength']} characters")
        if "pattern" in schema and not re.search(schema["pattern"], value):
            fail(f"{json.dumps(value)} does not match the pattern {schema['pattern']}")
    if isinstance(value, list):
        if len(value) < schema.get("minItems", 0):
            fail(f"has {len(value)} items")
        if "maxItems" in schema and len(value) > schema["maxItems"]:
            fail(f"has {len(value)} items")
        if "items" in schema:
            for i, item in enumerate(value):
                validate(item, schema["items"], root, f"{path}[{i}]")
    if isinstance(value, dict):
        props = schema.get("properties", {})
        for name in schema.get("required", []):
            if name not in value:
                sub = _resolve(props.get(name, {}), root)
                raise RequestError("invalid_request",
                                   f"{label} lacks the required field {name!r}; allowed: {_describe(sub)}",
                                   field=f"{path}.{name}" if path else name, allowed=_describe(sub))
        if schema.get("additionalProperties") is False:
            extra = sorted(set(value) - set(props))
            if extra:
                raise RequestError("invalid_request",
                                   f"{label} has unknown field(s) {extra}; allowed fields: {sorted(props)}",
                                   field=f"{path}.{extra[0]}" if path else extra[0], allowed=sorted(props))
        for name, sub in props.items():
            if name in value:
                validate(value[name], sub, root, f"{path}.{name}" if path else name)


def decode_request(payload: bytes | None, schema_name: str, *, encoding: str | None = None,
                   required: bool = True, limit: int = MAX_PAYLOAD_BYTES) -> dict[str, Any] | None:
    """Check the encoding, decode strictly and validate against schema ``schema_name``.
    ``required`` and ``limit`` as for :func:`decode_json`. Returns the request dict (``None``
    for an absent optional payload)."""
    check_encoding(encoding)
    data = decode_json(payload, required=required, limit=limit)
    if data is not None:
        validate(data, load_schema(schema_name))
    return data
