"""The one controller (falcon_plan.control.Controller): metadata round trip, other writers'
logs, clear errors, the open-loop offsets checked against an independent computation, and
the executor running exactly the value it logs."""
from __future__ import annotations

import math

import numpy as np
import pytest

from falcon_plan.control import Controller
from falcon_plan.errors import InvalidParameterError, LogFormatError
from falcon_plan.falconlog import FalconLog, read_log, write_log
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects


def test_metadata_round_trip_through_a_log_file(tmp_path) -> None:
    ctl = Controller(1000.0, 12.5, 0.0731, "error", 42.0, "model", 3, 2500,
                     Effects(coulomb_Nm=0.0079, payload_kg=0.05, cable_stiffness_Nm_rad=80.0))
    log = FalconLog(np.arange(3) / 1000.0, np.zeros((3, 3), int), np.zeros((3, 3), int), np.zeros((3, 3)),
                    {**ctl.to_meta(), "params": "acra2009"})
    write_log(tmp_path / "a.csv", log)
    assert Controller.from_meta(read_log(tmp_path / "a.csv").meta) == ctl
    # a gain that %g would round is still written exactly
    odd = Controller(kp=10.123456789)
    assert Controller.from_meta(odd.to_meta()) == odd


def test_other_writers_logs_still_read() -> None:
    plain = Controller.from_meta({"rate_hz": "800", "controller": "pd kp=10 kd=0.1"})
    assert plain == Controller()  # the conventions' PD: 50 Hz filter, kd v, no feed-forward
    assert (plain.derivative, plain.feedforward, plain.velocity_cutoff_hz) == ("measurement", "none", 50.0)
    older = Controller.from_meta({"rate_hz": "1000", "feedforward": "model", "command_limit": "3000",
                                  "controller": "pd kp=10 kd=0.1 cutoff_hz=40 d_on_error=1 ff_lead=2"})
    assert older == Controller(1000.0, 10, 0.1, "error", 40.0, "model", 2, 3000)


@pytest.mark.parametrize("meta, text, needle", [
    ({"rate_hz": "800"}, None, "--controller"),
    ({"rate_hz": "800", "controller": "pid kp=1 kd=2"}, None, "not 'pd'"),
    ({"rate_hz": "800", "controller": "pd kd=0.1"}, None, "lacks kp"),
    ({"rate_hz": "800", "controller": "pd kp=10 kd=0.1 ki=3"}, None, "unknown word"),
    ({"rate_hz": "800", "controller": "pd kp=10 kd=0.1", "feedforward": "plan"}, None, "open-loop"),
    ({"controller": "pd kp=10 kd=0.1"}, None, "--rate"),
    ({"rate_hz": "800"}, "pd kp=-1 kd=0.1", "kp must be"),
])
def test_a_controller_that_cannot_be_reproduced_is_a_clear_error(meta, text, needle) -> None:
    with pytest.raises(LogFormatError, match=needle) as err:
        Controller.from_meta(meta, text=text)
    assert "\n" not in str(err.value)


def test_bad_values_are_rejected() -> None:
    for bad in ({"derivative": "both"}, {"feedforward": "plan"}, {"feedforward_lead_samples": -1},
                {"command_limit": 5000}, {"rate_hz": 0.0}, {"kd": math.nan}):
        with pytest.raises(InvalidParameterError):
            Controller(**bad)


