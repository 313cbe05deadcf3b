"""Who is up under a prefix, from liveliness tokens, and which instance answers a request on a
shared key.

Every instance declares the token ``<prefix>/alive/<instance>`` and watches
``<prefix>/alive/*`` with a liveliness subscriber (``history=True`` reports the tokens already
there). An instance refuses to start when its own token is already up
(:func:`require_free_id`).

The shared plan key ``<prefix>/plan`` is served by a queryable that every instance declares
*not complete*, so Zenoh delivers each get on it to every instance, whatever the session
modes (peer, client of a peer, client of a router) and the query target (``BEST_MATCHING``,
``ALL``). Each instance then computes the same owner for the request with rendezvous
hashing over the live members and the request's bytes (:meth:`Members.owner`); only the
owner answers, the others finalise the query without a reply. So one request gets one
answer, requests spread evenly over the instances (capacity adds up), and a repeated
request goes to the instance that has it in its plan cache.
"""
from __future__ import annotations

import hashlib
import threading
from typing import Any

from falcon_plan.errors import InvalidParameterError
from service.keys import ServiceKeys, instance_from_alive_key

ID_CHECK_TIMEOUT_S = 1.0
"""Longest wait for the liveliness answer when checking an instance id is free [s]."""


class InstanceIdTaken(InvalidParameterError):
    """Another running instance already uses this prefix and instance id."""


def require_free_id(session: Any, keys: ServiceKeys, timeout_s: float = ID_CHECK_TIMEOUT_S) -> None:
    """Raise :class:`InstanceIdTaken` if the liveliness token of ``keys`` is already up
    anywhere ``session`` reaches (asking for at most ``timeout_s`` [s])."""
    for reply in session.liveliness().get(keys.alive, timeout=timeout_s):
        if reply.ok is not None:
            raise InstanceIdTaken(
                f"instance id {keys.instance!r} is already running under prefix {keys.prefix!r} (its liveliness "
                f"token {keys.alive} is up): give this one another --instance, or stop the other first")


def _score(instance: str, payload: bytes) -> int:
    digest = hashlib.blake2b(payload, digest_size=8, key=instance.encode()[:64]).digest()
    return int.from_bytes(digest, "big")


def rendezvous_owner(members: set[str] | frozenset[str], payload: bytes) -> str | None:
    """The one of ``members`` with the highest hash of (member, payload); None if there are none."""
    return max(members, key=lambda m: (_score(m, payload), m), default=None)


class Members:
    """The live instances under ``keys.prefix`` as this instance sees them."""

    def __init__(self, keys: ServiceKeys) -> None:
        self.keys = keys
        self._ids: set[str] = set()
        self._lock = threading.Lock()
        self._subscriber: Any = None

    def watch(self, session: Any) -> None:
        """Start following the liveliness tokens on ``session`` (including those already up)."""
        self._subscriber = session.liveliness().declare_subscriber(self.keys.alive_pattern, self._on_sample,
                                                                   history=True)

    def _on_sample(self, sample: Any) -> None:
        import zenoh

        instance = instance_from_alive_key(str(sample.key_expr), self.keys.prefix)
        if instance is None:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._ids.add(instance)
            else:
                self._ids.discard(instance)

    def ids(self) -> list[str]:
        """The live instances, sorted (this one included once its token is seen)."""
        with self._lock:
            return sorted(self._ids)

    def owner(self, payload: bytes) -> str:
        """The instance that answers a shared-key request whose body is ``payload``: the same on every
        instance that sees the same members. This instance counts as a member from its start
        to its end; a stopping instance withdraws its token first (answering its share with
        ``overloaded`` until its session closes), and the others take its share over as soon
        as they see the token go."""
        with self._lock:
            members = self._ids | {self.keys.instance}
        return rendezvous_owner(members, payload) or self.keys.instance
