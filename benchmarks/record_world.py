"""Record a falcon log with ``falcon-plan experiment run --device emulated`` whose emulated
Falcon has the independent world's physics inside (``tests/discrepancy/world_device.py``)
instead of the project's plant: the project's executor and threaded USB driver, in wall-clock
time, as a user records a real device.

Usage::

    python benchmarks/record_world.py CASE -- experiment run --device emulated --usb-timing wall ...

``CASE`` is a name of ``tests/discrepancy/host_cases.py``'s HOST_CASES (its world, dead band
and gain drift); the arguments after ``--`` are the command line's (``--effects`` is refused:
the world is the truth).
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))      # the test tree's worlds (tests/discrepancy)


def main(argv: list[str]) -> int:
    if len(argv) < 2 or argv[1] != "--" or "--effects" in argv:
        print("usage: record_world.py CASE -- experiment run --device emulated ... (no --effects)", file=sys.stderr)
        return 2
    from falcon_plan import cli
    from falcon_plan.execution import device_factory
    from tests.discrepancy.host_cases import HOST_CASES
    from tests.discrepancy.world_device import WorldPlant, open_world_device

    case = HOST_CASES[argv[0]]
    real_open = device_factory.open_device

    def open_device(kind: str, **options):
        if kind != "emulated":
            return real_open(kind, **options)
        plant = WorldPlant(case.world, options.get("rate_hz", 1000.0), deadband=case.deadband,
                           gain_drift=case.gain_drift)
        return open_world_device(plant, rate_hz=options.get("rate_hz", 1000.0), usb_timing=options.get("usb_timing"))

    device_factory.open_device = open_device
    return cli.main(argv[2:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
