"""01: the Falcon model -- kinematics, workspace, force mapping and dynamics.

Run: .venv/bin/python examples/01_kinematics_and_dynamics.py
"""
from __future__ import annotations

import numpy as np

import falcon_plan as fp
from falcon_plan.model.kinematics import leg_torques_for_force


def main() -> None:
    # --- a point in the workspace and its leg angles --------------------------------------
    point_m = np.array([0.01, -0.02, 0.13])
    angles = fp.inverse_kinematics(point_m)
    counts = fp.position_to_counts(point_m, whole=True)
    print(f"point {point_m} m -> theta1 {np.degrees(angles.theta1).round(2)} deg, counts {counts}")

    # --- back again: forward kinematics from whole encoder counts --------------------------
    back_m = fp.counts_to_position(counts)
    print(f"counts {counts} -> point {back_m.round(6)} m (quantisation {1e3 * np.linalg.norm(back_m - point_m):.3f} mm)")

    # --- workspace --------------------------------------------------------------------------
    for p in ([0.0, 0.0, 0.12], [0.0, 0.0, 0.30], [0.07, 0.07, 0.10]):
        check = fp.check_workspace(np.array(p))
        print(f"{p} inside workspace: {bool(check.inside)} {check.reason()}")

    # --- force mapping: pivot torques for 3 N along z ----------------------------------------
    tau = leg_torques_for_force(point_m, [0.0, 0.0, 3.0])
    print(f"3 N along +z at {point_m} needs pivot torques {tau.round(4)} N.m")

    # --- dynamics: holding commands and a motion ---------------------------------------------
    model = fp.FalconModel()
    print(f"commands that hold the device still against gravity: {model.holding_commands(point_m).round(1)}")
    accel = np.array([0.0, 0.0, 20.0])
    velocity = np.array([0.0, 0.0, 0.3])
    print(f"commands for a = {accel} m/s^2 at v = {velocity} m/s: "
          f"{model.inverse_dynamics(point_m, velocity, accel).round(1)}")


if __name__ == "__main__":
    main()
