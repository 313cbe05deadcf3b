"""Preemption over a real Zenoh session on loopback (issue 24 item 4): a goal with ``preempt``
replaces the running goal in motion, spliced in continuous in position and velocity; the
running goal ends ``preempted``; progress of a running goal comes at >= 50 Hz with its
tracking error, command margin and which plan runs; the results list every splice."""
from __future__ import annotations

import threading
import time

import numpy as np

from falcon_plan.model.kinematics import counts_to_position
from service.testing import HOME_M, check_schema


PREEMPT_ATTEMPTS = 3
"""Scenarios tried until one preemption came in time to be spliced (see the test)."""


def _preempt_while_moving(client, attempt: int) -> tuple[dict, dict, list[dict]]:
    """From home, a long first motion (via points, a lower command bound: 0.5 s), and once it
    moves (past its pre-roll: 0.5 s, 400 samples) a preempting goal. Returns the first goal's
    result, the second's and the first's progress bodies (each with its arrival time)."""
    first_goal, via = (0.03, -0.02, 0.135), [(0.03, 0.025, 0.125), (-0.03, 0.02, 0.135)]
    second_goal = np.array(HOME_M) + [0.01, -0.01, 0.0]
    one_id, two_id = f"pre-{attempt}-1", f"pre-{attempt}-2"
    seen: list[dict] = []
    moving = threading.Event()

    def on_progress(body: dict) -> None:
        seen.append({**body, "received": time.monotonic()})
        if body["phase"] == "executing" and body.get("detail", {}).get("samples_done", 0) > 0:
            moving.set()

    # from a known point (the shared device may be anywhere after other tests); home again after
    assert client.wait_result(client.submit_goal(list(HOME_M))["id"], timeout_s=60)["status"] == "done"
    first = client.submit_goal(list(first_goal), goal_id=one_id, via_m=via, options={"tc_max": 1200})
    assert first["id"] == one_id
    results: dict[str, dict] = {}
    waiter = threading.Thread(target=lambda: results.update(one=client.wait_result(one_id, timeout_s=60,
                                                                                        on_progress=on_progress)))
    waiter.start()
    assert moving.wait(30), "the first goal never moved"
    deadline = time.monotonic() + 30
    while not any(b.get("detail", {}).get("samples_done", 0) > 400 for b in seen):
        assert time.monotonic() < deadline and waiter.is_alive(), (results.get("one", {}).get("status"), [b.get("detail") for b in seen[-3:]])
        time.sleep(0.002)
    ack = client.submit_goal(list(second_goal), goal_id=two_id, preempt=True)
    assert ack["status"] == "pending" and ack["position"] == 0
    second = client.wait_result(two_id, timeout_s=60)
    waiter.join(60)
    client.wait_result(client.submit_goal(list(HOME_M))["id"], timeout_s=60)
    return results["one"], second, seen


def test_a_preempting_goal_is_spliced_into_the_running_motion(client):
    """The scenario is tried until the preemption came in time to be spliced: its replan's
    budget (measured, 0.25-0.45 s here) leaves the first motion about 0.1 s to spare, and on a
    loaded machine a replan can come after the motion's end; the service then runs the new goal
    after the first, which ends "done" (the behaviour documented for a preemption that cannot be
    spliced), and the next try is made warm."""
    second_goal = np.array(HOME_M) + [0.01, -0.01, 0.0]
    for attempt in range(PREEMPT_ATTEMPTS):
        one, second, seen = _preempt_while_moving(client, attempt)
        check_schema(one, "goal_result")
        check_schema(second, "goal_result")
        if one["status"] == "done" and second["status"] == "done" and not second["splices"]:
            continue                      # too late to splice: run after it, as documented
        break
    one_id, two_id = f"pre-{attempt}-1", f"pre-{attempt}-2"
    assert one["status"] == "preempted" and one["preempted_by"] == two_id, (one["status"], one["error"], second["splices"])
    assert second["status"] == "done", second.get("error")
    # the splice: taken, continuous in position and velocity, listed in both results
    (splice,) = [s for s in second["splices"] if s.get("goal") == two_id]
    assert splice["taken"] and splice["position_jump_counts"] < 1e-6 and splice["velocity_jump_counts_s"] < 1.0
    assert any(s.get("goal") == two_id and s["taken"] for s in one["splices"])
    # ready in time for its tick (what decides a splice; its latency may pass its budget by
    # less than the tick's rounding and lead: 151 ms against 150 was seen, in time)
    assert splice["arrived_tick"] <= splice["tick"] and splice["latency_ms"] > 0
    # the device went to the second goal, not the first, without stopping in between: the
    # second goal's run is the same execution (its log has the first goal's start and the new end)
    run = second["run"]
    end = counts_to_position(np.asarray(run["ref"][-1], dtype=float))
    np.testing.assert_allclose(end, second_goal, atol=1e-4)
    # feedback: at >= 50 Hz while executing, with the run's feedback fields
    executing = [b for b in seen if b["phase"] == "executing" and "tracking_error_mm" in b.get("detail", {})]
    assert len(executing) > 10
    for body in executing[:3]:
        check_schema({k: v for k, v in body.items() if k != "received"}, "goal_progress")
        detail = body["detail"]
        assert detail["plan"]["goal_id"] == one_id and detail["command_margin"] > 0 and detail["tracking_error_mm"] >= 0
        assert detail["rate_hz"] > 0 and 0 < detail["motion_start_sample"] < detail["samples_total"]
    stamps = np.array([b["received"] for b in executing])
    assert np.median(np.diff(stamps)) <= 1 / 50 + 0.004, np.median(np.diff(stamps))


def test_the_moving_target_demo_splices_goal_after_goal(tmp_path):
    """``demo --moving-target``: a goal every 50 ms with preempt, over its own service and a
    real Zenoh session; the plans are spliced in one after the other without a jump, in one
    run that never ends between goals (on a busy machine too: fewer splices then, as each
    replan takes longer, but every goal is spliced in or replaced by a newer one)."""
    import io
    import json

    from service.commands.demo import run_moving_demo

    out = io.StringIO()
    code = run_moving_demo(2.5, timeout_s=60, out=out, as_json=True, plot=tmp_path / "moving.png")
    body = json.loads(out.getvalue())
    summary = body["summary"]
    assert code == 0, summary
    # one execution served every goal: each one but the last was spliced in or replaced, the last ran to its end
    assert summary["goals"] >= 40 and summary["executions"] == 1, summary
    assert summary["statuses"] == {"preempted": summary["goals"] - 1, "done": 1}, summary
    splices = [s for s in body["last_result"]["splices"] if s.get("taken")]
    assert len(splices) == summary["splices_taken"] >= 3, summary
    for splice in splices:  # continuous in position and velocity, newer goals one after the other, each in time
        assert splice["position_jump_counts"] < 1e-6 and splice["velocity_jump_counts_s"] < 1.0, splice
    order = [int(s["goal"].split("-")[1]) for s in splices]
    assert order == sorted(set(order)) and order[-1] == summary["goals"] - 1, order
    assert (tmp_path / "moving.png").stat().st_size > 20_000
