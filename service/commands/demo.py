"""``falcon-plan demo``: the service end to end in one process.

Starts the Zenoh service in-process (peer mode, loopback only, multicast scouting off,
simulated device in real time), opens a separate client session, sends one goal (plan and
execute), follows its progress, prints a summary of the plan and of the tracking (``--json``:
the whole goal result), and closes both sessions and the device. ``--plot FILE.png`` draws
the executed run against its plan, and the plan next to it (FILE-plan.png).

``--moving-target SECONDS``: instead, the goal moves: a target going round a 20 mm circle
about the device's position (once every 2 s) is sent as a new goal every 50 ms with
``"preempt": true`` (each spliced into the running motion by the service); the last goal's
result holds the whole run. ``--plot`` then draws the target, the spliced plans and the
executed path (:func:`falcon_plan.moving_target.plot_moving_target`); the summary says how far
behind the target the device stayed.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path
from collections.abc import Callable, Iterator
from typing import Any, TextIO

from falcon_plan.commands import common
from service.commands.request import add_options_argument, goal_summary, plot_goal

DEMO_GOAL_M = (0.02, 0.01, 0.13)
"""Default goal [m]: about 25 mm from the simulated device's home (0, 0, 0.145) m."""


def register(subparsers: Any) -> None:
    """Add the ``demo`` subcommand to ``subparsers`` (the ``falcon-plan`` command line's)."""
    parser = subparsers.add_parser(
        "demo", help="start the service in-process and send it one goal end to end (plan + execute)",
        description=__doc__.splitlines()[0])
    common.add_point_option(parser, "--to", "--goal", dest="goal", default=DEMO_GOAL_M, help="goal point [m]")
    add_options_argument(parser)
    parser.add_argument("--port", type=int, default=0, help="loopback port to listen on (default: a free one)")
    parser.add_argument("--timeout", type=common.positive_float, default=120.0, help="longest wait for the goal [s]")
    parser.add_argument("--plot", type=common.output_file_as(".png"), default=None, metavar="FILE.png",
                        help="write a plot of the executed run (measured against the plan) and, next to it "
                             "as FILE-plan.png, the plan's")
    parser.add_argument("--moving-target", type=common.positive_float, default=None, metavar="SECONDS",
                        help="let the goal move for SECONDS: a circle sampled at 20 Hz, each sample a preempting goal "
                             "spliced into the running motion")
    common.add_json_option(parser)
    parser.set_defaults(func=_run)


def run_demo(goal_m: tuple[float, float, float] = DEMO_GOAL_M, *, options: dict[str, Any] | None = None,
             port: int = 0, timeout_s: float = 120.0, out: TextIO | None = None, as_json: bool = False,
             plot: Path | None = None) -> int:
    """Run the demo: a service on loopback port ``port`` (0: a free one) and one goal to
    ``goal_m`` [m, base frame] planned with ``options`` (PlanOptions fields, None: the
    defaults), waiting at most ``timeout_s`` [s] for it; printing to ``out`` (default: the
    current sys.stdout). Returns 0 when the goal was planned and executed (status done). ``as_json`` prints the goal result as
    JSON instead of the summary; ``plot`` draws the executed run to that PNG and the plan next to it
    (``request goal --plot``)."""
    out = out or sys.stdout
    from falcon_plan.commands.common import mm

    say = sys.stderr.write if as_json else out.write
    with _demo_session(port, timeout_s, say) as client:
        state = client.state()
        say(f"client connected; device at {mm(state['position_m'])}, homed {'yes' if all(state['homed']) else 'no'}\n")
        ack = client.submit_goal(goal_m, options=options)
        say(f"goal {ack['id']} to {mm(goal_m)} accepted (queue position {ack['position']}); "
            f"result on {ack['keys']['result']}\n")
        phases: set[str] = set()

        def on_progress(body: dict[str, Any]) -> None:
            if body["phase"] not in phases:
                phases.add(body["phase"])
                say(f"  {body['phase']} ...\n")

        result = client.wait_result(ack["id"], timeout_s=timeout_s, on_progress=on_progress)
        if plot is not None and result["status"] == "done":  # the service answers from its plan cache
            plot_goal(result, client.plan(result["start_m"], result["goal_m"], options), plot)
    if as_json:
        json.dump(result, out, indent=2)
        out.write("\n")
    else:
        out.write(goal_summary(result) + "\n")
    say("sessions closed\n")
    return 0 if result["status"] == "done" else 1


