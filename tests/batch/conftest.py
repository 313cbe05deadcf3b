"""Fixtures of the batch tests, and the ``benchmark`` marker: the full benchmark run is not a
unit test; it runs only with FALCON_BENCH=1."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

PROBLEMS_DIR = Path(__file__).resolve().parents[2] / "problems"


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "benchmark: the full benchmark run (only with FALCON_BENCH=1)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if os.environ.get("FALCON_BENCH") == "1":
        return
    skip = pytest.mark.skip(reason="benchmark, not a unit test: set FALCON_BENCH=1 to run it")
    for item in items:
        if "benchmark" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def problems_dir() -> Path:
    """The committed problems folder."""
    return PROBLEMS_DIR
