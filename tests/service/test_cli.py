"""The commands as a user runs them: ``falcon-plan serve`` stops cleanly on SIGINT,
``falcon-plan request`` talks to it, ``falcon-plan demo`` runs end to end and exits."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from service.client import FalconClient, wait_for_instance
from service.config import SessionSettings

from service.testing import endpoint

CLI = [sys.executable, "-m", "falcon_plan.cli"]
ENV = {**os.environ, "FALCON_PLAN_LOG": "WARNING"}


@pytest.mark.slow
def test_serve_answers_request_and_exits_cleanly_on_sigint():
    ep = endpoint()
    prefix = "falconcli"
    server = subprocess.Popen([*CLI, "serve", "--device", "sim", "--instance", "cli0", "--prefix", prefix,
                               "--listen", ep], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        with FalconClient(SessionSettings.client([ep]), prefix=prefix, instance="cli0") as client:
            wait_for_instance(client, "cli0", timeout_s=40)
            out = subprocess.run([*CLI, "request", "state", "--instance", "cli0", "--prefix", prefix, "--connect", ep,
                                  "--json"], capture_output=True, text=True, timeout=40, env=ENV)
            assert out.returncode == 0, out.stderr
            state = json.loads(out.stdout)
            assert state["instance"] == "cli0" and state["device"] == "sim"
            bad = subprocess.run([*CLI, "request", "result", "nope", "--instance", "cli0", "--prefix", prefix,
                                  "--connect", ep, "--json"], capture_output=True, text=True, timeout=40, env=ENV)
            assert bad.returncode == 2 and "unknown_goal" in bad.stderr
            assert json.loads(bad.stdout)["error"]["code"] == "unknown_goal"   # --json: the error body too
            # a plan through a via point with a payload, and a via point outside the workspace
            move = ["--from", "0,0,0.14", "--to", "0.02,0.01,0.13", "--instance", "cli0", "--prefix", prefix,
                    "--connect", ep]
            via = subprocess.run([*CLI, "request", "plan", *move, "--via", "0.01,0.012,0.138", "--payload-kg", "0.1",
                                  "--json"], capture_output=True, text=True, timeout=60, env=ENV)
            assert via.returncode == 0, via.stderr
            problem = json.loads(via.stdout)["report"]["problem"]
            assert problem["via_m"] == [[0.01, 0.012, 0.138]] and problem["payload_kg"] == 0.1
            far = subprocess.run([*CLI, "request", "plan", *move, "--via", "0,0,0.3"], capture_output=True, text=True,
                                 timeout=40, env=ENV)
            assert far.returncode == 2 and len(far.stderr.strip().splitlines()) == 1  # bad input, as for `plan`
            assert "outside_workspace" in far.stderr and "via_m[0]" in far.stderr
            # a second instance with the same id refuses to start, in one line
            twin = subprocess.run([*CLI, "serve", "--device", "none", "--instance", "cli0", "--prefix", prefix,
                                   "--listen", endpoint(), "--connect", ep], capture_output=True, text=True,
                                  timeout=60, env=ENV)
            assert twin.returncode == 2 and "ready" not in twin.stdout
            assert twin.stderr.strip().splitlines() == [
                f"falcon-plan serve: error: instance id 'cli0' is already running under prefix '{prefix}' (its "
                f"liveliness token {prefix}/alive/cli0 is up): give this one another --instance, or stop the other "
                "first"]
            server.send_signal(signal.SIGINT)
            stdout, stderr = server.communicate(timeout=20)  # it stops, not waiting for anything
            assert server.returncode == 0, stderr
            assert "ready" in stdout and "stopped" in stdout
            assert client.instances(timeout_s=1.0) == []
    finally:
        if server.poll() is None:
            server.kill()
            server.communicate()


@pytest.mark.slow
def test_demo_runs_end_to_end_and_exits():
    proc = subprocess.run([*CLI, "demo"], capture_output=True, text=True, timeout=90, env=ENV)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = proc.stdout
    assert ": done, from (" in out and "sessions closed" in out
    assert "plan: casadi optimal, motion" in out and "execution: completed" in out
    samples = int(out.split("execution: completed, ")[1].split(" samples")[0])
    assert samples > 10 and len(out.splitlines()) < 15  # a compact summary, not the raw JSON


def test_a_payload_plans_plot_uses_the_payload(model, tmp_path) -> None:
    """``request plan --plot`` of a plan with a payload: the feed-forward drawn is the planned
    one (with the payload: 100 % of the bound, as the report says; without it, 85 %), and the
    title says the payload."""
    import json

    import matplotlib.axes
    import matplotlib.figure

    from falcon_plan.planning.api import plan
    from falcon_plan.planning.problem import PlanOptions
    from service.commands.request import plot_reply

    result = plan((0.0, 0.0, 0.13), (0.03, -0.02, 0.14), PlanOptions.fast(), model, payload_kg=0.15)
    reply = {"trajectory": json.loads(result.trajectory.to_json()), "report": result.report.to_dict()}
    titles: list[str] = []
    draw_title = matplotlib.axes.Axes.set_title

    def keep(ax, text, *args, **kwargs):
        titles.append(text)
        return draw_title(ax, text, *args, **kwargs)

    suptitle = matplotlib.figure.Figure.suptitle

    def keep_sup(fig, text, *args, **kwargs):
        titles.append(text)
        return suptitle(fig, text, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(matplotlib.axes.Axes, "set_title", keep)
        patch.setattr(matplotlib.figure.Figure, "suptitle", keep_sup)
        plot_reply(reply, tmp_path / "plan.png")
    peak = next(t for t in titles if t.startswith("Commands: peak"))
    percent = float(peak.split("= ")[1].split(" %")[0])
    assert percent == pytest.approx(100 * result.report.worst_command_ratio, abs=0.2), peak
    assert any("payload 0.15 kg" in t for t in titles), titles
    assert (tmp_path / "plan.png").stat().st_size > 10_000