def test_offsets_match_the_analytic_feedforward_of_a_quintic() -> None:
    """Second formulation: the feed-forward from finite differences of the logged reference
    counts against the model's inverse dynamics of the analytic quintic at the period's
    midpoint (mean acceleration), lead samples ahead; and the reference-rate term against a
    plain loop of the filter."""
    from falcon_plan.planning.quintic import quintic_trajectory
    from falcon_plan.model.kinematics import position_to_counts

    model = FalconModel()
    rate, lead = 1000.0, 2
    traj = quintic_trajectory((0.0, 0.0, 0.12), (0.03, -0.02, 0.13), model, duration_s=0.4, rate_hz=rate)
    t = np.arange(-50, 450) / rate
    pos, _, _ = traj.at_time(np.clip(t, 0, traj.duration_s))
    ref = position_to_counts(pos, model.params)
    ctl = Controller(rate, derivative="measurement", feedforward="model", feedforward_lead_samples=lead)
    got = ctl.offsets(ref, model)
    # the analytic quintic: s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 along the line
    start, goal, T = np.array([0.0, 0.0, 0.12]), np.array([0.03, -0.02, 0.13]), traj.duration_s

    def state(tt):
        tau = np.clip(tt / T, 0, 1)[:, None]
        s = tau ** 3 * (10 - 15 * tau + 6 * tau ** 2)
        ds = 30 * tau ** 2 * (1 - tau) ** 2 / T
        return start + s * (goal - start), ds * (goal - start)

    t_mid = t + (lead + 0.5) / rate
    p_mid, v_mid = state(t_mid)
    a_mean = (state(t_mid + 0.5 / rate)[1] - state(t_mid - 0.5 / rate)[1]) * rate
    expected = model.inverse_dynamics(p_mid, v_mid, a_mean)
    inside = slice(55, 440)
    assert np.abs(got[inside] - expected[inside]).max() < 2.0  # command units (of ~2500)
    # the derivative-on-error term: -kd times the filtered reference rate
    err_form = ctl.replace(derivative="error").offsets(ref, model) - got
    v, prev, loop = 0.0 * ref[0], ref[0], []
    for r in ref:
        v = v + ctl.alpha * ((r - prev) * rate - v)
        prev = r
        loop.append(-ctl.kd * v)
    np.testing.assert_allclose(err_form, np.array(loop), atol=1e-9)


def test_the_executor_runs_the_controller_it_logs(tmp_path) -> None:
    """The executor's log, replayed through Controller.run_on from the same plant state, gives
    the same commands sample for sample (until a floating-point tie flips a count)."""
    from falcon_plan.devices.sim_device import SimDevice
    from falcon_plan.execution.executor import Executor
    from falcon_plan.planning.quintic import quintic_trajectory
    from falcon_plan.sim.plant import SimPlant

    model = FalconModel()
    start = np.array([0.0, 0.0, 0.125])
    traj = quintic_trajectory(start, start + [0.03, -0.02, 0.01], model, rate_hz=800.0)
    with SimDevice(model=model, rate_hz=800.0, start_position_m=start) as device:
        device.home()
        Executor(device, model, log_path=tmp_path / "run.csv", preroll_s=0.3, settle_s=0.2).run(traj)
    log = read_log(tmp_path / "run.csv")
    ctl = Controller.from_meta(log.meta)
    assert ctl == Controller.executor_default(800.0, model)
    plant = SimPlant(model, rate_hz=800.0)
    plant.reset(start)
    plant.step([0, 0, 0])  # the executor's zero-force first read
    run = ctl.run_on(plant, log.ref, model)
    same = np.all(run.commands == log.tc, axis=1)
    assert same[:500].all() and same.mean() > 0.95, np.flatnonzero(~same)[:5]


def test_the_velocity_filter_over_a_signal_matches_scipy_lfilter() -> None:
    """low_pass (the PD's filter update run over a whole reference) against scipy's lfilter
    of the same first-order low-pass, b = [alpha], a = [1, alpha - 1], from rest."""
    from scipy.signal import lfilter

    from falcon_plan.control import low_pass, velocity_filter_alpha

    raw = np.random.default_rng(4).normal(scale=2000.0, size=(3000, 3))
    alpha = velocity_filter_alpha(800.0)
    np.testing.assert_allclose(low_pass(raw, alpha), lfilter([alpha], [1.0, alpha - 1.0], raw, axis=0),
                               rtol=1e-12, atol=1e-9)


def test_offsets_are_remembered_per_reference_and_handed_out_as_copies() -> None:
    """A replay reruns one log's offsets under many trial effects: the second call returns what
    the first computed (same values, for the same reference, gains and parameter set), a caller
    that writes into its copy changes nothing for the next, and another reference or another
    controller is computed afresh."""
    model = FalconModel()
    ctl = Controller(1000.0, derivative="error", feedforward="model")
    ref = np.cumsum(np.full((300, 3), 0.4), axis=0)
    first = ctl.offsets(ref, model)
    first[:] = 0.0
    again = ctl.offsets(ref, model)
    np.testing.assert_array_equal(again, ctl._offsets(ref, model))
    assert np.abs(again).max() > 1.0
    np.testing.assert_array_equal(ctl.replace(kd=0.2).offsets(ref, model), ctl.replace(kd=0.2)._offsets(ref, model))
    assert not np.array_equal(ctl.replace(kd=0.2).offsets(ref, model), again)
    np.testing.assert_array_equal(ctl.offsets(ref[:200], model), ctl._offsets(ref[:200], model))
