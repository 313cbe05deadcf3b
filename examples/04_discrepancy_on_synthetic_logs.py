"""04: hide an effect in simulated logs and let the discrepancy workflow find it.

Two logs are made on the plant with Coulomb friction switched on (a training motion and a
different held-out motion); the workflow is not told what is there.

Run: .venv/bin/python examples/04_discrepancy_on_synthetic_logs.py
"""
from __future__ import annotations

import argparse

from falcon_plan.discrepancy.excitation import design_trajectory
from falcon_plan.discrepancy.synth import synthesize_log
from falcon_plan.discrepancy.workflow import find_discrepancy
from falcon_plan.model.effects import Effects


def main() -> None:
    hidden = Effects(coulomb_Nm=0.008)
    # --- data: different motions and seeds for training and held-out ------------------------
    train = synthesize_log(hidden, design_trajectory("mixed", duration_s=6.0, seed=11), seed=11)
    heldout = synthesize_log(hidden, design_trajectory("fourier", duration_s=4.0, seed=23), seed=23)
    # --- the workflow -----------------------------------------------------------------------
    report = find_discrepancy(train, heldout)
    summary = report.to_dict()
    print("named effects:", summary["effects"])
    print("parameters:", summary["parameters"])
    print(f"held-out RMS [counts]: {summary['heldout_rms_before']:.2f} -> {summary['heldout_rms_after']:.2f}")
    print("corrected model effects:", report.corrected.to_dict())


if __name__ == "__main__":
    # no options: it writes nothing (an unknown argument, --out say, is refused, not ignored)
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    main()