@contextlib.contextmanager
def _demo_session(port: int, timeout_s: float, say: Callable[[str], Any]) -> Iterator[Any]:
    """The demo's service (peer mode, the simulated device, one planning worker) on loopback
    ``port`` (0: a free one) and a client session connected to it (a FalconClient waiting at
    most ``timeout_s`` [s]); ``say`` reports where it listens. Both close on leaving."""
    from service.client import FalconClient, wait_for_instance
    from service.config import SessionSettings, free_loopback_port
    from service.main import build_service, serve_arguments

    endpoint = f"tcp/127.0.0.1:{port or free_loopback_port()}"
    service = build_service(serve_arguments(["--device", "sim", "--listen", endpoint, "--planning-workers", "1"]))
    say(f"service {service.keys.base}: peer mode, listening on {endpoint}, simulated device\n")
    with service, FalconClient(SessionSettings.client([endpoint]), timeout_s=timeout_s) as client:
        wait_for_instance(client, service.keys.instance)
        yield client


MOVING_UPDATE_HZ = 20.0
"""How often the moving target's goal is sent [Hz]."""
MOVING_LEAD_S = 0.1
"""Each goal is where the target will be this much later [s] (about the splice's latency budget,
30-40 ms, and a short plan, ~50 ms: the goal the device can reach when the target is there).
With 0.15 s, once nearly every goal was spliced in, the device ran ~4 mm ahead of the target
(4.8 mm on average from it); with 0.1 s 2.6 mm, with 0.08 s 3.2 mm (bench_moving_demo.py, the
median of 3 runs each)."""


