"""``falcon-plan experiment design|run|synth``: excitation trajectories for identification,
recording them on a device, and synthetic falcon logs from the simulated plant.

``run --device sim|emulated|usb --kind KIND --out LOG`` homes the device if needed, moves it
from where it is to the excitation's start with a planned approach move, runs the excitation
with the executor and writes the falcon log (pre-roll, approach and excitation; its metadata
describes the controller exactly, so ``discrepancy`` replays it; ``--out LOG.mcap`` records an
MCAP file instead, ``--mcap FILE`` one beside the log, ``--live`` shows the run in Foxglove).
``--model FILE`` runs with a
model file's feed-forward; ``--effects`` gives the simulated device hidden effects."""
from __future__ import annotations

import argparse
from pathlib import Path

from falcon_plan.commands import common
from falcon_plan.errors import InvalidParameterError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``experiment`` subcommand (``design``, ``synth``, ``run``) to ``subparsers`` (the
    CLI's argparse subparsers)."""
    from falcon_plan.discrepancy.excitation import KINDS

    p = subparsers.add_parser("experiment", help="identification experiments (design, run, synth)",
                              description=__doc__)
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    d = sub.add_parser("design", help="write an excitation trajectory (JSON) for the executor")
    d.add_argument("--kind", choices=KINDS, default="mixed", help="excitation design")
    d.add_argument("--duration", type=common.positive_float, default=8.0,
                   help="excitation length [s] (+0.5 s holds at each end)")
    d.add_argument("--seed", type=int, default=0, help="random seed of the design")
    common.add_rate_option(d, help="sample rate [Hz]")
    d.add_argument("--out", required=True, type=common.output_file_as(".json"), metavar="FILE.json",
                   help="trajectory JSON to write")
    common.add_json_option(d)
    d.set_defaults(func=run_design)
    from falcon_plan.commands.execute import add_device_arguments, add_model_arguments

    r = sub.add_parser("run", help="record an excitation on a device (approach move, executor, log)")
    add_device_arguments(r)
    add_model_arguments(r)
    r.add_argument("--kind", default="mixed",
                   help=f"excitation kind ({', '.join(KINDS)}) or a trajectory JSON file")
    r.add_argument("--duration", type=common.positive_float, default=8.0, help="excitation length [s] for a kind")
    r.add_argument("--seed", type=int, default=0, help="seed of the design")
    r.add_argument("--realtime", action="store_true", help="pace sim/emulated runs in wall-clock time")
    r.add_argument("--out", required=True, type=common.output_file_as(".csv", ".mcap"), metavar="FILE.csv",
                   help="falcon log (CSV) to write; a FILE.mcap gets an MCAP recording instead")
    common.add_recording_options(r)
    common.add_json_option(r)
    r.set_defaults(func=run_record)
    s = sub.add_parser("synth", help="simulate a falcon log with effects switched on")
    s.add_argument("--effects", default="",
                   help=common.EFFECTS_HELP.format(fields=common.effect_fields()).replace("%", "%%")
                   + " (default: nominal)")
    s.add_argument("--kind", "--trajectory", dest="kind", default="mixed",  # --trajectory: the older spelling
                   help=f"excitation kind ({', '.join(KINDS)}) or a trajectory JSON file")
    s.add_argument("--duration", type=common.positive_float, default=8.0, help="excitation length [s] for a kind")
    s.add_argument("--seed", type=int, default=0, help="seed of the design and of the noise")
    common.add_rate_option(s)
    s.add_argument("--noise", type=float, default=0.0, help="encoder noise std [counts]")
    s.add_argument("--controller", default="pd kp=10 kd=0.1", type=common.controller_text,
                   help="the loop that runs the plant: 'pd kp=NUMBER kd=NUMBER' [command units per count, "
                        "per count/s] with the optional words of the log metadata form, e.g. the executor's "
                        "'pd kp=10 kd=0.1 fc=50 d_on_error=1 ff=1 ff_lead=2 limit=4096', or the executor's "
                        "default LQR 'lqr' (optional words e_pos=, e_vel=, e_u=, delay=, limit=)")
    common.add_model_option(s, "model file whose parameters the plant and the controller's feed-forward use "
                               "(the plant's effects are --effects)")
    s.add_argument("--out", required=True, type=common.output_file_as(".csv"), metavar="FILE.csv",
                   help="falcon log (CSV) to write")
    common.add_json_option(s)
    s.set_defaults(func=run_synth)


def _trajectory(kind_or_path: str, duration_s: float, seed: int, rate_hz: float):
    from falcon_plan.discrepancy.excitation import KINDS, design_trajectory
    if kind_or_path in KINDS:
        return design_trajectory(kind_or_path, duration_s, seed, rate_hz)
    path = Path(kind_or_path)
    if not path.exists():
        raise InvalidParameterError(f"{kind_or_path!r} is neither an excitation kind "
                                    f"({', '.join(KINDS)}) nor an existing JSON file")
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import get_params

    trajectory = common.read_trajectory(path)
    model = FalconModel(get_params(trajectory.params_name))
    return common.checked_for_device(trajectory, path, model, rate_hz).sample(rate_hz, model)


def run_design(args: argparse.Namespace) -> int:
    """Write the designed trajectory."""
    traj = _trajectory(args.kind, args.duration, args.seed, args.rate)
    common.write_trajectory(args.out, traj)
    if args.json:
        common.print_json({"out": str(args.out), "kind": args.kind, "duration_s": traj.duration_s,
                           "rate_hz": args.rate, "samples": len(traj.t_s)})
    else:
        print(f"{args.kind} excitation, {traj.duration_s:.2f} s at {args.rate:g} Hz -> {args.out}")
    return 0


def run_synth(args: argparse.Namespace) -> int:
    """Simulate and write the log."""
    from falcon_plan.control import Controller
    from falcon_plan.discrepancy.synth import synthesize_log
    from falcon_plan.falconlog import write_log
    from falcon_plan.model.effects import Effects
    from falcon_plan.model.modelfile import load_model

    effects = common.load_effects(args.effects)
    model = load_model(args.model)
    controller = Controller.from_meta({}, text=args.controller, rate_hz=args.rate)
    controller = controller.replace(feedforward_effects=model.effects)
    traj = _trajectory(args.kind, args.duration, args.seed, args.rate)
    with common.progress("simulating"):
        log = synthesize_log(effects, traj, rate_hz=args.rate, seed=args.seed, noise_counts=args.noise,
                             controller=controller, model=model.with_effects(Effects()))
    write_log(args.out, log)
    if args.json:
        common.print_json({"out": str(args.out), "samples": len(log), "meta": log.meta})
    else:
        print(f"{len(log)} samples -> {args.out}")
    return 0


def run_record(args: argparse.Namespace) -> int:
    """Record the excitation on the device; exit code 0 when the run completed."""
    from falcon_plan.commands.execute import loop_rate, open_for, wants_pacing
    from falcon_plan.approach import run_from_here
    from falcon_plan.execution.executor import ExecutionStatus
    from falcon_plan.model.modelfile import load_model

    model = load_model(args.model)
    traj = _trajectory(args.kind, args.duration, args.seed, loop_rate(args))
    pace = wants_pacing(args)
    with open_for(args, model) as device, common.live_view(args) as live, \
            common.progress(f"recording on the {args.device} device"):
        # identification records under the PD + feed-forward: its modest gains let the effects
        # show in the motion (the LQR's integral action moves them into the commands), and the
        # discrepancy workflow's thresholds were set on such logs
        report, _ = run_from_here(device, args.device, traj, model, rate_hz=loop_rate(args),
                                  log_path=args.out, pace=pace, mcap=args.mcap, live=live,
                                  controller_kind="pd")
    if args.json:
        common.print_json(report.to_dict())
    else:
        print(report.summary())
    return 0 if report.status == ExecutionStatus.COMPLETED else 1
