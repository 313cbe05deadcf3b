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


def _second_run(argv: list[str], capsys, monkeypatch) -> tuple[str, str]:
    """Run the command line ``argv`` twice (the first fills the kernel cache if this machine
    has none yet); the second run's (stdout, stderr), with progress shown at once, after
    checking that it compiled nothing."""
    from falcon_plan import cli
    from falcon_plan.commands import common
    from falcon_plan.compiled import build

    assert cli.main(argv) == 0
    capsys.readouterr()
    monkeypatch.setattr(common, "PROGRESS_AFTER_S", 0.0)
    before = build.compilations
    assert cli.main(argv) == 0
    out, err = capsys.readouterr()
    assert build.compilations == before
    return out, err


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


def test_a_plan_says_compiled_only_when_a_kernel_is_compiled(capsys, monkeypatch) -> None:
    """Every wait's progress is shown at once here (PROGRESS_AFTER_S = 0); with the kernels
    already cached (the plan before) nothing is compiled and no line says so; the report
    says the cross-checks were not run (the command line leaves them to --crosscheck)."""
    out, err = _second_run(["plan", "--from", "0,0,0.12", "--to", "0.02,0.01,0.13"], capsys, monkeypatch)
    assert "preparing the planner" in err and "compil" not in err.lower()
    assert "cross-checks (toppra same path and straight line, ruckig): not run" in out


def test_a_default_plan_loads_neither_scipy_nor_the_cross_checks_libraries() -> None:
    """The default plan on the command line (dense re-check, refinement, plant run) needs
    numpy, CasADi and ruckig only: toppra (which loads matplotlib) with --crosscheck, SciPy's
    QR for via points with surplus switch times, its k-d tree to build the forward-kinematics
    seed table once per machine (then read from the cache folder)."""
    code = ("from falcon_plan import cli\n"
            "assert cli.main(['plan', '--from', '0,0,0.12', '--to', '0.03,0.02,0.14']) == 0")
    _loaded_after(code)  # a fresh machine fills its caches here
    assert _loaded_after(code) == ["casadi", "ruckig"]


def test_execute_says_compiled_only_when_a_kernel_is_compiled(capsys, monkeypatch) -> None:
    """The LQR's set-up in ``execute`` (its linearisation built, its kernels loaded) shows its
    progress, but with the kernels already cached (the run before) nothing is compiled and no
    line claims it ("preparing the controller's compiled kernels (once per machine)" was
    printed on every run, issue 28 item 3)."""
    argv = ["execute", "--device", "sim", "--from", "0,0,0.12", "--to", "-0.02,0.01,0.13", "--planner", "quintic"]
    _out, err = _second_run(argv, capsys, monkeypatch)
    assert "preparing the controller" in err and "compil" not in err.lower() and "once per machine" not in err, err
