"""Pure parts of the service: the key layout, strict JSON decoding, the schema checker and
the published schema files (no zenoh)."""
from __future__ import annotations

import json

import pytest

from falcon_plan.errors import InvalidParameterError
from service.codec import (ERROR_CODES, RequestError, decode_json, decode_request, encode_json, load_schema,
                           validate)
from service.config import SessionSettings, parse_override
from service.keys import SCHEMA_NAMES, Route, ServiceKeys, instance_from_alive_key


def test_key_layout_round_trips_through_route():
    keys = ServiceKeys("lab/falcon", "bench-1")
    assert keys.plan == "lab/falcon/bench-1/plan" and keys.alive == "lab/falcon/alive/bench-1"
    cases = {keys.plan: Route("plan"), keys.shared_plan: Route("plan"), keys.state: Route("state"),
             keys.info: Route("info"), keys.errors: Route("errors"), keys.goals_submit: Route("goals/submit"),
             keys.goal_result("g1"): Route("goal/result", "g1"), keys.goal_cancel("g1"): Route("goal/cancel", "g1"),
             keys.goal_progress("g1"): Route("goal/progress", "g1"), keys.schema("state"): Route("schema", "state"),
             keys.shared_schema("error"): Route("schema", "error")}
    for key, route in cases.items():
        assert keys.route(key) == route, key
    for key in ("lab/falcon/bench-1", "lab/falcon/bench-1/goals", "lab/falcon/other/plan",
                "lab/falcon/bench-1/goals/g1/explode", "lab/falcon/bench-1/plan/extra"):
        assert keys.route(key) is None, key
    assert instance_from_alive_key(keys.alive, "lab/falcon") == "bench-1"
    assert instance_from_alive_key("lab/falcon/alive/**", "lab/falcon") is None


@pytest.mark.parametrize("prefix,instance", [("fal*con", "a"), ("a//b", "a"), ("", "a"), ("falcon", "plan"),
                                             ("falcon", "alive"), ("falcon", "-x"), ("falcon", "a/b"),
                                             ("falcon", "x" * 65), ("falcon", "$*")])
def test_bad_prefixes_and_instance_ids_are_refused(prefix, instance):
    with pytest.raises(InvalidParameterError):
        ServiceKeys(prefix, instance)


@pytest.mark.parametrize("payload,code", [
    (b"NaN", "non_finite_number"), (b'{"a": -Infinity}', "non_finite_number"), (b'{"a": 1e400}', "non_finite_number"),
    (b'{"a": 1, "a": 2}', "malformed_json"), (b"\xfe\xff", "malformed_json"), (b'{"a": [}', "malformed_json"),
    (b"[" * 100_000 + b"]" * 100_000, "payload_too_large"), (b"3", "invalid_request"), (b"", "invalid_request")])
def test_strict_decoding(payload, code):
    with pytest.raises(RequestError) as err:
        decode_json(payload, limit=64 * 1024)
    assert err.value.code == code


def test_deep_nesting_within_the_size_limit_is_a_clean_error():
    with pytest.raises(RequestError) as err:
        decode_json(b"[" * 30_000 + b"]" * 30_000)
    assert err.value.code in ("malformed_json", "invalid_request")


def test_encoding_is_strict_json_without_nan():
    body = json.loads(encode_json({"x": float("nan"), "y": [1.0, float("inf")], "z": 2}))
    assert body == {"x": None, "y": [1.0, None], "z": 2}


def test_every_schema_loads_and_lists_known_error_codes():
    for name in SCHEMA_NAMES:
        schema = load_schema(name)
        assert schema["$id"] == f"falcon-plan/service/{name}" and schema["type"] == "object"
    assert load_schema("error")["properties"]["error"]["properties"]["code"]["enum"] == list(ERROR_CODES)


def test_schema_checker_names_the_field_and_what_is_allowed():
    schema = load_schema("goal_request")
    validate({"goal_m": [0, 0, 0.13], "id": "ok-1"}, schema)
    for bad, field in [({"goal_m": [0, 0]}, "goal_m"), ({"goal_m": [0, 0, "z"]}, "goal_m[2]"),
                       ({"goal_m": [0, 0, 0.1], "id": "a b"}, "id"), ({}, "goal_m"),
                       ({"goal_m": [0, 0, 0.1], "extra": 1}, "extra"), ({"goal_m": [0, 0, 2.0]}, "goal_m[2]")]:
        with pytest.raises(RequestError) as err:
            validate(bad, schema)
        assert err.value.code == "invalid_request" and err.value.field == field, bad
        assert "allowed" in str(err.value)
    data = decode_request(b'{"goal_m": [0, 0, 0.13]}', "goal_request", encoding="application/json")
    assert data == {"goal_m": [0, 0, 0.13]}
    with pytest.raises(RequestError) as err:
        decode_request(b"{}", "goal_request", encoding="application/x-pickle")
    assert err.value.code == "unsupported_encoding"


def test_session_settings_default_to_loopback_without_multicast():
    server = SessionSettings.server()
    assert server.listen == ("tcp/127.0.0.1:7447",) and server.connect == ()
    conf = SessionSettings.server(cfg=["scouting/gossip/enabled:false"]).to_zenoh()
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    client = SessionSettings.client()
    assert client.listen == () and client.connect == ("tcp/127.0.0.1:7447",)
    assert json.loads(client.to_zenoh().get_json("listen/endpoints")) == []
    assert parse_override("connect/endpoints:[\"tcp/127.0.0.1:1\"]") == ("connect/endpoints", '["tcp/127.0.0.1:1"]')
    for bad in (lambda: parse_override("novalue"), lambda: SessionSettings(mode="bridge"),
                lambda: SessionSettings(mode="client"),
                lambda: SessionSettings.server(cfg=["no/such/key:1"]).to_zenoh()):
        with pytest.raises(InvalidParameterError):
            bad()


def test_input_error_codes_are_codes_and_set_the_exit_status() -> None:
    """A refusal of the request's own content is bad input (exit 2, as the library's own
    refusals); the service failing to do what was asked is a failed run (exit 1)."""
    from falcon_plan.cli import EXIT_FAILED, EXIT_USAGE, _classify
    from service.client import ServiceError
    from service.codec import INPUT_ERROR_CODES

    assert INPUT_ERROR_CODES < set(ERROR_CODES)
    far = ServiceError({"error": {"code": "outside_workspace", "message": "via_m[0] is outside the workspace"}})
    busy = ServiceError({"error": {"code": "overloaded", "message": "64 plans waiting"}})
    assert (far.bad_input, busy.bad_input) == (True, False)
    assert _classify(far)[0] == EXIT_USAGE and _classify(busy)[0] == EXIT_FAILED


def test_a_point_given_in_millimetres_gets_the_metres_hint() -> None:
    """As on the command line: a coordinate like 130 in a point field says points are in metres."""
    import json

    from service.codec import RequestError
    from service.handlers import parse_goal_request

    for body, hint in (({"goal_m": [0, 0, 130]}, "did you mean 0.13?"),
                       ({"goal_m": [0, 0, 0.13], "via_m": [[-30, 0, 0.12]]}, "did you mean -0.03?")):
        with pytest.raises(RequestError, match="points are in metres") as err:
            parse_goal_request(json.dumps(body).encode(), require_id=False)
        assert hint in str(err.value)
