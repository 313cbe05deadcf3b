"""A small typed client of the service that uses only the documented keys and JSON bodies.

``with FalconClient(SessionSettings.client([...])) as client: client.plan(start, goal)``.
Error replies raise :class:`ServiceError` with the service's ``code``, ``message`` and
``field``; no reply within the timeout raises :class:`ServiceUnavailable`.

Instances: :meth:`FalconClient.instances` lists the running ones from their liveliness tokens
(``<prefix>/alive/*``). :meth:`FalconClient.plan` without an instance uses the shared
``<prefix>/plan`` key: every instance receives the get and exactly one answers (the instances
agree on it, spreading the load; see service/members.py); with ``instance`` it goes to that
instance's own key. Each plan request says how long the client waits (``timeout_s``), so an
instance never plans for a client that has given up.
"""
from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any, Callable, Sequence, TypedDict, Unpack

from falcon_plan.errors import FalconPlanError
from service.codec import INPUT_ERROR_CODES
from service.config import SessionSettings, open_session
from service.keys import DEFAULT_INSTANCE, DEFAULT_PREFIX, ServiceKeys, instance_from_alive_key, validate_id

log = logging.getLogger(__name__)

FINAL = ("done", "failed", "cancelled", "preempted")
RESULT_POLL_S = 1.0
"""While waiting for a goal's result, the client also asks for it this often [s] (a result
published before its subscription reached the service is not missed)."""


class Motion(TypedDict, total=False):
    """The optional problem fields of a goal, as keywords of :meth:`FalconClient.submit_goal`
    and :meth:`FalconClient.put_goal` (meanings as for :meth:`FalconClient.plan`)."""

    via_m: Sequence[Sequence[float]]
    start_velocity_m_s: Sequence[float]
    goal_velocity_m_s: Sequence[float]
    payload_kg: float


class ServiceError(FalconPlanError, RuntimeError):
    """An error reply: ``code``, ``field``, ``allowed`` and the whole ``body``; ``bad_input``
    is True when the code refuses the request's own content
    (:data:`~service.codec.INPUT_ERROR_CODES`)."""

    def __init__(self, body: dict[str, Any]) -> None:
        err = body.get("error", {}) if isinstance(body, dict) else {}
        super().__init__(f"{err.get('code', 'error')}: {err.get('message', body)}")
        self.body = body
        self.code: str = err.get("code", "error")
        self.field: str | None = err.get("field")
        self.allowed: Any = err.get("allowed")
        self.bad_input: bool = self.code in INPUT_ERROR_CODES


DISCOVERY_S = 3.0
"""How long a request that found nobody serving its key keeps asking [s] (capped by its
timeout): two peered instances, a fresh client connected to one found the other after up to a
second or so (gossip); asked once, 5 of 6 state requests to the other failed at once."""
DISCOVERY_RETRY_S = 0.05
"""The pause between those asks [s]."""
INSTANCES_SETTLE_S = 1.0
"""How long :meth:`FalconClient.instances` keeps collecting liveliness tokens [s]."""


class ServiceUnavailable(FalconPlanError, TimeoutError):
    """No instance answered (none running, or the timeout passed)."""


def _loads(zbytes: Any) -> Any:
    return json.loads(zbytes.to_bytes() or b"null")


def no_reply_message(key: str, timeout_s: float, waited_s: float) -> str:
    """What a get on ``key`` that ended without a reply after ``waited_s`` [s] means: with the
    timeout ``timeout_s`` [s] spent, nobody answered in time; ended well before it, Zenoh knew
    of no queryable on the key (no instance reachable), so nothing was waited for."""
    if waited_s >= 0.9 * timeout_s:
        return f"no reply on {key} within {timeout_s:g} s (is the instance running, or busy?)"
    return (f"no instance answers on {key}: asked for {waited_s:.1f} s without a reply, as nothing "
            "reachable serves that key (is an instance running, under this prefix and id, and reachable "
            "through --connect/--listen? 'falcon-plan request instances' lists those found)")


