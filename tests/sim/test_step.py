"""The simulated Section 6 step experiment and ``falcon-plan simulate step``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from falcon_plan.cli import main
from falcon_plan.errors import WorkspaceError
from falcon_plan.falconlog import read_log
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.kinematics import position_to_counts
from falcon_plan.sim.step import pd_equilibrium, run_step_experiment

START, GOAL = (0.0, 0.0, 0.12), (0.02, 0.015, 0.14)


@pytest.fixture(scope="module")
def result(model: FalconModel):  # type: ignore[no-untyped-def]
    return run_step_experiment(START, GOAL, model=model)


def test_log_has_ref_and_metadata(result) -> None:  # type: ignore[no-untyped-def]
    log = result.log
    assert len(log) == 1200 and log.rate_hz == 800.0 and log.meta["params"] == "acra2009"
    assert log.controller is not None and log.controller.gains == {"kp": 10.0, "kd": 0.1}
    assert log.ref is not None
    k_step = int(0.25 * 800)
    assert np.allclose(log.ref[:k_step], position_to_counts(np.array(START)))
    assert np.allclose(log.ref[k_step:], position_to_counts(np.array(GOAL)))


def test_starts_settled_and_ends_at_the_predicted_error(result) -> None:  # type: ignore[no-untyped-def]
    log = result.log
    k_step = int(0.25 * 800)
    assert np.ptp(log.enc[:k_step], axis=0).max() <= 1  # at rest before the step
    assert np.abs(result.steady_state_error_counts - result.predicted_error_counts).max() < 2.0
    assert np.isfinite(result.settling_time_s).all() and (result.settling_time_s < 1.25).all()
    assert result.peak_command.max() == 4096  # the step saturates the commands
    summary = result.summary()
    assert "steady-state error" in summary and "settling" in summary


def test_pd_equilibrium_balances_gravity(model: FalconModel) -> None:
    ref = position_to_counts(np.array(START))
    p = pd_equilibrium(model, ref)
    n = position_to_counts(p)
    assert np.abs(10.0 * (n - ref) - model.holding_commands(p)).max() < 1e-4


def test_rejects_goal_outside_the_workspace(model: FalconModel) -> None:
    with pytest.raises(WorkspaceError):
        run_step_experiment(START, (0.0, 0.0, 0.5), model=model)


def test_cli_writes_log_plot_and_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    effects = tmp_path / "effects.json"
    effects.write_text(json.dumps({"viscous_Nms": 0.005}))
    code = main(["simulate", "step", "--from", "0,0,0.12", "--to", "0.02,0.015,0.14",
                 "--duration", "1.0", "--out", str(tmp_path / "out"), "--effects", str(effects)])
    assert code == 0
    out = tmp_path / "out"
    log = read_log(out / "step_log.csv")
    assert len(log) == 800 and json.loads(log.meta["effects"]) == {"viscous_Nms": 0.005}
    assert (out / "step_plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((out / "step_summary.json").read_text())
    assert summary["effects"] == {"viscous_Nms": 0.005} and len(summary["peak_command"]) == 3
    assert "peak command" in capsys.readouterr().out


def test_cli_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", "step", "--from", "0,0,0.12", "--to", "0,0,0.5",
                 "--out", str(tmp_path)]) == 2
    assert "error" in capsys.readouterr().err
    assert main(["simulate", "step", "--from", "0,0,0.12", "--to", "0,0,0.13",
                 "--effects", '{"warp_drive": 1}', "--out", str(tmp_path)]) == 2
    with pytest.raises(SystemExit):
        main(["simulate", "step", "--from", "0,0", "--to", "0,0,0.13"])


def test_effects_change_the_experiment(model: FalconModel, result) -> None:  # type: ignore[no-untyped-def]
    damped = run_step_experiment(START, GOAL, model=model, effects=Effects(viscous_Nms=0.02))
    assert (damped.settling_time_s < result.settling_time_s).all()
