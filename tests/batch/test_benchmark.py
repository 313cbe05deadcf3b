"""The full benchmark (every problem, every core): a benchmark, not a unit test.

Skipped unless FALCON_BENCH=1 (see conftest.py); the same as
``falcon-plan bench problems/ --out out/bench``.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from falcon_plan.cli import main as cli_main


@pytest.mark.benchmark
def test_full_benchmark(problems_dir: Path, tmp_path: Path) -> None:
    code = cli_main(["bench", str(problems_dir), "--out", str(tmp_path)])
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert code == 0, summary["not_met"]
    assert summary["methods"]["casadi"]["success_rate"] == 1.0
