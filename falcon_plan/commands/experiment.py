"""``falcon-plan experiment design|synth``: excitation trajectories for identification, and
synthetic falcon logs from the simulated plant with chosen effects switched on."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from falcon_plan.errors import InvalidParameterError


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``experiment`` subcommand with ``design`` and ``synth``."""
    from falcon_plan.discrepancy.excitation import KINDS

    p = subparsers.add_parser("experiment", help="identification experiments (design, synth)",
                              description=__doc__)
    sub = p.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    d = sub.add_parser("design", help="write an excitation trajectory (JSON) for the executor")
    d.add_argument("--kind", choices=KINDS, default="mixed")
    d.add_argument("--duration", type=float, default=8.0, help="excitation length [s] (+0.5 s holds)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--rate", type=float, default=800.0, help="sample rate [Hz]")
    d.add_argument("--out", required=True, help="trajectory JSON path")
    d.set_defaults(func=run_design)
    s = sub.add_parser("synth", help="simulate a falcon log with effects switched on")
    s.add_argument("--effects", default="{}",
                   help="effects as JSON text or a JSON file (Effects.to_dict() fields)")
    s.add_argument("--trajectory", default="mixed",
                   help=f"excitation kind ({', '.join(KINDS)}) or a trajectory JSON file")
    s.add_argument("--duration", type=float, default=8.0, help="excitation length [s] for a kind")
    s.add_argument("--seed", type=int, default=0, help="seed of the design and of the noise")
    s.add_argument("--rate", type=float, default=800.0, help="control rate [Hz]")
    s.add_argument("--noise", type=float, default=0.0, help="encoder noise std [counts]")
    s.add_argument("--controller", default="pd kp=10 kd=0.1")
    s.add_argument("--out", required=True, help="falcon log CSV path")
    s.set_defaults(func=run_synth)


def _trajectory(kind_or_path: str, duration_s: float, seed: int, rate_hz: float):
    from falcon_plan.discrepancy.excitation import KINDS, design_trajectory
    from falcon_plan.planning.trajectory import Trajectory

    if kind_or_path in KINDS:
        return design_trajectory(kind_or_path, duration_s, seed, rate_hz)
    path = Path(kind_or_path)
    if not path.exists():
        raise InvalidParameterError(f"--trajectory {kind_or_path!r} is neither a kind "
                                    f"({', '.join(KINDS)}) nor an existing JSON file")
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import get_params

    trajectory = Trajectory.from_json(path)
    return trajectory.sample(rate_hz, FalconModel(get_params(trajectory.params_name)))


def run_design(args: argparse.Namespace) -> int:
    """Write the designed trajectory."""
    traj = _trajectory(args.kind, args.duration, args.seed, args.rate)
    traj.to_json(args.out)
    print(f"{args.kind} excitation, {traj.duration_s:.2f} s at {args.rate:g} Hz -> {args.out}")
    return 0


def run_synth(args: argparse.Namespace) -> int:
    """Simulate and write the log."""
    from falcon_plan.discrepancy.synth import synthesize_log
    from falcon_plan.falconlog import write_log
    from falcon_plan.model.effects import Effects

    text = args.effects
    if not text.lstrip().startswith("{"):
        text = Path(text).read_text()
    try:
        effects = Effects.from_dict(json.loads(text))
    except json.JSONDecodeError as exc:
        raise InvalidParameterError(f"--effects is not valid JSON: {exc}") from exc
    traj = _trajectory(args.trajectory, args.duration, args.seed, args.rate)
    log = synthesize_log(effects, traj, rate_hz=args.rate, seed=args.seed, noise_counts=args.noise,
                         controller=args.controller)
    write_log(args.out, log)
    print(f"{len(log)} samples -> {args.out}")
    return 0
