"""The workflow on logs a real host records (issue 26): the independent world behind a busy
real-time host (:mod:`.host_world`: jitter, stalls that skip ticks, a fractional transport
delay). Representative cases of ``benchmarks/bench_identification_host.py``'s table: the
nominal device answers none without a flag (the floor comes from the log), a pair is named,
and an effect outside the library is reported as unexplained with nothing listed."""
from __future__ import annotations

import math

import numpy as np
import pytest

from falcon_plan.discrepancy.checks import UNEXPLAINED_FACTOR
from falcon_plan.discrepancy.replay import closed_loop_replay, log_controller, tick_schedule
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import NOMINAL

from .host_cases import HOST_CASES, host_logs, host_report


def test_host_logs_carry_the_timing_and_replay_within_the_floor() -> None:
    """The host world's logs have timing columns, skipped ticks and jitter; the timed replay
    of the nominal device follows them to about the quantisation floor."""
    train, _ = host_logs(HOST_CASES["none"])
    schedule = tick_schedule(train, 1000.0)
    assert schedule.timed and train.skipped.sum() > 50 and train.skipped.max() >= 5
    assert np.ptp(schedule.sent - schedule.slot) > 0.4    # jitter of the sends, in periods
    sim = closed_loop_replay(train, NOMINAL, FalconModel(), 1000.0, log_controller(train))
    assert np.sqrt(np.mean((sim - train.enc) ** 2)) < 0.8


@pytest.mark.slow
def test_nominal_device_on_a_busy_host_answers_none_without_a_flag() -> None:
    report = host_report("none")
    assert report.effects == ["none"] and not report.unexplained.unexplained, report.unexplained
    assert report.unexplained.timing_counts > 0.0


@pytest.mark.slow
def test_a_pair_is_named_on_a_busy_host() -> None:
    report = host_report("coulomb+payload")
    assert sorted(report.effects) == ["coulomb_friction", "payload_mass"], report.evidence
    assert report.parameters["payload_kg"].value == pytest.approx(0.04, rel=0.2)
    assert report.heldout_after.rms_counts_all < 0.2 * report.heldout_before.rms_counts_all
    assert report.settings["stribeck_replay_refit"] is None     # no Stribeck curve named: nothing refitted


@pytest.mark.slow
def test_a_stribeck_curve_is_refitted_on_the_replay() -> None:
    """The world's break-away (exponential in speed, 0.008 N.m above Coulomb) is named as a
    Stribeck curve whose inverse-dynamics fit sees only the moving samples; refitted on the
    replay (where sticking and break-away show) the training replay improves by more than 15 %
    and the held-out error falls fourfold. The world sticks exactly (an impulse up to the
    break-away torque), which the model's smoothed sign approaches but does not reach: what
    the refit leaves sits at the open-world rule (2x the floor). Over 8 draws of the busy
    host's timing it was flagged in 7, at 0.88-1.23 times the rule where the curve was named
    (in 3 of 5 before the world's half-angle fix): the flag is not asserted either way, only
    that the remainder stays near the rule."""
    report = host_report("stribeck_friction")
    assert sorted(report.effects) == ["coulomb_friction", "stribeck_friction"], report.evidence
    refit = report.settings["stribeck_replay_refit"]
    assert refit["kept"] and refit["rms_fitted"] < 0.85 * refit["rms_default"], refit
    assert refit["after"]["stribeck_Nm"] > refit["before"]["stribeck_Nm"]
    assert report.parameters["stribeck_Nm"].value == refit["after"]["stribeck_Nm"]
    check = report.unexplained
    assert check.replay_rms_counts < 1.25 * UNEXPLAINED_FACTOR * check.floor_counts, check
    assert report.heldout_after.rms_counts_all < 0.25 * report.heldout_before.rms_counts_all


