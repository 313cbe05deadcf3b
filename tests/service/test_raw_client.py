"""A separate process that speaks only zenoh + JSON (no project imports) gets the same
answers as the project's client."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from service.testing import GOAL_A_M, HOME_M, PREFIX, check_schema

SCRIPT = Path(__file__).with_name("raw_zenoh_client.py")


def test_documented_json_is_enough(client, sim_service):
    request = {"start_m": list(HOME_M), "goal_m": list(GOAL_A_M), "request_id": "raw-1"}
    ours = client.plan(HOME_M, GOAL_A_M, request_id="raw-1", instance="sim0")
    proc = subprocess.run([sys.executable, "-I", str(SCRIPT), sim_service.settings.listen[0], PREFIX, "sim0",
                           json.dumps(request), "raw-goal"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    theirs = json.loads(proc.stdout)
    assert theirs["project_modules_imported"] == []
    assert f"{PREFIX}/alive/sim0" in theirs["alive"]
    (plan,) = theirs["plan"]
    assert plan["ok"] and plan["key"] == f"{PREFIX}/sim0/plan"
    assert plan["body"]["request_id"] == "raw-1"
    assert plan["body"]["trajectory"] == ours["trajectory"] and plan["body"]["report"] == ours["report"]
    (nan,) = theirs["plan_nan"]
    assert not nan["ok"] and check_schema(nan["body"], "error")["error"]["code"] == "non_finite_number"
    (state,) = theirs["state"]
    assert state["ok"] and check_schema(state["body"], "state")["instance"] == "sim0"
    (schema,) = theirs["schema"]
    assert schema["body"] == client.schema("goal_request")
    goal = check_schema(theirs["goal"], "goal_result")
    assert goal["id"] == "raw-goal" and goal["status"] == "done", goal["error"]
    assert goal == client.result("raw-goal")
