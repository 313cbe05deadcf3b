"""The service under faults, over real sessions and real planning processes: a plan past the
service's cap, queue time counted in a request's deadline, requests abandoned by their
clients, cancel while planning and while executing, shutdown with a plan in flight, a put on
a key that takes none, and goals outliving their submitter."""
from __future__ import annotations

import json
import threading
import time
from typing import Any, Iterator

import pytest

from service.client import FalconClient, ServiceError
from service.options import ServiceOptions
from service.server import FalconService
from service.testing import GOAL_A_M, GOAL_B_M, HOME_M, check_schema, client_for, running_service, wait_until

CAP_S = 3.0
"""The test instance's cap on one request [s] (30 s in production)."""

LONG = {"hessian": "exact", "n_intervals": 400, "switching": False, "refine": True, "plant_check": True, "crosscheck": True}
"""Legal options that keep a planner busy for ~30 s on this machine."""

SLOW_MOTION = {"tc_max": 950}
"""A weak command limit (800 usable after the 150 feedback reserve): GOAL_A_M is then
~0.31 s away instead of 0.07 s."""


@pytest.fixture(scope="module")
def faults(model: Any) -> Iterator[FalconService]:
    """An instance with a simulated device, one planning process and a 3 s cap."""
    with running_service("flt0", "sim", model, options=ServiceOptions(request_cap_s=CAP_S)) as service:
        yield service


@pytest.fixture
def fclient(faults: FalconService) -> Iterator[FalconClient]:
    with client_for(faults, "flt0") as c:
        yield c


def _planning(client: FalconClient) -> dict[str, int]:
    return check_schema(client.info(), "info")["planning"]


def _wait_idle(client: FalconClient) -> None:
    """Until the pool is idle (after a kill, its process has restarted)."""
    wait_until(lambda: (p := _planning(client))["running"] == 0 and p["waiting"] == 0, "an idle planning pool", 30.0)


def _wait_planning(client: FalconClient) -> None:
    """Until the pool's process is planning something."""
    wait_until(lambda: _planning(client)["running"] == 1, "a plan to start", 30.0)


class _Get:
    """A get in the background: records (ok, body, seconds after sending) of each reply."""

    def __init__(self, client: FalconClient, key: str, body: dict[str, Any], timeout_s: float) -> None:
        self.replies: list[tuple[bool, dict[str, Any], float]] = []
        self.done = threading.Event()
        self.t0 = time.monotonic()

        def on_reply(reply: Any) -> None:
            sample = reply.ok if reply.ok is not None else reply.err
            text = sample.payload.to_bytes()
            body_ = json.loads(text) if text.startswith(b"{") else {"zenoh": text.decode()}
            self.replies.append((reply.ok is not None, body_, time.monotonic() - self.t0))

        client.session.get(key, on_reply, payload=json.dumps(body).encode(), timeout=timeout_s)
        threading.Thread(target=self._watch, args=(client, key), daemon=True).start()

    def _watch(self, client: FalconClient, key: str) -> None:
        while not self.replies and time.monotonic() - self.t0 < 60:
            time.sleep(0.01)
        self.done.set()


def _plan_body(goal_m, options=None, timeout_s=None, request_id=None) -> dict[str, Any]:
    body: dict[str, Any] = {"start_m": list(HOME_M), "goal_m": list(goal_m)}
    if options:
        body["options"] = options
    if timeout_s is not None:
        body["timeout_s"] = timeout_s
    if request_id:
        body["request_id"] = request_id
    return body


def test_a_plan_past_the_cap_is_answered_at_the_cap_and_frees_the_worker(fclient):
    _wait_idle(fclient)
    before = _planning(fclient)
    t0 = time.monotonic()
    with pytest.raises(ServiceError) as info:
        fclient.plan(HOME_M, GOAL_A_M, LONG, instance="flt0", timeout_s=20.0)
    elapsed = time.monotonic() - t0
    assert info.value.code == "deadline_exceeded" and "while planning" in str(info.value)
    # at the cap, not at the client's 20 s nor at the plan's ~30 s (loose: a loaded machine is late)
    assert CAP_S - 0.1 < elapsed < CAP_S + 8.0
    _wait_idle(fclient)
    after = _planning(fclient)
    assert after["deadline_exceeded"] == before["deadline_exceeded"] + 1
    assert after["restarts"] == before["restarts"] + 1  # the busy process was replaced
    body = fclient.plan(HOME_M, (0.015, 0.0, 0.13), instance="flt0", timeout_s=20.0)
    assert not body["timing"]["cached"] and body["timing"]["plan_s"] < CAP_S


