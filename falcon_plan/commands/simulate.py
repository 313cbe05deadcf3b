"""``falcon-plan simulate``: experiments on the simulated plant.

``falcon-plan simulate step --from X,Y,Z --to X,Y,Z [--rate 800] [--duration 1.5]
[--out DIR] [--effects JSON]`` runs the paper's Section 6 step experiment
(:mod:`falcon_plan.sim.step`) and writes to DIR: ``step_log.csv`` (falcon log),
``step_plot.png`` (counts and commands, like the paper's Figure 9) and ``step_summary.json``;
it prints a short summary. Points are in metres, base frame.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from falcon_plan.errors import InvalidParameterError


def _point(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in metres (e.g. 0,0,0.12), got {text!r}")
    return values  # type: ignore[return-value]


def _positive(text: str) -> float:
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def load_effects(text: str | None) -> Any:
    """Effects from a JSON object given inline or as a file path (None: nominal)."""
    from falcon_plan.model.effects import Effects
    if not text:
        return Effects()
    source = Path(text).read_text() if not text.lstrip().startswith("{") else text
    try:
        data = json.loads(source)
    except json.JSONDecodeError as exc:
        raise InvalidParameterError(f"--effects is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise InvalidParameterError("--effects must be a JSON object of effect fields")
    return Effects.from_dict(data)


def register(subparsers: Any) -> None:
    """Add the ``simulate`` subcommand (with its ``step`` experiment)."""
    parser = subparsers.add_parser("simulate", help="experiments on the simulated plant",
                                   description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="experiment", metavar="EXPERIMENT")
    sub.required = True
    step = sub.add_parser("step", help="the paper's Section 6 PD step experiment, simulated")
    step.add_argument("--from", dest="start", required=True, type=_point, help="start X,Y,Z [m]")
    step.add_argument("--to", dest="goal", required=True, type=_point, help="goal X,Y,Z [m]")
    step.add_argument("--rate", type=_positive, default=800.0, help="control rate [Hz] (default 800)")
    step.add_argument("--duration", type=_positive, default=1.5, help="total time [s] (default 1.5)")
    step.add_argument("--step-at", type=_positive, default=0.25,
                      help="time of the reference step [s] (default 0.25)")
    step.add_argument("--out", type=Path, default=Path("."), help="output directory (default .)")
    step.add_argument("--effects", default=None,
                      help='effects of the simulated device: JSON object or file, e.g. '
                           '\'{"coulomb_Nm": 0.01, "backlash_rad": 0.002}\'')
    step.add_argument("--params", default="acra2009", help="parameter set (default acra2009)")
    step.add_argument("--model", type=Path, default=None,
                      help="model file (JSON): the simulated device is that model (parameters and "
                           "effects; --effects, if given, replaces its effects); overrides --params")
    step.set_defaults(func=run_step)


def run_step(args: argparse.Namespace) -> int:
    """Run the step experiment and write its outputs; returns the exit code."""
    from falcon_plan.falconlog import write_log
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import get_params
    from falcon_plan.sim.step import plot_step, run_step_experiment

    from falcon_plan.model.modelfile import load_model

    if args.model is not None:
        loaded = load_model(args.model)
        model = FalconModel(loaded.params)
        effects = loaded.effects if args.effects is None else load_effects(args.effects)
    else:
        model = FalconModel(get_params(args.params))
        effects = load_effects(args.effects)
    result = run_step_experiment(args.start, args.goal, rate_hz=args.rate, duration_s=args.duration,
                                 step_at_s=args.step_at, effects=effects, model=model)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    write_log(out / "step_log.csv", result.log)
    plot_step(result, out / "step_plot.png")
    (out / "step_summary.json").write_text(json.dumps(result.to_dict(), indent=2) + "\n")
    print(result.summary())
    print(f"wrote {out / 'step_log.csv'}, {out / 'step_plot.png'}, {out / 'step_summary.json'}")
    return 0
