"""The command line's parser loads no heavy library: ``falcon-plan --help`` and every command's
argument parsing cost the interpreter, numpy and the parsers, not CasADi, SciPy, matplotlib,
the solvers or Zenoh (those load when a command runs; the time is measured by
benchmarks/bench_cli.py)."""
from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("casadi", "scipy", "matplotlib", "toppra", "ruckig", "osqp", "zenoh", "usb")


def _loaded_after(code: str) -> list[str]:
    probe = f"{code}\nimport json, sys\nprint(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.splitlines()[-1])


def test_building_the_parser_loads_no_heavy_library() -> None:
    code = ("from falcon_plan.cli import build_parser, command_names\n"
            "parser = build_parser()\n"
            "assert len(command_names()) >= 14\n"
            "parser.format_help()")
    assert _loaded_after(code) == []


def test_importing_the_package_loads_no_heavy_library_and_names_still_resolve() -> None:
    assert _loaded_after("import falcon_plan") == []
    code = ("import falcon_plan as fp\n"
            "assert fp.FalconModel.__name__ == 'FalconModel' and callable(fp.plan)\n"
            "assert set(fp.__all__) <= set(dir(fp)) and fp.__version__")
    assert "casadi" in _loaded_after(code)