@pytest.mark.slow
def test_queue_time_counts_and_abandoned_requests_are_never_planned(fclient):
    _wait_idle(fclient)
    key = fclient.keys().plan
    hog = _Get(fclient, key, _plan_body(GOAL_A_M, LONG, request_id="hog"), 20.0)
    _wait_planning(fclient)  # the hog is planning now
    before = _planning(fclient)
    # a client that waits 1 s: the service answers it at 1 s, unplanned, although it never
    # reached a worker (its queue time counted)
    patient = _Get(fclient, key, _plan_body((0.011, 0.0, 0.13), timeout_s=1.0, request_id="queued"), 5.0)
    # clients that give up after 0.3 s and say so
    abandoned = [_Get(fclient, key, _plan_body((0.001 * i, 0.002, 0.13), timeout_s=0.3, request_id=f"gone{i}"), 0.3)
                 for i in range(8)]
    assert patient.done.wait(30)
    (ok, body, t_reply), = patient.replies
    assert not ok and body["error"]["code"] == "deadline_exceeded" and body["request_id"] == "queued"
    assert "still queued, so it was not planned" in body["error"]["message"]
    assert t_reply > 0.9  # not before its deadline
    for get in abandoned:
        assert get.done.wait(30) and not any(ok for ok, _body, _t in get.replies)
    assert hog.done.wait(30)
    assert hog.replies[0][1]["error"]["code"] == "deadline_exceeded"
    # answered at its deadline, while the hog still held the worker (not when the worker freed)
    assert patient.t0 + t_reply < hog.t0 + hog.replies[0][2]
    _wait_idle(fclient)
    after = _planning(fclient)
    assert after["dropped"] - before["dropped"] == len(abandoned) + 1
    assert after["planned"] == before["planned"]  # none of them reached the planner


def test_cancel_while_planning_ends_the_goal_at_once(fclient):
    _wait_idle(fclient)
    before = _planning(fclient)
    ack = fclient.submit_goal(GOAL_B_M, options=LONG)
    _wait_planning(fclient)
    assert fclient.result(ack["id"])["status"] == "running"
    reply = check_schema(fclient.cancel(ack["id"]), "cancel_reply")
    assert reply["cancelled"] and reply["status"] == "running"
    result = check_schema(fclient.wait_result(ack["id"], timeout_s=30), "goal_result")
    assert result["status"] == "cancelled" and result["tracking_report"] is None
    _wait_idle(fclient)
    # the plan was stopped by the cancel, not at the cap (which would count a deadline_exceeded)
    after = _planning(fclient)
    assert after["cancelled"] == before["cancelled"] + 1
    assert after["deadline_exceeded"] == before["deadline_exceeded"]
    # the next goal runs at once
    done = fclient.wait_result(fclient.submit_goal(GOAL_A_M)["id"], timeout_s=20)
    assert done["status"] == "done", done["error"]


def _cancel_in_motion(client: FalconClient, goal_m, motion_s: float, goal_id: str,
                      release: bool = False) -> tuple[dict[str, Any], list[int]]:
    """Run the goal ``goal_id`` to ``goal_m`` with SLOW_MOTION (about ``motion_s`` [s] long) and
    cancel it by put a quarter into its motion, past the executor's 0.5 s hold of the start
    (by the service's own clock in the progress bodies, or by the samples done, whichever
    comes first: a loaded machine skips slots, so samples lag); its result and the samples
    done when the cancel was sent."""
    ack = client.submit_goal(goal_m, options=SLOW_MOTION, goal_id=goal_id, release=release)
    at_cancel: list[int] = []
    executing_since: list[float] = []

    def on_progress(p: dict[str, Any]) -> None:
        detail = p.get("detail", {})
        done, total = detail.get("samples_done", 0), detail.get("samples_total", 0)
        if p["phase"] != "executing" or at_cancel or done == 0:   # (from the run's first tick, not its setup)
            return
        executing_since[:1] = executing_since[:1] or [p["elapsed_s"]]
        if p["elapsed_s"] - executing_since[0] >= 0.5 + motion_s / 4 or \
                (total and done >= total * (0.5 + motion_s / 4) / (0.5 + motion_s)):
            at_cancel.append(done)
            client.session.put(client.keys().goal_cancel(ack["id"]), b"")

    return client.wait_result(ack["id"], timeout_s=30, on_progress=on_progress), at_cancel