def run_moving_demo(seconds: float, *, port: int = 0, timeout_s: float = 120.0, out: TextIO | None = None,
                    as_json: bool = False, plot: Path | None = None, goal_options: dict[str, Any] | None = None) -> int:
    """The demo with a moving goal (module docstring) for ``seconds`` [s] on a service on
    loopback ``port``; ``timeout_s``, ``out``, ``as_json`` and ``plot`` as for :func:`run_demo`;
    ``goal_options``: the planner options of the preempting goals (default
    :data:`~falcon_plan.moving_target.FOLLOW_OPTIONS`). Returns 0 when the last goal finished
    done and every splice was continuous."""
    import threading
    import time
    from types import SimpleNamespace

    import numpy as np

    from falcon_plan.falconlog import motion_start_s
    from falcon_plan.model.kinematics import counts_to_position
    from falcon_plan.moving_target import FOLLOW_OPTIONS, MovingTargetRun, circle_target, plot_moving_target
    from service.device import run_log

    out = out or sys.stdout
    say = sys.stderr.write if as_json else out.write
    options = FOLLOW_OPTIONS if goal_options is None else goal_options
    with _demo_session(port, timeout_s, say) as client:
        centre = np.asarray(client.state()["position_m"], dtype=float)
        target = circle_target(centre, radius_m=0.02, period_s=2.0)
        started: list[float] = []

        def on_progress(body: dict[str, Any]) -> None:
            # the target moves once the run's trajectory does (after the pre-roll hold), from the
            # sample the progress says it starts at
            detail = body.get("detail", {})
            if body["phase"] == "executing" and not started and "motion_start_sample" in detail and \
                    detail["samples_done"] >= detail["motion_start_sample"]:
                ahead_s = (detail["samples_done"] - detail["motion_start_sample"]) / detail["rate_hz"]
                started.append(time.monotonic() - ahead_s)

        first = client.submit_goal(list(target(0.0)), goal_id="moving-0")["id"]
        follow = SimpleNamespace(ids=[first], samples=[])
        waiter = threading.Thread(target=lambda: client.wait_result(first, timeout_s=timeout_s, on_progress=on_progress))
        waiter.start()
        deadline = time.monotonic() + timeout_s
        while not started and time.monotonic() < deadline:
            time.sleep(0.005)
        say(f"target moving for {seconds:g} s; a preempting goal every {1e3 / MOVING_UPDATE_HZ:.0f} ms\n")
        t0 = started[0] if started else time.monotonic()
        k = 1
        while (t := time.monotonic() - t0) <= seconds:
            follow.samples.append((t, target(t)))
            follow.ids.append(client.submit_goal(list(target(t + MOVING_LEAD_S)), goal_id=f"moving-{k}", preempt=True,
                                              options=options)["id"])
            k += 1
            time.sleep(max(0.0, t0 + k / MOVING_UPDATE_HZ - time.monotonic() - 1.0 / MOVING_UPDATE_HZ))
        waiter.join(timeout_s)
        # the last goal first: once it ended, every result is final with its run (a goal replaced
        # while its plan was under way may still be spliced in and run until the next splice)
        final = client.wait_result(follow.ids[-1], timeout_s=timeout_s)
        results = [client.wait_result(gid, timeout_s=timeout_s) for gid in follow.ids[:-1]] + [final]
    # the goal each execution served last holds its run and every splice of it; the longest
    # (most splices) is the one drawn and measured against the target
    executions = [r for r in results if r.get("run")]
    taken = {id(r): [s for s in r.get("splices") or [] if s.get("taken") and "goal" in s] for r in executions}
    last = max(executions or results, key=lambda r: len(taken.get(id(r), [])))
    statuses = {s: sum(r["status"] == s for r in results) for s in {r["status"] for r in results}}
    every = [s for r in executions for s in taken[id(r)]]
    splices = taken.get(id(last), [])
    planned = [s["latency_ms"] for s in every if not s.get("reused")]   # (a late plan offered again is not planned again)
    summary = {"goals": len(results), "statuses": statuses, "executions": len(executions),
               "splices_taken": len(every), "splices_reused": len(every) - len(planned),
               "largest_position_jump_counts": max((s["position_jump_counts"] for s in every), default=0.0),
               "largest_velocity_jump_counts_s": max((s["velocity_jump_counts_s"] for s in every), default=0.0),
               "replan_latency_p50_ms": float(np.percentile(planned, 50)) if planned else None,
               "replan_latency_p99_ms": float(np.percentile(planned, 99)) if planned else None,
               "methods": {m: sum(s.get("method") == m for s in every) for m in {s.get("method") for s in every}}}
    run = last.get("run")
    if run:
        log = run_log(run)
        rate_hz = float(log.rate_hz)   # the executor always logs its rate
        motion_start = int(round(motion_start_s(log.meta or {}) * rate_hz))
        t_run = log.t_s - motion_start / rate_hz       # from the motion's start, as the target's clock
        measured = counts_to_position(log.enc.astype(float))
        planned = counts_to_position(log.ref)
        bounds = [0.0] + [(s["tick"] - motion_start) / rate_hz for s in splices] + [np.inf]
        moving = MovingTargetRun(SimpleNamespace(splices=splices), rate_hz, motion_start, target,
                                 np.array([s[0] for s in follow.samples]), np.array([s[1] for s in follow.samples]),
                                 [(a, planned[(t_run >= a) & (t_run < b)]) for a, b in zip(bounds[:-1], bounds[1:])],
                                 t_run, measured, planned)
        summary["lag"] = moving.lag()
        if plot is not None:
            say(f"plot: {plot_moving_target(moving, plot)}\n")
    if as_json:
        json.dump({"summary": summary, "last_result": last}, out, indent=2)
        out.write("\n")
    else:
        lag = summary.get("lag", {})
        out.write(f"{summary['goals']} goals ({', '.join(f'{n} {s}' for s, n in sorted(statuses.items()))}); "
                  f"{summary['splices_taken']} plans spliced in, largest jump {summary['largest_position_jump_counts']:.2g} "
                  f"counts, {summary['largest_velocity_jump_counts_s']:.2g} counts/s\n")
        if lag:
            out.write(f"behind the target: mean {lag['distance_mean_mm']:.1f} mm, max {lag['distance_max_mm']:.1f} mm, "
                      f"about {1e3 * lag['time_lag_s']:.0f} ms (replan latency p50 "
                      f"{summary['replan_latency_p50_ms'] or float('nan'):.0f} ms)\n")
    say("sessions closed\n")
    ok = results[-1]["status"] == "done" and summary["largest_position_jump_counts"] < 1e-6
    return 0 if ok else 1


def _run(args: argparse.Namespace) -> int:
    if args.moving_target is not None:
        return run_moving_demo(args.moving_target, port=args.port, timeout_s=args.timeout, as_json=args.json,
                               plot=args.plot)
    return run_demo(tuple(args.goal), options=args.options, port=args.port, timeout_s=args.timeout,
                    as_json=args.json, plot=args.plot)
