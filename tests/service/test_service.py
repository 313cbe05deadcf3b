"""The service over real Zenoh sessions: plan by get, goals by put and get with progress and
results, state, cancel, queueing, and every kind of bad input (each gets an error reply that
says what is wrong and what is allowed, and the service keeps answering)."""
from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from falcon_plan.trajectory import Trajectory
from service.client import ServiceError
from service.keys import SCHEMA_NAMES

from service.testing import (GOAL_A_M, GOAL_B_M, HOME_M, PREFIX, check_schema, client_for, left_at_tolerance_mm,
                             running_service, wait_until)

KEY = f"{PREFIX}/sim0"


def raw_get(client, key: str, payload: bytes | None, encoding: str | None = "application/json"):
    """One get with raw bytes; returns the list of (ok?, decoded body)."""
    replies = client.session.get(key, payload=payload, encoding=encoding, timeout=10.0)
    out = []
    for reply in replies:
        sample = reply.ok if reply.ok is not None else reply.err
        out.append((reply.ok is not None, json.loads(sample.payload.to_bytes())))
        assert str(sample.encoding) == "application/json"
    return out


def test_plan_by_get_on_instance_and_shared_keys(client):
    # a move no other test plans, so this one reaches the planner
    body = check_schema(client.plan(GOAL_B_M, GOAL_A_M, request_id="plan-1", instance="sim0"), "plan_reply")
    assert body["request_id"] == "plan-1" and body["instance"] == "sim0"
    traj = Trajectory.from_dict(body["trajectory"])
    np.testing.assert_allclose(traj.position_m[0], GOAL_B_M, atol=1e-6)
    np.testing.assert_allclose(traj.position_m[-1], GOAL_A_M, atol=1e-6)
    assert traj.t_s[0] == 0.0 and 0.02 < traj.duration_s < 2.0
    assert body["report"]["status"] and body["timing"]["plan_s"] > 0 and not body["timing"]["cached"]
    # the shared key reaches the same planner; the repeat comes from the cache, identical
    shared = check_schema(client.plan(GOAL_B_M, GOAL_A_M, request_id="plan-2"), "plan_reply")
    assert shared["request_id"] == "plan-2" and shared["timing"]["cached"]
    assert shared["trajectory"] == body["trajectory"] and shared["report"] == body["report"]


VIA_M = (0.01, 0.012, 0.138)
"""A via point off the straight line GOAL_B_M -> GOAL_A_M, inside the workspace."""


def test_plan_with_via_point_end_velocity_and_payload(client):
    body = check_schema(client.plan(GOAL_B_M, GOAL_A_M, via_m=[VIA_M], goal_velocity_m_s=(0.0, 0.0, -0.05),
                                    payload_kg=0.1, request_id="via-1", instance="sim0"), "plan_reply")
    traj = Trajectory.from_dict(body["trajectory"])
    # the motion passes through the via point at one of its nodes
    gap_m = np.linalg.norm(traj.position_m - np.asarray(VIA_M), axis=1).min()
    assert gap_m < 1e-6, gap_m
    np.testing.assert_allclose(traj.position_m[[0, -1]], [GOAL_B_M, GOAL_A_M], atol=1e-6)
    np.testing.assert_allclose(traj.velocity_m_s[-1], (0.0, 0.0, -0.05), atol=1e-6)
    problem = body["report"]["problem"]
    assert problem["payload_kg"] == 0.1 and problem["via_m"] == [list(VIA_M)]
    # the same ends without the via point and the payload are another problem (not the cache's)
    plain = client.plan(GOAL_B_M, GOAL_A_M, goal_velocity_m_s=(0.0, 0.0, -0.05), instance="sim0")
    assert not plain["timing"]["cached"] and plain["report"]["problem"]["payload_kg"] == 0.0
    assert client.plan(GOAL_B_M, GOAL_A_M, via_m=[VIA_M], goal_velocity_m_s=(0.0, 0.0, -0.05), payload_kg=0.1,
                       instance="sim0")["timing"]["cached"]


