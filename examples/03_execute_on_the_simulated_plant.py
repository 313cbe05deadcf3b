"""03: plan a move and execute it on the simulated Falcon; print the tracking report and plot it.

The same Executor drives the real device (``open_device("usb", firmware=...)``) and the
emulated one (``open_device("emulated")``, the real pyusb driver over an emulated backend).

Run: .venv/bin/python examples/03_execute_on_the_simulated_plant.py [--out DIR]   (default: out/examples)
"""
from __future__ import annotations

import argparse
from pathlib import Path

import falcon_plan as fp
from falcon_plan.execution.device_factory import open_device, read_position
from falcon_plan.execution.executor import Executor

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "out" / "examples"
RATE_HZ = 800.0  # the paper's control rate, the default everywhere


def main(out_dir: Path) -> None:
    model = fp.FalconModel()
    out_dir.mkdir(parents=True, exist_ok=True)
    log_path = out_dir / "03_run.csv"
    # --- device: the simulated plant, started at a chosen point -----------------------------
    with open_device("sim", rate_hz=RATE_HZ, model=model, start_m=(0.0, 0.0, 0.12)) as device:
        device.home()
        start_m = read_position(device, model.params)
        # --- plan from where the device is --------------------------------------------------
        result = fp.plan(start_m, (0.025, -0.015, 0.135), fp.PlanOptions.fast(), model)
        print(f"planned {1e3 * result.report.duration_s:.1f} ms motion")
        # --- execute: PD + feed-forward, as fast as the simulation runs ----------------------
        report = Executor(device, model, RATE_HZ, log_path=log_path).run(result.trajectory)
    print(report.summary())
    # --- the picture: reference vs measured, errors in counts and mm, commands vs limit -----
    png = fp.plot_run(fp.read_log(log_path), out_dir / "03_run.png")
    print(f"falcon log {log_path}, plot {png}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="folder for the log and the PNG")
    main(parser.parse_args().out)