@pytest.mark.parametrize("release", [False, True])
def test_a_goal_cancelled_while_executing_reports_what_ran(fclient, release):
    _wait_idle(fclient)
    motion_s = fclient.plan(HOME_M, GOAL_A_M, SLOW_MOTION, instance="flt0")["report"]["duration_s"]
    assert motion_s > 0.2
    # the cancel has the rest of the motion (~0.18 s) to arrive in; a loaded machine can miss
    # that, or starve the real-time run into a safety stop (the watchdog, or the workspace
    # guard when skipped slots let the arm lag): such a goal is run again (a cancel that never
    # works fails every time)
    result, at_cancel = {"status": "not run"}, []
    for attempt in range(5):
        home = fclient.wait_result(fclient.submit_goal(HOME_M)["id"], timeout_s=30)
        if home["status"] != "done":  # a loaded machine stopped the way home: go home again from there
            continue
        result, at_cancel = _cancel_in_motion(fclient, GOAL_A_M, motion_s, f"slow-cancel-{release}-{attempt}", release)
        stopped = result["status"] == "failed" and "safety_stop" in json.dumps(result["error"])
        # a starved way home can end a few mm off home, where the weak limit cannot hold the
        # grip against gravity: the goal is refused before any motion, and run again from home
        off_home = result["status"] == "failed" and "tc_max_too_small: holding still" in json.dumps(result["error"])
        assert result["status"] in ("cancelled", "done") or stopped or off_home, result["error"]
        if result["status"] == "cancelled":
            break
    assert at_cancel and result["status"] == "cancelled"
    track = result["tracking_report"]
    assert track["status"] == "cancelled" and "cancelled after" in track["reason"]
    if release:  # what ran, up to the cancel, then zero force
        assert track["brake"] is None and at_cancel[0] <= track["samples"] < track["planned_samples"]
    else:  # what ran: up to the cancel, then the safe stop (braked to rest and held) to the run's end
        assert at_cancel[0] <= track["brake"]["tick"] < track["samples"]
        assert track["brake"]["peak_feedforward"] <= 2350
    assert track["tracking"]["norm_max_mm"] >= track["tracking"]["norm_rms_mm"] > 0
    assert result["plan_report"]["duration_s"] > 0


def test_goals_keep_running_after_their_submitter_leaves(fclient, faults):
    _wait_idle(fclient)
    with client_for(faults, "flt0") as leaving:
        leaving.put_goal("orphan-1", GOAL_B_M)
        fclient.wait_known("orphan-1", timeout_s=30)  # the service has it before its submitter leaves
    result = fclient.wait_result("orphan-1", timeout_s=20)
    assert result["status"] == "done", result["error"]


def test_a_put_on_a_key_that_takes_none_is_reported(fclient):
    errors: list[dict[str, Any]] = []
    keys = fclient.keys()
    sub = fclient.session.declare_subscriber(keys.errors, lambda s: errors.append(json.loads(s.payload.to_bytes())))
    try:
        fclient.session.put(keys.state, b'{"position_m": [0, 0, 0.1]}')
        wait_until(lambda: errors, "an error publication")
    finally:
        sub.undeclare()
    body = check_schema(errors[0], "error")
    assert body["key"] == keys.state and body["error"]["code"] == "unknown_key"
    assert keys.goals_submit in body["error"]["allowed"]


def test_shutdown_answers_a_plan_in_flight(model):
    with running_service("flt1", "none", model) as service, client_for(service, "flt1") as client:
        inflight = _Get(client, client.keys().plan, _plan_body(GOAL_A_M, LONG, request_id="late"), 20.0)
        queued = _Get(client, client.keys().plan, _plan_body(GOAL_B_M, LONG, request_id="later"), 20.0)
        wait_until(lambda: service.pool.busy() == (1, 1), "one plan running and one waiting", 30.0)
        t0 = time.monotonic()
        service.close()
        assert inflight.done.wait(30) and queued.done.wait(30)
        for get, rid in ((inflight, "late"), (queued, "later")):
            (ok, body, _t), = get.replies
            assert not ok and body["error"]["code"] == "overloaded" and body["request_id"] == rid
            assert "shutting down" in body["error"]["message"]
        assert time.monotonic() - t0 < 15.0  # not after the plans (~30 s each); loose for a loaded machine