def test_a_bad_via_point_gets_one_line_naming_it(client):
    with pytest.raises(ServiceError) as err:
        client.plan(GOAL_B_M, GOAL_A_M, via_m=[(0.0, 0.0, 0.30)], instance="sim0")
    assert (err.value.code, err.value.field) == ("outside_workspace", "via_m[0]")
    assert "via_m[0]" in str(err.value) and "\n" not in str(err.value) and err.value.allowed
    with pytest.raises(ServiceError) as err:
        client.submit_goal(GOAL_A_M, via_m=[(0.0, 0.0, 0.30)])
    assert (err.value.code, err.value.field) == ("outside_workspace", "via_m[0]")
    with pytest.raises(ServiceError) as err:
        client.plan(GOAL_B_M, GOAL_A_M, payload_kg=2.0, instance="sim0")
    assert (err.value.code, err.value.field) == ("invalid_request", "payload_kg") and "maximum 1" in str(err.value)
    with pytest.raises(ServiceError) as err:
        client.submit_goal(GOAL_A_M, start_velocity_m_s=(0.01, 0.0, 0.0))
    assert (err.value.code, err.value.field) == ("invalid_request", "start_velocity_m_s")
    assert client.info()["instance"] == "sim0"  # and the service goes on answering


def test_goal_by_put_publishes_progress_and_result(client):
    progress, published = [], []
    keys = client.keys()
    subs = [client.session.declare_subscriber(keys.goal_progress("put-1"),
                                              lambda s: progress.append(json.loads(s.payload.to_bytes()))),
            client.session.declare_subscriber(keys.goal_result("put-1"),
                                              lambda s: published.append(json.loads(s.payload.to_bytes())))]
    try:
        client.put_goal("put-1", GOAL_A_M)
        # a put is registered some time after it is sent: the client waits until the service knows it
        result = check_schema(client.wait_result("put-1", timeout_s=30), "goal_result")
        wait_until(lambda: published and published[-1]["status"] == result["status"], "the published result")
    finally:
        for sub in subs:
            sub.undeclare()
    assert result["status"] == "done", result["error"]
    assert result["plan_report"]["status"] and result["tracking_report"]["status"] == "completed"
    assert result["tracking_report"]["samples"] > 10
    assert result["started_at"] <= result["finished_at"]
    assert published and published[-1] == result
    for body in progress:
        check_schema(body, "goal_progress")
    phases = [p["phase"] for p in progress]
    assert phases[0] == "planning" and phases[-1] == "executing" and progress[-1]["fraction"] == 1.0
    executing = [p["fraction"] for p in progress if p["phase"] == "executing"]
    assert executing == sorted(executing)
    assert client.result("put-1") == result
    # the state shows the device where the executor left it (its final tracking error from the
    # plan's end, the goal); how small that error is, is the executor's business
    final_error_mm = 1e3 * np.linalg.norm(np.subtract(client.state()["position_m"], GOAL_A_M))
    track = result["tracking_report"]
    assert abs(final_error_mm - track["tracking"]["final_mm"]) < left_at_tolerance_mm(track)


def test_state_is_published_at_a_steady_rate_and_queryable(client, sim_service):
    samples, arrivals = [], []

    def on_state(sample) -> None:
        arrivals.append(time.monotonic())
        samples.append(json.loads(sample.payload.to_bytes()))

    sub = client.session.declare_subscriber(f"{KEY}/state", on_state)
    try:
        wait_until(lambda: len(samples) >= 30, "30 state publications")
    finally:
        sub.undeclare()
    # the mean rate over 30 publications: never above the set rate (a late one is skipped, not
    # made up); the floor is loose, as a loaded machine delays a sleeping publisher
    rate = sim_service.options.state_rate_hz
    measured_hz = (len(arrivals) - 1) / (arrivals[-1] - arrivals[0])
    assert 0.25 * rate <= measured_hz <= 1.5 * rate, measured_hz
    state = check_schema(client.state(), "state")
    for body in samples[:3]:
        check_schema(body, "state")
    assert state["device"] == "sim" and state["homed"] in ([True] * 3, [False] * 3)
    assert len(state["position_m"]) == 3 and len(state["encoders"]) == 3
    # a wildcard get over instances answers with each instance's own state key
    replies = list(client.session.get(f"{PREFIX}/*/state", timeout=5.0))
    assert [str(r.ok.key_expr) for r in replies] == [f"{KEY}/state"]


