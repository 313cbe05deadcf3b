"""A planning process's first start on a machine compiles kernels (minutes): the pool waits
for a process that lives and says so, instead of giving up after a fixed time; a process that
dies while starting is an error naming its exit status."""
from __future__ import annotations

import logging
import threading

import pytest

import service.workers as workers
from service.testing import START_GATE_ENV, gated_planner_factory, wait_until
from service.workers import PlanningPool


def _start_in_thread(pool: PlanningPool) -> tuple[threading.Thread, list[BaseException]]:
    errors: list[BaseException] = []

    def start() -> None:
        try:
            pool.start()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            errors.append(exc)

    thread = threading.Thread(target=start, daemon=True)
    thread.start()
    return thread, errors


def test_a_slow_first_start_is_waited_for_and_reported(tmp_path, monkeypatch, caplog):
    gate = tmp_path / "gate"
    monkeypatch.setenv(START_GATE_ENV, str(gate))
    monkeypatch.setattr(workers, "WORKER_START_NOTICE_S", 0.05)
    pool = PlanningPool(1, gated_planner_factory, name="slow-start")
    caplog.set_level(logging.WARNING, logger="service.workers")
    thread, errors = _start_in_thread(pool)
    try:
        # the process is still starting, past several notices: the pool waits and says so
        wait_until(lambda: sum("is still starting" in r.getMessage() for r in caplog.records) >= 3,
                   "three 'still starting' notices")
        assert thread.is_alive() and not errors
        gate.write_text("go")
        thread.join(60)
        assert not thread.is_alive() and not errors, errors
        assert pool._slots[0].alive()
    finally:
        gate.write_text("go") if not gate.exists() else None
        thread.join(60)
        pool.close()


def test_a_process_that_dies_while_starting_is_an_error_naming_its_status(tmp_path, monkeypatch):
    gate = tmp_path / "gate"
    gate.write_text("exit")
    monkeypatch.setenv(START_GATE_ENV, str(gate))
    monkeypatch.setattr(workers, "WORKER_START_NOTICE_S", 0.05)
    pool = PlanningPool(1, gated_planner_factory, name="dies")
    try:
        with pytest.raises(RuntimeError, match=r"did not start \(it exited with status 3\)"):
            pool.start()
    finally:
        pool.close()
