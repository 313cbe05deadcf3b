"""The key-expression layout of the falcon-plan Zenoh service (documented in service/README.md).

Every instance serves the keys below ``<prefix>/<instance>``; a few keys are shared by all
instances under ``<prefix>``::

    <prefix>/alive/<instance>                 liveliness token of a running instance
    <prefix>/plan                             get: plan on any one instance (shared queryable)
    <prefix>/schema/<name>                    get: a JSON schema (shared queryable)
    <prefix>/<instance>/plan                  get: plan on this instance
    <prefix>/<instance>/goals/submit          put (id required) or get (acknowledged): a goal
    <prefix>/<instance>/goals/<id>/progress   published progress of a goal
    <prefix>/<instance>/goals/<id>/result     published final result; get: status now
    <prefix>/<instance>/goals/<id>/cancel     put or get: cancel a goal
    <prefix>/<instance>/state                 published device state (50 Hz); get: state now
    <prefix>/<instance>/info                  get: what this instance is and serves
    <prefix>/<instance>/schema/<name>         get: a JSON schema
    <prefix>/<instance>/errors                published: errors in puts (they have no reply)

This module only builds and parses key strings; it does not import zenoh.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from falcon_plan.errors import InvalidParameterError

DEFAULT_PREFIX = "falcon"
"""Default first chunk(s) of every key."""

DEFAULT_INSTANCE = "falcon0"
"""Instance id when none is given (give each of several instances its own)."""

ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
"""Instance ids and goal ids: 1-64 characters, letters, digits, ``_ . -``, not starting with
a punctuation mark (so never a wildcard, a verbatim ``@`` chunk or a path separator)."""

RESERVED_INSTANCE_IDS = frozenset({"alive", "plan", "schema"})
"""Chunks used by the shared keys under the prefix, so no instance may be called that."""

_PREFIX_CHUNK = re.compile(r"^[A-Za-z0-9_.-]+$")

SCHEMA_NAMES = ("plan_request", "plan_reply", "goal_request", "goal_ack", "goal_progress",
                "goal_result", "cancel_reply", "state", "info", "error")
"""Names of the published JSON schemas (files ``service/schemas/<name>.json``)."""


def validate_id(value: str, what: str = "id") -> str:
    """Return ``value`` if it is a valid instance or goal id, else raise InvalidParameterError
    naming it as ``what``."""
    if not isinstance(value, str) or not ID_PATTERN.match(value):
        raise InvalidParameterError(
            f"{what} {value!r} is not allowed: use 1-64 letters, digits, '_', '.' or '-', "
            "starting with a letter or digit")
    return value


def validate_prefix(prefix: str) -> str:
    """Return ``prefix`` if it is one or more plain key chunks (no wildcards, no ``@``)."""
    chunks = prefix.split("/") if isinstance(prefix, str) else [""]
    if not all(_PREFIX_CHUNK.match(c) for c in chunks):
        raise InvalidParameterError(
            f"prefix {prefix!r} is not allowed: use '/'-separated chunks of letters, digits, "
            "'_', '.' or '-' (no wildcards, no empty chunks)")
    return prefix


@dataclass(frozen=True)
class Route:
    """What a concrete key of an instance addresses: ``endpoint`` is one of ``plan``,
    ``goals/submit``, ``goal/progress``, ``goal/result``, ``goal/cancel``, ``state``,
    ``info``, ``schema``, ``errors``; ``arg`` is the goal id or schema name, if any."""

    endpoint: str
    arg: str | None = None


@dataclass(frozen=True)
class ServiceKeys:
    """The keys of one instance. ``prefix`` is shared by cooperating instances;
    ``instance`` names this one (and its device)."""

    prefix: str = DEFAULT_PREFIX
    instance: str = DEFAULT_INSTANCE

    def __post_init__(self) -> None:
        validate_prefix(self.prefix)
        validate_id(self.instance, "instance id")
        if self.instance in RESERVED_INSTANCE_IDS:
            raise InvalidParameterError(
                f"instance id {self.instance!r} is reserved (not one of {sorted(RESERVED_INSTANCE_IDS)})")

    # --- shared keys ------------------------------------------------------------------------
    @property
    def shared_plan(self) -> str:
        """Plan on any one instance: the shared queryable (all instances declare it)."""
        return f"{self.prefix}/plan"

    @property
    def shared_schema_pattern(self) -> str:
        """Key pattern of the shared schema queryable."""
        return f"{self.prefix}/schema/*"

    def shared_schema(self, name: str) -> str:
        """The shared key of schema ``name``."""
        return f"{self.prefix}/schema/{name}"

    @property
    def alive(self) -> str:
        """This instance's liveliness token."""
        return f"{self.prefix}/alive/{self.instance}"

    @property
    def alive_pattern(self) -> str:
        """Liveliness pattern matching every instance under the prefix."""
        return f"{self.prefix}/alive/*"

    # --- instance keys ----------------------------------------------------------------------
    @property
    def base(self) -> str:
        """``<prefix>/<instance>``: every instance key starts with it."""
        return f"{self.prefix}/{self.instance}"

    @property
    def all(self) -> str:
        """Pattern matching every key of the instance (its catch-all queryable)."""
        return f"{self.base}/**"

    @property
    def plan(self) -> str:
        """Plan on this instance."""
        return f"{self.base}/plan"

    @property
    def goals_submit(self) -> str:
        """Submit a goal (put or get)."""
        return f"{self.base}/goals/submit"

    def goal_progress(self, goal_id: str) -> str:
        """Where the progress of goal ``goal_id`` is published."""
        return f"{self.base}/goals/{goal_id}/progress"

    def goal_result(self, goal_id: str) -> str:
        """Where the result of goal ``goal_id`` is published (and can be queried)."""
        return f"{self.base}/goals/{goal_id}/result"

    def goal_cancel(self, goal_id: str) -> str:
        """Cancel goal ``goal_id`` (put or get)."""
        return f"{self.base}/goals/{goal_id}/cancel"

    @property
    def goals_pattern(self) -> str:
        """Subscriber pattern for the puts under ``goals/`` (submissions and cancels)."""
        return f"{self.base}/goals/**"

    @property
    def state(self) -> str:
        """Device state: published and queryable."""
        return f"{self.base}/state"

    @property
    def info(self) -> str:
        """What the instance is (device, queue, keys)."""
        return f"{self.base}/info"

    def schema(self, name: str) -> str:
        """Schema ``name`` on this instance."""
        return f"{self.base}/schema/{name}"

    @property
    def errors(self) -> str:
        """Errors in puts, which have no reply channel, are published here."""
        return f"{self.base}/errors"

    def route(self, key: str) -> Route | None:
        """Parse a concrete key of this instance (or a shared key) into a :class:`Route`;
        None if the key is not one the service answers."""
        if key == self.shared_plan:
            return Route("plan")
        shared_schema_head = f"{self.prefix}/schema/"
        if key.startswith(shared_schema_head) and "/" not in key[len(shared_schema_head):]:
            return Route("schema", key[len(shared_schema_head):])
        if not key.startswith(self.base + "/"):
            return None
        rest = key[len(self.base) + 1:].split("/")
        if rest in (["plan"], ["state"], ["info"], ["errors"]):
            return Route(rest[0])
        if rest == ["goals", "submit"]:
            return Route("goals/submit")
        if len(rest) == 2 and rest[0] == "schema":
            return Route("schema", rest[1])
        if len(rest) == 3 and rest[0] == "goals" and rest[2] in ("progress", "result", "cancel"):
            return Route(f"goal/{rest[2]}", rest[1])
        return None

    def layout(self) -> dict[str, str]:
        """The keys of this instance by name (served by ``info`` and shown by clients)."""
        return {
            "alive": self.alive, "shared_plan": self.shared_plan,
            "shared_schema": self.shared_schema("<name>"), "plan": self.plan,
            "goals_submit": self.goals_submit, "goal_progress": self.goal_progress("<id>"),
            "goal_result": self.goal_result("<id>"), "goal_cancel": self.goal_cancel("<id>"),
            "state": self.state, "info": self.info, "schema": self.schema("<name>"),
            "errors": self.errors,
        }


def instance_from_alive_key(key: str, prefix: str = DEFAULT_PREFIX) -> str | None:
    """The instance id in a liveliness key ``<prefix>/alive/<instance>`` (None otherwise)."""
    head = f"{prefix}/alive/"
    if key.startswith(head) and ID_PATTERN.match(key[len(head):]):
        return key[len(head):]
    return None