def test_goals_queue_in_order_and_cancel(client):
    first = check_schema(client.submit_goal(GOAL_B_M, goal_id="queue-1"), "goal_ack")
    second = check_schema(client.submit_goal(GOAL_A_M), "goal_ack")
    client.put_goal("queue-3", GOAL_B_M)
    client.session.put(f"{KEY}/goals/queue-3/cancel", b"")  # cancel by put: no reply
    assert first["position"] == 0 and second["position"] == 1
    assert second["id"].startswith("g-") and second["keys"]["result"] == f"{KEY}/goals/{second['id']}/result"
    assert client.result(second["id"])["status"] == "pending"
    # the worker takes the first goal from the queue when it wakes
    state = wait_until(lambda: (st := client.state())["executing"] == "queue-1" and st, "queue-1 to start")
    assert state["queue"][0] == second["id"]
    # a pending goal is dequeued at once; the running one is stopped and reported cancelled
    assert check_schema(client.cancel(second["id"]), "cancel_reply") == {
        "schema_version": 1, "id": second["id"], "instance": "sim0", "cancelled": True, "status": "cancelled"}
    running = client.cancel("queue-1")
    assert running["cancelled"] and running["status"] in ("running", "cancelled")
    assert client.wait_result("queue-1", timeout_s=30)["status"] == "cancelled"
    assert client.wait_result("queue-3", timeout_s=10)["status"] == "cancelled"  # the result key tells
    assert client.result(second["id"])["status"] == "cancelled"
    again = client.cancel("queue-1")
    assert not again["cancelled"] and again["status"] == "cancelled"
    with pytest.raises(ServiceError) as err:
        client.cancel("no-such-goal")
    assert err.value.code == "unknown_goal" and err.value.field == "id"
    with pytest.raises(ServiceError) as err:
        client.submit_goal(GOAL_A_M, goal_id="queue-1")
    assert err.value.code == "duplicate_goal_id"


GOOD = {"start_m": list(HOME_M), "goal_m": list(GOAL_A_M)}
BAD_PLAN_INPUTS = [
    ("malformed json", b'{"start_m": [0, 0,', "malformed_json", None),
    ("not utf-8", b'{"start_m": "\xff"}', "malformed_json", None),
    ("duplicate field", b'{"start_m": [0,0,0.14], "start_m": [0,0,0.1], "goal_m": [0,0,0.14]}', "malformed_json",
     "start_m"),
    ("not an object", b"[0, 0, 0.14]", "invalid_request", None),
    ("empty payload", b"", "invalid_request", None),
    ("wrong type", json.dumps({**GOOD, "start_m": "home"}).encode(), "invalid_request", "start_m"),
    ("wrong element type", json.dumps({**GOOD, "goal_m": [0, True, 0.13]}).encode(), "invalid_request", "goal_m[1]"),
    ("two coordinates", json.dumps({**GOOD, "goal_m": [0, 0.13]}).encode(), "invalid_request", "goal_m"),
    ("missing field", json.dumps({"start_m": list(HOME_M)}).encode(), "invalid_request", "goal_m"),
    ("unknown field", json.dumps({**GOOD, "speed": 3}).encode(), "invalid_request", "speed"),
    ("wrong schema version", json.dumps({**GOOD, "schema_version": 2}).encode(), "invalid_request", "schema_version"),
    ("NaN", b'{"start_m": [NaN, 0, 0.14], "goal_m": [0, 0, 0.13]}', "non_finite_number", None),
    ("Infinity", b'{"start_m": [0, 0, 0.14], "goal_m": [0, -Infinity, 0.13]}', "non_finite_number", None),
    ("overflow to infinity", b'{"start_m": [0, 0, 1e999], "goal_m": [0, 0, 0.13]}', "non_finite_number", None),
    ("far outside the box", json.dumps({**GOOD, "goal_m": [0, 0, 5.0]}).encode(), "invalid_request", "goal_m[2]"),
    ("outside the workspace", json.dumps({**GOOD, "goal_m": [0.0, 0.0, 0.30]}).encode(), "outside_workspace", "goal_m"),
    ("oversize", json.dumps({**GOOD, "request_id": "x", "pad": "y" * 70_000}).encode(), "payload_too_large", None),
    ("bad option value", json.dumps({**GOOD, "options": {"tc_max": -5}}).encode(), "invalid_problem",
     "options.tc_max"),
    ("unknown option", json.dumps({**GOOD, "options": {"warp": 9}}).encode(), "invalid_request", "options.warp"),
    ("bad option type", json.dumps({**GOOD, "options": {"hessian": 3}}).encode(), "invalid_problem",
     "options.hessian"),
    ("hogging budget", json.dumps({**GOOD, "options": {"time_budget_s": 500}}).encode(), "invalid_problem",
     "options.time_budget_s"),
]