@pytest.mark.slow
def test_a_command_dead_band_is_unexplained_with_nothing_listed() -> None:
    """A dead band acts on the command: the residual has the command's sign, which no
    candidate has; the listed effects that stood in for it are dropped."""
    report = host_report("command dead band (outside)")
    assert report.effects == ["none"]
    u = report.unexplained
    assert u.unexplained and u.outside_library is not None and u.outside_library["shape"] == "command dead band", u
    assert u.where is not None and u.when.end_s > u.when.start_s
    dropped = [r["effect"] for r in report.evidence if r["status"].startswith("dropped (outside the library")]
    assert dropped, report.evidence


def test_an_unmeasured_transport_delay_is_fitted() -> None:
    """A log with timing columns but no measured delay (no doctor run): the fractional delay
    is fitted on the training replay; here the host's sample-to-send-to-act path takes 4.25
    periods in the replay's convention (reading arrival + 17 world steps of a quarter period;
    a slow link, e.g. a 2 ms FTDI latency timer). (At 3.25 periods the replay with the default
    2 is already within 0.15 counts of the fitted one, which the practical rule does not keep.)"""
    from falcon_plan.discrepancy.checks import fit_transport_delay
    from falcon_plan.discrepancy.excitation import design_trajectory

    from .host_world import HostTiming, simulate_host_log
    from .independent_world import World

    ref = design_trajectory("mixed", 6.0, seed=11, rate_hz=1000.0).counts
    log = simulate_host_log(World(), ref, 1000.0, timing=HostTiming(out_delay=15), seed=11, measured_delay=False)
    fit = fit_transport_delay(log, FalconModel(), 1000.0, log_controller(log), NOMINAL)
    assert fit is not None and fit.kept, fit
    assert fit.value == pytest.approx(4.25, abs=0.25)
    assert fit.rms_fitted < 0.8 * fit.rms_default
    measured = simulate_host_log(World(), ref[:1500], 1000.0, seed=11)   # a measured delay is used as it is
    assert fit_transport_delay(measured, FalconModel(), 1000.0, log_controller(measured), NOMINAL) is None


def test_a_much_slower_link_is_reached_by_the_far_first_trial(monkeypatch: pytest.MonkeyPatch) -> None:
    """A link three periods slower than the run assumed (5.25 periods from the reading to the
    command acting): the latest of the first trials is the best of them, so the far trial
    (:data:`~falcon_plan.discrepancy.checks.DELAY_FAR_OFFSET`) is replayed too and the search
    reaches the delay; without it the refinement stops short, the criterion far above."""
    from falcon_plan.discrepancy import checks
    from falcon_plan.discrepancy.excitation import design_trajectory

    from .host_world import HostTiming, simulate_host_log
    from .independent_world import World

    ref = design_trajectory("mixed", 6.0, seed=11, rate_hz=1000.0).counts
    log = simulate_host_log(World(), ref, 1000.0, timing=HostTiming(out_delay=19), seed=11, measured_delay=False)
    fit = checks.fit_transport_delay(log, FalconModel(), 1000.0, log_controller(log), NOMINAL)
    assert fit is not None and fit.kept and fit.value == pytest.approx(5.25, abs=0.3), fit
    assert fit.rms_fitted < 0.2 * fit.rms_default, fit
    monkeypatch.setattr(checks, "DELAY_FAR_OFFSET", math.inf)   # never replayed
    short = checks.fit_transport_delay(log, FalconModel(), 1000.0, log_controller(log), NOMINAL)
    assert short is not None and short.value < fit.value - 0.2 and short.rms_fitted > 1.5 * fit.rms_fitted, short


def test_a_slow_link_is_not_named_as_a_command_delay() -> None:
    """A device with a payload behind a slow link (4.25 periods from the reading to the command
    acting) and no measured delay: the extra delay the inverse-dynamics residual sees is the
    link's, not the device's; it is fitted as the transport delay and only the payload is named."""
    from falcon_plan.discrepancy.excitation import design_trajectory
    from falcon_plan.discrepancy.workflow import find_discrepancy

    from .host_world import HostTiming, simulate_host_log
    from .independent_world import World

    logs = [simulate_host_log(World(payload_kg=0.04), design_trajectory(kind, seconds, seed=seed, rate_hz=1000.0).counts, 1000.0,
                              timing=HostTiming(out_delay=15), seed=seed, measured_delay=False)
            for kind, seconds, seed in (("mixed", 4.0, 11), ("fourier", 3.0, 23))]
    report = find_discrepancy(*logs)
    assert report.effects == ["payload_mass"], report.evidence
    fit = report.settings["transport_delay_fit"]
    assert fit["kept"] and fit["value"] == pytest.approx(4.25, abs=0.3), fit