class FalconClient:
    """A session plus helpers for every documented key.

    Parameters
    ----------
    settings : how to open the session (default: peer, connect to tcp/127.0.0.1:7447).
    prefix : key prefix of the instances.
    instance : default instance for device operations (goals, state, cancel).
    timeout_s : default reply timeout [s].
    """

    def __init__(self, settings: SessionSettings | None = None, prefix: str = DEFAULT_PREFIX,
                 instance: str = DEFAULT_INSTANCE, timeout_s: float = 10.0, session: Any = None) -> None:
        import zenoh

        self._zenoh = zenoh
        self.prefix = prefix
        self.instance = instance
        self.timeout_s = timeout_s
        self._owns_session = session is None
        self.session = session if session is not None else open_session(settings or SessionSettings.client())

    def __enter__(self) -> "FalconClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Close the session (if this client opened it)."""
        if self._owns_session and not self.session.is_closed():
            self.session.close()

    def keys(self, instance: str | None = None) -> ServiceKeys:
        """The keys of ``instance`` (default: this client's)."""
        return ServiceKeys(self.prefix, instance or self.instance)

    # --- raw request --------------------------------------------------------------------------
    def request(self, key: str, body: dict[str, Any] | None = None, timeout_s: float | None = None) -> dict[str, Any]:
        """A get on ``key`` with a JSON body; the first reply's body, or ServiceError. A get
        that ends at once without a reply (Zenoh knows of no instance serving the key yet: a
        peer learns of the others by gossip, some time after it connects to one; or the
        instance it knows chose another for a shared key) is asked again until
        :data:`DISCOVERY_S` (at most the timeout) has passed: nothing was received, so nothing is
        done twice."""
        payload = json.dumps(body, allow_nan=False).encode() if body is not None else None
        timeout = timeout_s or self.timeout_s
        start = time.monotonic()
        while True:
            asked = time.monotonic()
            replies = self.session.get(key, payload=payload, encoding=self._zenoh.Encoding.APPLICATION_JSON,
                                       timeout=max(timeout - (asked - start), 0.05))
            for reply in replies:
                if reply.ok is not None:
                    return _loads(reply.ok.payload)
                try:
                    body = _loads(reply.err.payload)
                except ValueError:  # not the service's: Zenoh's own (e.g. its timeout)
                    raise ServiceUnavailable(f"no reply on {key}: {reply.err.payload.to_string()}") from None
                raise ServiceError(body)
            now = time.monotonic()
            if now - asked >= 0.5 * (timeout - (asked - start)) or now - start >= min(timeout, DISCOVERY_S):
                break   # it waited (busy, or gone), or discovery had its time
            time.sleep(DISCOVERY_RETRY_S)
        raise ServiceUnavailable(no_reply_message(key, timeout, time.monotonic() - start))

    # --- discovery ----------------------------------------------------------------------------
    def instances(self, timeout_s: float = 2.0) -> list[str]:
        """Ids of the running instances under the prefix (from liveliness tokens), sorted: the
        tokens seen by asking again for :data:`INSTANCES_SETTLE_S` (at most ``timeout_s`` [s]),
        as a fresh peer learns of the instances beyond the one it connected to by gossip (asked
        once, a second peered instance was missing in 3 of 6 listings)."""
        found = set()
        start = time.monotonic()
        while True:
            left = max(timeout_s - (time.monotonic() - start), 0.05)
            for reply in self.session.liveliness().get(f"{self.prefix}/alive/*", timeout=left):
                if reply.ok is not None:
                    inst = instance_from_alive_key(str(reply.ok.key_expr), self.prefix)
                    if inst:
                        found.add(inst)
            if time.monotonic() - start >= min(timeout_s, INSTANCES_SETTLE_S):
                return sorted(found)
            time.sleep(DISCOVERY_RETRY_S)

    def info(self, instance: str | None = None) -> dict[str, Any]:
        """What an instance is (device, keys, limits)."""
        return self.request(self.keys(instance).info)

    def schema(self, name: str) -> dict[str, Any]:
        """The published JSON schema ``name`` (one of keys.SCHEMA_NAMES; shared key)."""
        return self.request(self.keys().shared_schema(name))

    # --- planning -----------------------------------------------------------------------------
    def plan(self, start_m: Sequence[float], goal_m: Sequence[float], options: dict[str, Any] | None = None, *,
             via_m: Sequence[Sequence[float]] = (), start_velocity_m_s: Sequence[float] | None = None,
             goal_velocity_m_s: Sequence[float] | None = None, payload_kg: float | None = None,
             instance: str | None = None, request_id: str | None = None,
             timeout_s: float | None = None) -> dict[str, Any]:
        """Plan from ``start_m`` to ``goal_m`` [m, base frame] through the points ``via_m``
        [m] in order, from ``start_velocity_m_s`` to ``goal_velocity_m_s`` [m/s] (None: rest),
        carrying ``payload_kg`` [kg] at the end effector (None: none), with ``options``
        (PlanOptions fields; None: the service's defaults) on ``instance`` (default: any one,
        via the shared key), tagged with ``request_id`` (echoed in the reply), waiting at most
        ``timeout_s`` [s] (default the client's); the plan reply body."""
        timeout_s = timeout_s or self.timeout_s
        body: dict[str, Any] = {"schema_version": 1, "start_m": list(start_m), "goal_m": list(goal_m),
                                **_motion_fields(via_m, start_velocity_m_s, goal_velocity_m_s, payload_kg),
                                "timeout_s": timeout_s}
        if options:
            body["options"] = options
        if request_id is not None:
            body["request_id"] = request_id
        key = self.keys(instance).plan if instance else self.keys().shared_plan
        return self.request(key, body, timeout_s)

    # --- goals --------------------------------------------------------------------------------
    def submit_goal(self, goal_m: Sequence[float], *, start_m: Sequence[float] | None = None,
                    options: dict[str, Any] | None = None, goal_id: str | None = None,
                    instance: str | None = None, release: bool = False, preempt: bool = False,
                    **motion: Unpack[Motion]) -> dict[str, Any]:
        """Submit a goal to ``goal_m`` [m] by get (from ``start_m``, default where the device
        is; ``options``: PlanOptions fields; ``goal_id``: default one the service makes) on
        ``instance``: the acknowledgement (id, position) or ServiceError. ``release``: a cancel
        in motion drops to zero force at once instead of braking to rest and holding; ``preempt``:
        replace the running goal in motion (spliced in) instead of waiting. ``motion``: the
        keywords ``via_m``, ``start_velocity_m_s`` (only with ``start_m``),
        ``goal_velocity_m_s`` and ``payload_kg`` as for :meth:`plan`."""
        body = self._goal_body(goal_m, start_m, options, goal_id, motion)
        if release:
            body["release"] = True
        if preempt:
            body["preempt"] = True
        return self.request(self.keys(instance).goals_submit, body)

    def put_goal(self, goal_id: str, goal_m: Sequence[float], *, start_m: Sequence[float] | None = None,
                 options: dict[str, Any] | None = None, instance: str | None = None,
                 **motion: Unpack[Motion]) -> None:
        """Submit the goal ``goal_id`` to ``goal_m`` [m] by put (``start_m``, ``options``,
        ``instance`` and the ``motion`` keywords as for :meth:`submit_goal`; fire and forget:
        rejections appear on the errors key, and the service may register the goal after this
        returns, so ask for it through :meth:`wait_known` or :meth:`wait_result`)."""
        self.session.put(self.keys(instance).goals_submit,
                         json.dumps(self._goal_body(goal_m, start_m, options, goal_id, motion)).encode(),
                         encoding=self._zenoh.Encoding.APPLICATION_JSON)

    @staticmethod
    def _goal_body(goal_m: Sequence[float], start_m: Sequence[float] | None, options: dict[str, Any] | None,
                   goal_id: str | None, motion: Motion) -> dict[str, Any]:
        body: dict[str, Any] = {"schema_version": 1, "goal_m": list(goal_m)}
        if start_m is not None:
            body["start_m"] = list(start_m)
        body.update(_motion_fields(**motion))
        if options:
            body["options"] = options
        if goal_id is not None:
            body["id"] = goal_id
        return body

    def result(self, goal_id: str, instance: str | None = None) -> dict[str, Any]:
        """The status and reports of goal ``goal_id`` on ``instance`` now (InvalidParameterError
        for an id that is not one: a key pattern like ``a*`` ended in Zenoh's own error)."""
        return self.request(self.keys(instance).goal_result(validate_id(goal_id, "goal id")))

    def cancel(self, goal_id: str, instance: str | None = None) -> dict[str, Any]:
        """Cancel goal ``goal_id`` on ``instance`` (by get, so the answer says what happened;
        InvalidParameterError for an id that is not one)."""
        return self.request(self.keys(instance).goal_cancel(validate_id(goal_id, "goal id")))

    def state(self, instance: str | None = None) -> dict[str, Any]:
        """The device state now."""
        return self.request(self.keys(instance).state)

    def wait_known(self, goal_id: str, *, instance: str | None = None, timeout_s: float = 10.0) -> dict[str, Any]:
        """Poll the result key until ``instance`` knows goal ``goal_id`` (a put is registered
        some time after it is sent), at most ``timeout_s`` [s]; its result body now. Raises
        the ``unknown_goal`` ServiceError if it is still unknown then."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return self.result(goal_id, instance)
            except ServiceError as exc:
                if exc.code != "unknown_goal" or time.monotonic() > deadline:
                    raise
            time.sleep(0.02)

    def wait_result(self, goal_id: str, *, instance: str | None = None, timeout_s: float = 60.0,
                    on_progress: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
        """Wait at most ``timeout_s`` [s] for the final result of goal ``goal_id`` on
        ``instance`` (subscribing to its result and progress keys, then asking until the
        instance knows the goal, and again every :data:`RESULT_POLL_S`, so a result published
        before the subscription reached the service is not missed and a goal just sent by put
        is waited for); ``on_progress`` gets each progress body."""
        keys = self.keys(instance)
        final = threading.Event()
        box: dict[str, Any] = {}

        def on_result(sample: Any) -> None:
            body = _loads(sample.payload)
            if body.get("status") in FINAL:
                box["result"] = body
                final.set()

        subs = [self.session.declare_subscriber(keys.goal_result(goal_id), on_result)]
        if on_progress is not None:
            subs.append(self.session.declare_subscriber(keys.goal_progress(goal_id),
                                                        lambda s: on_progress(_loads(s.payload))))
        deadline = time.monotonic() + timeout_s
        try:
            now = self.wait_known(goal_id, instance=instance, timeout_s=min(timeout_s, 10.0))
            # asked again now and then: a subscription reaches the service some time after it is
            # declared, and a result published meanwhile (the goal ending just then) never comes
            while now.get("status") not in FINAL:
                if final.wait(max(0.0, min(RESULT_POLL_S, deadline - time.monotonic()))):
                    return box["result"]
                if time.monotonic() >= deadline:
                    raise ServiceUnavailable(f"goal {goal_id} did not finish within {timeout_s} s")
                now = self.result(goal_id, instance)
            return now
        finally:
            for sub in subs:
                sub.undeclare()


def _motion_fields(via_m: Sequence[Sequence[float]] = (), start_velocity_m_s: Sequence[float] | None = None,
                   goal_velocity_m_s: Sequence[float] | None = None,
                   payload_kg: float | None = None) -> dict[str, Any]:
    """The optional problem fields of a plan or goal body (those given), as JSON values."""
    body: dict[str, Any] = {}
    if via_m:
        body["via_m"] = [list(map(float, p)) for p in via_m]
    for name, value in (("start_velocity_m_s", start_velocity_m_s), ("goal_velocity_m_s", goal_velocity_m_s)):
        if value is not None:
            body[name] = list(map(float, value))
    if payload_kg is not None:
        body["payload_kg"] = float(payload_kg)
    return body


def wait_for_instance(client: FalconClient, instance: str, timeout_s: float = 10.0) -> None:
    """Block until ``instance`` is alive (its liveliness token is visible to ``client``), at
    most ``timeout_s`` [s] (then ServiceUnavailable)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if instance in client.instances(timeout_s=0.5):
            return
        time.sleep(0.05)
    raise ServiceUnavailable(f"instance {instance!r} not alive under {client.prefix} after {timeout_s} s")