@pytest.mark.parametrize("name,payload,code,field", BAD_PLAN_INPUTS, ids=[b[0] for b in BAD_PLAN_INPUTS])
def test_bad_plan_input_gets_an_error_reply(client, name, payload, code, field):
    replies = raw_get(client, f"{KEY}/plan", payload)
    assert len(replies) == 1
    ok, body = replies[0]
    assert not ok, body
    check_schema(body, "error")
    assert body["error"]["code"] == code and body["error"]["field"] == field
    assert len(body["error"]["message"]) > 15
    if code in ("invalid_request", "payload_too_large", "non_finite_number", "outside_workspace",
                "invalid_problem"):
        assert body["error"].get("allowed"), body
    assert client.info()["instance"] == "sim0"  # and the service goes on answering


def test_error_reply_names_what_is_allowed(client):
    _ok, body = raw_get(client, f"{KEY}/plan", json.dumps({**GOOD, "speed": 3}).encode())[0]
    allowed = ("allowed fields: ['goal_m', 'goal_velocity_m_s', 'options', 'payload_kg', 'request_id', "
               "'schema_version', 'start_m', 'start_velocity_m_s', 'timeout_s', 'via_m']")
    assert allowed in body["error"]["message"]
    _ok, body = raw_get(client, f"{KEY}/plan", json.dumps({**GOOD, "options": {"n_intervals": 2}}).encode())[0]
    assert body["error"]["field"] == "options.n_intervals"
    assert body["error"]["allowed"] == "a whole number in [4, 400]"
    _ok, body = raw_get(client, f"{KEY}/plan", json.dumps({**GOOD, "options": {"warp": 9}}).encode())[0]
    assert "n_intervals" in body["error"]["allowed"] and "tc_max" in body["error"]["allowed"]
    _ok, body = raw_get(client, f"{KEY}/plan", json.dumps({**GOOD, "goal_m": [0, 0.13]}).encode())[0]
    assert "an array of 3 numbers" in body["error"]["message"]


def test_other_encodings_are_refused(client):
    (ok, body), = raw_get(client, f"{KEY}/plan", json.dumps(GOOD).encode(), encoding="application/python-pickle")
    assert not ok and body["error"]["code"] == "unsupported_encoding"
    assert "application/json" in body["error"]["allowed"]


def test_unknown_and_publication_only_keys(client):
    for key in (f"{KEY}/bogus", f"{KEY}/goals/x/progress", f"{KEY}/errors", f"{KEY}/schema/nope"):
        (ok, body), = raw_get(client, key, None)
        assert not ok and body["error"]["code"] == "unknown_key", key
        assert body["error"]["allowed"]


def test_bad_goals_by_get_and_by_put(client):
    with pytest.raises(ServiceError) as err:
        client.submit_goal((0.0, 0.0, 0.30))
    assert err.value.code == "outside_workspace" and err.value.field == "goal_m"
    with pytest.raises(ServiceError) as err:
        client.submit_goal(GOAL_A_M, goal_id="bad id/with slash")
    assert err.value.code == "invalid_request" and err.value.field == "id"
    errors = []
    sub = client.session.declare_subscriber(f"{KEY}/errors", lambda s: errors.append(json.loads(s.payload.to_bytes())))
    try:
        client.session.put(f"{KEY}/goals/submit", json.dumps({"goal_m": list(GOAL_A_M)}).encode())  # no id
        client.session.put(f"{KEY}/goals/submit", b'{"id": "nan-1", "goal_m": [NaN, 0, 0.13]}')
        client.session.put(f"{KEY}/goals/ghost/cancel", b"")
        client.session.put(f"{KEY}/goals/put-1/progress", b"{}")  # publication-only key
        wait_until(lambda: len(errors) >= 4, "four error publications")
    finally:
        sub.undeclare()
    for body in errors:
        check_schema(body, "error")
    # puts from one session are handled in the order sent
    assert [(e["error"]["code"], e.get("request_id"), e["key"]) for e in errors] == [
        ("invalid_request", None, f"{KEY}/goals/submit"), ("non_finite_number", "nan-1", f"{KEY}/goals/submit"),
        ("unknown_goal", "ghost", f"{KEY}/goals/ghost/cancel"),
        ("unknown_key", "put-1", f"{KEY}/goals/put-1/progress")]
    with pytest.raises(ServiceError) as err:
        client.result("nan-1")
    assert err.value.code == "unknown_goal"