@pytest.mark.slow
def test_a_device_delay_behind_an_unmeasured_link_is_kept_in_the_replay() -> None:
    """A device with one period of extra command delay, recorded with timing columns but no
    measured transport delay: the logs cannot tell the device's delay from the link's, so the
    delay is fitted as the link's, seeded by the command delay the residual chose, and kept
    for both logs' replays: the held-out replay then matches as a nominal device's does (0.51
    counts). (Before the training design had its reversals, the fit lowered the training
    replay by less than 0.2 counts, 25 %, and was kept on its seed's evidence; with them it
    halves it.)"""
    from falcon_plan.discrepancy.excitation import design_trajectory
    from falcon_plan.discrepancy.workflow import find_discrepancy

    from .host_world import simulate_host_log
    from .independent_world import World

    logs = [simulate_host_log(World(extra_delay=1), design_trajectory(kind, seconds, seed=seed, rate_hz=1000.0).counts,
                              1000.0, seed=seed, measured_delay=False)
            for kind, seconds, seed in (("mixed", 6.0, 11), ("fourier", 4.0, 23))]
    report = find_discrepancy(*logs)
    fit = report.settings["transport_delay_fit"]
    assert fit["kept"] and fit["rms_fitted"] < fit["rms_default"], fit
    assert fit["value"] == pytest.approx(fit["seeded_by_command_delay"], abs=0.5), fit
    assert report.heldout_after.rms_counts_all < 0.7, report.heldout_after
    assert not report.unexplained.unexplained, report.unexplained


@pytest.mark.slow
def test_commands_acting_later_than_the_run_assumed_name_a_command_delay() -> None:
    """A device with two periods of extra command delay, on logs that record the link delay the
    run's controller led by (as the executor's do) but no measured transport delay: the fitted
    delay is two periods later than the run assumed, so a command delay is named (the device's
    or the link's: the logs cannot tell) and written into the model file as its link delay; the
    held-out replay improves from the delay the run assumed. A nominal device on the same host
    names none."""
    from falcon_plan.calibration import corrected_model_file
    from falcon_plan.discrepancy.excitation import design_trajectory
    from falcon_plan.discrepancy.workflow import find_discrepancy
    from falcon_plan.falconlog import LINK_DELAY_KEY, FalconLog

    from .host_world import BUSY, SUB, simulate_host_log
    from .independent_world import World

    link = (BUSY.out_delay + BUSY.in_delay) / SUB - FalconModel().params.command_delay_samples

    def logs(world: World) -> list[FalconLog]:
        out = []
        for kind, seconds, seed in (("mixed", 6.0, 11), ("fourier", 4.0, 23)):
            log = simulate_host_log(world, design_trajectory(kind, seconds, seed=seed, rate_hz=1000.0).counts,
                                    1000.0, seed=seed, measured_delay=False)
            out.append(FalconLog(log.t_s, log.enc, log.tc, log.ref, {**log.meta, LINK_DELAY_KEY: f"{link:g}"},
                                 *log.timing_columns))
        return out

    late = find_discrepancy(*logs(World(extra_delay=2)))
    assert late.effects == ["command_delay"], late.evidence
    assert late.parameters["extra_delay_samples"].value == pytest.approx(2.0, abs=0.3)
    assert late.corrected.extra_delay_samples == 0          # a fractional figure: the link's delay
    model_file = corrected_model_file(late, FalconModel(), {"train": "t", "heldout": "h"})
    assert model_file.model.params.link_delay_samples == pytest.approx(link + 2.0, abs=0.3)
    assert late.heldout_after.rms_counts_all < 0.5 * late.heldout_before.rms_counts_all, late.heldout_after
    assert "command_delay" not in find_discrepancy(*logs(World())).effects
