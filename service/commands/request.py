"""``falcon-plan request``: a small client of the Zenoh service using only the documented keys.

Actions: ``plan`` (plan --from -> --to, through any --via points, with an optional
--payload-kg, and print a summary; without --from the device's position from the instance's
state), ``goal`` (submit a goal, follow its progress, print
the plan and the tracking summary), ``state``, ``cancel ID``, ``result ID``, ``info``,
``instances``. Points are X,Y,Z in metres; the summaries give positions in mm; ``--json``
prints the whole reply body.
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from falcon_plan.commands import common
from falcon_plan.commands.common import mm
from falcon_plan.errors import InvalidParameterError

if TYPE_CHECKING:
    from service.client import FalconClient

ACTIONS = ("plan", "goal", "state", "cancel", "result", "info", "instances")


def register(subparsers: Any) -> None:
    """Add the ``request`` subcommand to ``subparsers`` (the ``falcon-plan`` command line's)."""
    from service.config import add_session_arguments
    from service.keys import DEFAULT_PREFIX

    parser = subparsers.add_parser(
        "request", help="send one request to a running service (plan, goal, state, cancel, ...)",
        description=__doc__)
    parser.add_argument("action", choices=ACTIONS, help="what to ask")
    parser.add_argument("goal_id", nargs="?", help="goal id (cancel, result; optional for goal)")
    common.add_point_option(parser, "--from", "--start", dest="start",
                            help="start point [m] (default: the device's position, from the instance's state)")
    common.add_point_option(parser, "--to", "--goal", dest="goal", help="goal point [m] (plan, goal)")
    common.add_point_option(parser, "--via", dest="via", repeat=True,
                            help="a via point [m] (plan, goal; repeatable, passed through in order)")
    parser.add_argument("--payload-kg", type=float, default=None,
                        help="payload carried at the end effector [kg] (plan, goal; default none)")
    add_options_argument(parser)
    parser.add_argument("--instance", default=None,
                        help="instance for goal/state/cancel/result/info (default falcon0); for plan, "
                             "without it the shared <prefix>/plan key is used (any one instance answers)")
    parser.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix of the service")
    parser.add_argument("--timeout", type=common.positive_float, default=30.0, help="reply timeout [s]")
    parser.add_argument("--no-wait", action="store_true", help="goal: return after the acknowledgement")
    parser.add_argument("--plot", type=common.output_file_as(".png"), default=None, metavar="FILE.png",
                        help="plan: write a plot of the planned motion; goal: a plot of the executed run "
                             "(measured against the plan, tracking error, commands) and, next to it as "
                             "FILE-plan.png, the plan's")
    common.add_json_option(parser)
    add_session_arguments(parser, server=False)
    parser.set_defaults(func=_run_json_errors)


def add_options_argument(parser: argparse.ArgumentParser) -> None:
    """Add ``--options JSON`` (the plan options of a request, a JSON object) to ``parser``
    (``request`` and ``demo``)."""
    parser.add_argument("--options", type=_json_object, default=None, metavar="JSON",
                        help='PlanOptions as a JSON object, e.g. \'{"tc_max": 2000}\'')


def _json_object(text: str) -> dict[str, Any]:
    try:
        return common.load_json_object(text, "--options")
    except InvalidParameterError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


# --- compact summaries (shared with ``falcon-plan demo``) ----------------------------------------

def plan_summary(report: dict[str, Any]) -> str:
    """One line of a plan report (PlanReport.to_dict())."""
    if not report:
        return "plan: none"
    text = (f"plan: {report.get('method')} {report.get('status')}, motion {1e3 * report.get('duration_s', 0):.1f} ms, "
            f"planned in {1e3 * report.get('total_time_s', 0):.0f} ms")
    ratio = report.get("worst_command_ratio")
    if ratio is not None:
        text += f", peak |Tc| {100 * ratio:.0f} % of its bound ({report.get('command_bound', '?')})"
    return text


def tracking_summary(track: dict[str, Any]) -> str:
    """One line of the tracking report ``track`` (ExecutionReport.to_dict())."""
    if not track:
        return "execution: none"
    text = (f"execution: {track.get('status')}, {track.get('samples')} samples at {track.get('rate_hz', 0):g} Hz, "
            f"missed deadlines {track.get('missed_deadlines')}")
    tr = track.get("tracking")
    if tr:
        text += (f"; error rms {tr['norm_rms_mm']:.2f} mm, max {tr['norm_max_mm']:.2f} mm, "
                 f"final {tr['final_mm']:.2f} mm")
    return text


def goal_summary(result: dict[str, Any]) -> str:
    """A few lines for the goal_result body ``result``."""
    lines = [f"goal {result.get('id')} on {result.get('instance')}: {result.get('status')}, from "
             f"{mm(result.get('start_m'))} to {mm(result.get('goal_m'))}"]
    if result.get("plan_report"):
        lines.append("  " + plan_summary(result["plan_report"]))
    if result.get("tracking_report"):
        lines.append("  " + tracking_summary(result["tracking_report"]))
    error = result.get("error")
    if error:
        lines.append(f"  error: {error.get('code', '')}: {error.get('message', error)}" if isinstance(error, dict)
                     else f"  error: {error}")
    return "\n".join(lines)


def state_summary(state: dict[str, Any]) -> str:
    """One line for a state body."""
    homed = state.get("homed") or []
    return (f"{state.get('instance')}: {state.get('device')} device at {mm(state.get('position_m'))}, "
            f"encoders {state.get('encoders')}, homed {'yes' if homed and all(homed) else homed}, "
            f"executing {state.get('executing') or 'nothing'}, {len(state.get('queue') or [])} queued")


def _info_summary(info: dict[str, Any]) -> str:
    """The info body, one ``key: value`` line each (nested values as compact JSON)."""
    return "\n".join(f"{k}: {v if isinstance(v, (str, int, float, bool)) or v is None else json.dumps(v)}"
                     for k, v in info.items() if k != "schema_version")


# --- the command ---------------------------------------------------------------------------

def _need(args: argparse.Namespace, *names: str) -> None:
    flags = {"goal": "--to X,Y,Z", "goal_id": "a goal id"}
    missing = [flags.get(n, n) for n in names if getattr(args, n) is None]
    if missing:
        raise InvalidParameterError(f"request {args.action} needs {', '.join(missing)}")


def _device_position(client: FalconClient, instance: str | None) -> list[float]:
    """Where the instance's device is [m], from its state (the start of a plan without --from)."""
    position = client.state(instance).get("position_m")
    if position is None:
        raise InvalidParameterError("the instance has not read its device's position yet: give --from X,Y,Z")
    print(f"from the device's position {mm(position)}", file=sys.stderr)
    return position


def plot_reply(reply: dict[str, Any], path: Any) -> None:
    """Draw the plan of a plan reply (its trajectory and command limit) to ``path``, the
    feed-forward from the model with the problem's payload (without it, a 0.15 kg plan's
    commands were drawn at 85 % of the bound the report said it reached)."""
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import get_params
    from falcon_plan.planning.problem import PlanProblem
    from falcon_plan.planning.transcription import payload_model
    from falcon_plan.plots import plot_plan
    from falcon_plan.trajectory import Trajectory

    trajectory = Trajectory.from_dict(reply["trajectory"])
    report = reply["report"]
    model = FalconModel(get_params(trajectory.params_name))
    if report.get("problem"):
        model = payload_model(model, PlanProblem.from_dict(report["problem"]))
    plot_plan(trajectory, path, model=model, tc_max=report.get("tc_max"))
    print(f"plot of the plan: {path}", file=sys.stderr)


def plot_goal(result: dict[str, Any], plan_reply: dict[str, Any], path: Any) -> None:
    """Draw a finished goal: its executed run (the goal result's ``run``: measured against the
    plan in counts and mm, commands against the limit) to ``path``, and the plan of
    ``plan_reply`` next to it (``path`` with ``-plan`` before the suffix)."""
    from pathlib import Path

    from falcon_plan.plots import plot_run
    from service.device import run_log

    path = Path(path)
    if result.get("run"):
        plot_run(run_log(result["run"]), path, title=f"Goal {result.get('id')} on {result.get('instance')}: "
                 f"the executed run against its plan, from {mm(result.get('start_m'))} to {mm(result.get('goal_m'))}")
        print(f"plot of the run: {path}", file=sys.stderr)
        path = path.with_name(f"{path.stem}-plan{path.suffix}")
    plot_reply(plan_reply, path)


def _run_json_errors(args: argparse.Namespace) -> int:
    """:func:`_run`; with ``--json`` a service's error reply is also printed as JSON on stdout
    (its body: code, message, field, allowed), beside the one line on stderr."""
    from service.client import ServiceError

    try:
        return _run(args)
    except ServiceError as exc:
        if args.json:
            common.print_json(exc.body)
        raise


def _run(args: argparse.Namespace) -> int:
    from service.client import FalconClient
    from service.config import settings_from_args
    from service.keys import DEFAULT_INSTANCE

    def show(body: Any, summary: str) -> None:
        if args.json:
            common.print_json(body)
        else:
            print(summary)

    needs = {"plan": ("goal",), "goal": ("goal",), "cancel": ("goal_id",), "result": ("goal_id",)}
    _need(args, *needs.get(args.action, ()))  # before any session is opened
    with FalconClient(settings_from_args(args, server=False), prefix=args.prefix,
                      instance=args.instance or DEFAULT_INSTANCE, timeout_s=args.timeout) as client:
        if args.action == "instances":
            names = client.instances()
            show(names, "\n".join(names) if names else "no instance answered")
        elif args.action == "info":
            info = client.info()
            show(info, _info_summary(info))
        elif args.action == "state":
            state = client.state()
            show(state, state_summary(state))
        elif args.action in ("cancel", "result"):
            if args.action == "cancel":
                body = client.cancel(args.goal_id)
                show(body, " ".join(f"{k}: {v}" for k, v in body.items() if k != "schema_version"))
            else:
                body = client.result(args.goal_id)
                show(body, goal_summary(body))
        elif args.action == "plan":
            start = args.start if args.start is not None else _device_position(client, args.instance)
            body = client.plan(start, args.goal, args.options, via_m=args.via, payload_kg=args.payload_kg,
                               instance=args.instance)
            timing = body.get("timing", {})
            show(body, f"{body['instance']}: {plan_summary(body['report'])}\n"
                       f"  from {mm(start)} to {mm(args.goal)}, {len(body['trajectory']['t_s'])} samples; "
                       f"service {1e3 * timing.get('service_s', 0):.0f} ms"
                       f"{' (cached)' if timing.get('cached') else ''}")
            if args.plot is not None:
                plot_reply(body, args.plot)
        else:  # goal
            ack = client.submit_goal(args.goal, start_m=args.start, options=args.options, goal_id=args.goal_id,
                                     via_m=args.via, payload_kg=args.payload_kg)
            print(f"goal {ack['id']} accepted on {ack['instance']} at queue position {ack['position']}",
                  file=sys.stderr)
            if args.no_wait:
                show(ack, ack["id"])
                return 0
            phases: set[str] = set()

            def on_progress(p: dict[str, Any]) -> None:
                if p["phase"] not in phases or p["fraction"] >= 1.0:
                    phases.add(p["phase"])
                    print(f"  {p['phase']}: {100 * p['fraction']:.0f} %", file=sys.stderr)

            result = client.wait_result(ack["id"], timeout_s=args.timeout, on_progress=on_progress)
            show(result, goal_summary(result))
            if args.plot is not None and result["status"] == "done":  # the service answers from its plan cache
                plot_goal(result, client.plan(result["start_m"], result["goal_m"], args.options, via_m=args.via,
                                              payload_kg=args.payload_kg, instance=args.instance), args.plot)
            return 0 if result["status"] == "done" else 1
    return 0