def test_schemas_and_info_are_served(client):
    info = check_schema(client.info(), "info")
    assert info["instance"] == "sim0" and info["can_execute"] and info["max_payload_bytes"] == 64 * 1024
    assert sorted(info["schemas"]) == sorted(SCHEMA_NAMES)
    for name in SCHEMA_NAMES:
        shared = client.schema(name)
        assert shared["$id"] == f"falcon-plan/service/{name}"
        assert client.request(f"{KEY}/schema/{name}") == shared


def test_concurrent_requests_are_all_answered_and_not_mixed(client):
    client.plan(HOME_M, GOAL_B_M)  # plan once; the rest come from the cache
    answers: dict[str, dict] = {}

    def ask(i: int) -> None:
        goal = GOAL_B_M if i % 2 else (0.0, 0.0, 0.30)  # alternate good and bad requests
        try:
            answers[f"c{i}"] = client.plan(HOME_M, goal, request_id=f"c{i}")
        except ServiceError as exc:
            answers[f"c{i}"] = exc.body

    threads = [threading.Thread(target=ask, args=(i,)) for i in range(40)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert len(answers) == 40
    for rid, body in answers.items():
        assert body["request_id"] == rid
        assert ("trajectory" in body) == (int(rid[1:]) % 2 == 1)


def test_planning_only_instance_refuses_device_requests(model):
    with running_service("plan0", "none", model) as service, client_for(service, "plan0") as c:
        assert not c.info()["can_execute"]
        for call in (lambda: c.submit_goal(GOAL_A_M), c.state):
            with pytest.raises(ServiceError) as err:
                call()
            assert err.value.code == "no_device"
        assert c.plan(HOME_M, GOAL_B_M)["instance"] == "plan0"


def test_emulated_device_runs_a_goal_through_the_usb_path(model):
    """``--device emulated``: the UsbFalcon driver over the emulated pyusb backend; the
    device is homed before the first goal and read with zero force while idle."""
    with running_service("emu0", "emulated", model) as service, client_for(service, "emu0") as c:
        assert c.state()["homed"] == [False, False, False]
        ack = c.submit_goal(GOAL_B_M)
        result = check_schema(c.wait_result(ack["id"], timeout_s=30), "goal_result")
        assert result["status"] == "done", result["error"]
        assert result["tracking_report"]["rate_hz"] == 1000.0
        first = c.state()
        assert first["homed"] == [True] * 3
        wait_until(lambda: c.state()["t_s"] > first["t_s"], "a newer reading of the idle device")
        # idle, read with zero force about 50 times a second, its released grip held still (as a
        # user holds a real one): it stays where the goal left it, and the next goal starts
        # there (before, each read stepped the emulated plant and within seconds the grip lay
        # on its stops, outside the workspace, where no goal could start)
        idle = c.state()
        wait_until(lambda: c.state()["t_s"] > idle["t_s"] + 1.0, "a second of idle readings", timeout_s=30)
        assert np.abs(np.subtract(c.state()["encoders"], idle["encoders"])).max() <= 1
        again = c.wait_result(c.submit_goal(GOAL_A_M)["id"], timeout_s=30)
        assert again["status"] == "done", again["error"]


def test_a_goal_cannot_start_from_outside_the_workspace_and_says_what_to_do(model):
    """A released real Falcon sags onto its stops, outside the workspace: a goal starting there
    is refused with where the device is, why, and what to do (it used to fail with an internal
    kinematics message, or with the planner's outside-the-workspace error for a start the user
    never gave)."""
    from service.codec import RequestError
    from service.device import make_runner

    runner = make_runner("sim", model)
    try:
        runner.require_start((0.0, 0.0, 0.125))            # inside: nothing to say
        with pytest.raises(RequestError) as err:
            runner.require_start((0.0198, -0.0975, 0.0567))   # where the emulated grip fell
        assert err.value.code == "outside_workspace" and err.value.field == "start_m"
        assert "the device's position" in str(err.value) and "move the grip into the workspace" in str(err.value)
    finally:
        runner.close()
