"""03: plan a move and execute it on the simulated Falcon; print the tracking report.

The same Executor drives the real device (``open_device("usb", firmware=...)``) and the
emulated one (``open_device("emulated")``, the real pyusb driver over an emulated backend).

Run: .venv/bin/python examples/03_execute_on_the_simulated_plant.py
"""
from __future__ import annotations

from falcon_plan.execution.device_factory import open_device, read_position
from falcon_plan.execution.executor import Executor
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.planning.api import plan
from falcon_plan.planning.problem import PlanOptions


def main() -> None:
    model = FalconModel()
    # --- device: the simulated plant at the paper's 800 Hz, started at a chosen point -------
    with open_device("sim", rate_hz=800.0, model=model, start_m=(0.0, 0.0, 0.12)) as device:
        device.home()
        start_m = read_position(device, model.params)
        # --- plan from where the device is --------------------------------------------------
        result = plan(start_m, (0.025, -0.015, 0.135), PlanOptions.fast(), model)
        print(f"planned {1e3 * result.report.duration_s:.1f} ms motion")
        # --- execute: PD + feed-forward, as fast as the simulation runs ----------------------
        report = Executor(device, model, log_path="example_run.csv").run(result.trajectory)
    print(report.summary())
    print("falcon log written to example_run.csv")


if __name__ == "__main__":
    main()
