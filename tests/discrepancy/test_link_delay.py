"""A USB link delay the run knew about (the device's, or the model file's measured one) is part
of the nominal replay: recorded in the log, counted once, and not named as a hidden command
delay (issue 26 item 2)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from falcon_plan.approach import run_from_here
from falcon_plan.devices.emulated import UsbTiming
from falcon_plan.discrepancy.checks import (PRACTICAL_MIN_COUNTS, PRACTICAL_MIN_FRACTION, WINDOW_S, practical_gate,
                                            replay_errors, window_gain)
from falcon_plan.discrepancy.excitation import design_trajectory
from falcon_plan.discrepancy.replay import closed_loop_replay, log_controller, transport_delay_samples
from falcon_plan.discrepancy.synth import synthesize_log
from falcon_plan.discrepancy.workflow import find_discrepancy
from falcon_plan.execution.device_factory import open_device
from falcon_plan.execution.safety import SafetyConfig
from falcon_plan.falconlog import LINK_DELAY_KEY, FalconLog, read_log
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import NOMINAL

from .conftest import TRAIN_S

RATE_HZ = 800.0
SAFETY = SafetyConfig(watchdog_timeout_s=0.09)
"""As tests/discrepancy/test_calibration_loop.py: a busy 2-core machine stalls 50 ms now and then."""
RECORD_ATTEMPTS = 3
"""Recordings tried (each on a freshly opened device) before the fixture gives up."""
_logs: dict[str, tuple[FalconLog, FalconLog]] = {}
ONE_LATE = NOMINAL.replace(extra_delay_samples=1)
"""The nominal device with its commands acting one period later."""


def framed_logs(tmp_path_factory) -> tuple[FalconLog, FalconLog]:
    """(training mixed 5 s, held-out fourier 4 s) logs of a nominal emulated Falcon behind
    threaded USB with 1 ms frames (``--usb-timing frames``), recorded as calibrate does."""
    if "frames" not in _logs:
        folder = tmp_path_factory.mktemp("framed")
        model, logs = FalconModel(), []
        for name, kind, seconds, seed in (("train", "mixed", 5.0, 11), ("held", "fourier", 4.0, 23)):
            path = folder / f"{name}.csv"
            for _attempt in range(RECORD_ATTEMPTS):   # a stall on a busy machine trips the watchdog
                with open_device("emulated", rate_hz=RATE_HZ, model=model, usb_timing=UsbTiming()) as dev:
                    report, _ = run_from_here(dev, "emulated", design_trajectory(kind, seconds, seed, RATE_HZ), model,
                                              rate_hz=RATE_HZ, log_path=path, pace=False, safety=SAFETY,
                                              controller_kind="pd")
                if report.status == "completed":
                    break
            assert report.status == "completed", report.reason
            logs.append(read_log(path))
        _logs["frames"] = (logs[0], logs[1])
    return _logs["frames"]


def _with_meta(log: FalconLog, **meta: str) -> FalconLog:
    return FalconLog(log.t_s, log.enc, log.tc, log.ref, {**log.meta, **meta}, *log.timing_columns)


def test_the_log_records_the_link_delay_its_controller_led_by(tmp_path_factory) -> None:
    """The executor's log says the link delay it assumed (2 ms of USB frames = 1.6 periods at
    800 Hz), and the replay's delay is the one the controller's feed-forward led by."""
    train, _ = framed_logs(tmp_path_factory)
    assert float(train.meta[LINK_DELAY_KEY]) == pytest.approx(1.6)
    lead = log_controller(train).feedforward_lead_samples
    assert transport_delay_samples(train, NOMINAL, FalconModel()) == pytest.approx(lead) == pytest.approx(3.6)


def test_a_measured_link_delay_is_counted_once(tmp_path_factory) -> None:
    """A model file carrying doctor's link delay and a log recorded with it: the replay delays
    by the link once; an older log without the entry takes the model's."""
    train, _ = framed_logs(tmp_path_factory)
    doctor = FalconModel(FalconModel().params.replace(link_delay_samples=1.25))
    recorded = _with_meta(train, **{LINK_DELAY_KEY: "1.25"})
    assert transport_delay_samples(recorded, NOMINAL, doctor) == pytest.approx(3.25)
    older = FalconLog(train.t_s, train.enc, train.tc, train.ref,
                      {k: v for k, v in train.meta.items() if k != LINK_DELAY_KEY}, *train.timing_columns)
    assert transport_delay_samples(older, NOMINAL, doctor) == pytest.approx(3.25)
    assert transport_delay_samples(older, NOMINAL, FalconModel()) == pytest.approx(2.0)


@pytest.mark.slow
def test_a_nominal_device_behind_usb_frames_names_no_command_delay(tmp_path_factory) -> None:
    """The nominal device behind the threaded USB path hides nothing: the link's delay the run
    knew is not named as a +2-sample command delay, and the held-out replay is no worse after
    the (empty) correction. (calibrate's longer recordings named a +2-sample command delay
    before the link entered the nominal replay; these short ones do not show it either way.)"""
    train, held = framed_logs(tmp_path_factory)
    report = find_discrepancy(train, held, candidates=["command_delay", "coulomb_friction", "payload_mass"])
    assert "command_delay" not in report.effects, report.effects
    assert report.corrected.extra_delay_samples == 0
    assert report.heldout_after.rms_counts_all <= report.heldout_before.rms_counts_all + 1e-9


def _late_in_windows(log: FalconLog, count: int) -> FalconLog:
    """``log`` with the counts of the ``count`` half-second windows where its one-period-late
    closed-loop replay differs most from it replaced by that replay's (rounded)."""
    rate, spec = float(log.meta["rate_hz"]), log_controller(log)
    enc = np.asarray(log.enc, float)
    late_counts = closed_loop_replay(log, ONE_LATE, FalconModel(), rate, spec)
    t = np.asarray(log.t_s, float)
    window = np.floor((t - t[0]) / WINDOW_S).astype(int)
    per_window = np.bincount(window, np.mean((late_counts - enc) ** 2, axis=1))
    replaced = np.isin(window, np.argsort(per_window)[::-1][:count])
    enc[replaced] = np.round(late_counts[replaced])
    return dataclasses.replace(log, enc=enc.astype(int))


def test_a_delay_that_helps_in_fewer_than_half_the_windows_is_not_kept(nominal_logs) -> None:
    """The rule pairs the windows: a delay is kept by the median of its gains window by window,
    not by the difference of the two replays' medians, which a shuffle of which windows sit in
    the middle can move. The nominal log with just under half of its windows replaced by a
    one-period-late replay's: the late replay's median is lower by the rule's amount, but it
    is worse in most windows, and the delay is dropped. (On a nominal emulated Falcon behind
    framed USB, 2 of 12 recordings named a delay that way: medians 1.73 -> 1.46 counts,
    paired gain -0.02, half the windows better, and the held-out replay 1.54 -> 2.86.)"""
    train, _ = nominal_logs
    model, late = FalconModel(), ONE_LATE
    rate, spec = float(train.meta["rate_hz"]), log_controller(train)
    windows = int(np.floor((train.t_s[-1] - train.t_s[0]) / WINDOW_S)) + 1
    shuffled = _late_in_windows(train, windows // 2)

    on_time, one_late = (replay_errors(shuffled, e, model, rate, spec) for e in (NOMINAL, late))
    median_gain = on_time.window_median - one_late.window_median
    assert median_gain >= max(PRACTICAL_MIN_COUNTS, PRACTICAL_MIN_FRACTION * on_time.window_median)
    assert np.mean(on_time.windows > one_late.windows) < 0.5
    _, kept, gate = practical_gate(shuffled, model, rate, spec, late, ["command_delay"])
    assert kept == [] and gate.dropped == ["command_delay"]
    assert gate.window_gains["command_delay"] == pytest.approx(window_gain(on_time, one_late))
    assert gate.window_gains["command_delay"] <= 0


def test_a_delay_seen_in_one_stretch_only_is_not_kept(nominal_logs) -> None:
    """A command delay acts on every command: the practical rule keeps it by the median over
    half-second windows of the training replay, not by the RMS that one stretch can carry. The
    nominal log with the counts of one window replaced by a one-period-late replay's (a loop
    ringing there, as the paper's PD does behind framed USB at the 8 Hz reversals) keeps no
    delay, although that window alone lowers the whole RMS by the rule; a log recorded with
    the delay throughout keeps it."""
    train, _ = nominal_logs
    model, late = FalconModel(), ONE_LATE
    rate, spec = float(train.meta["rate_hz"]), log_controller(train)
    one_stretch = _late_in_windows(train, 1)
    _, kept, gate = practical_gate(one_stretch, model, rate, spec, late, ["command_delay"])
    assert kept == [] and gate.dropped == ["command_delay"]
    assert gate.gains["command_delay"] >= max(PRACTICAL_MIN_COUNTS, PRACTICAL_MIN_FRACTION * gate.train_replay_rms)
    assert gate.window_gains["command_delay"] < 0

    throughout = synthesize_log(late, design_trajectory("mixed", TRAIN_S, seed=11), seed=11)
    _, kept, _ = practical_gate(throughout, model, rate, spec, late, ["command_delay"])
    assert kept == ["command_delay"]


def test_a_late_delay_is_named_only_beyond_three_quarters_of_a_period() -> None:
    """Devices with no extra delay were fitted half a period late on busy-host logs; devices with
    two extra periods 1.6-2.0 late. A kept fit names a command delay only from 0.75 periods
    later than the run assumed, on a log that records the link delay its controller led by."""
    from falcon_plan.discrepancy.checks import LATE_NAMED_MIN_PERIODS, DelayFit, later_than_assumed

    assert LATE_NAMED_MIN_PERIODS == pytest.approx(0.75)
    log = FalconLog(np.arange(3) / 1000.0, np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)),
                    {LINK_DELAY_KEY: "2"})

    def late(value: float, kept: bool = True) -> float | None:
        return later_than_assumed(DelayFit(value, 0.6, 0.5, kept, 4.0), log)

    assert late(4.5) is None and late(4.74) is None
    assert late(4.75) == pytest.approx(0.75) and late(5.8) == pytest.approx(1.8)
    assert late(5.8, kept=False) is None                                   # not kept: not named
    assert later_than_assumed(DelayFit(5.8, 0.6, 0.5, True, 4.0),
                              FalconLog(log.t_s, log.enc, log.tc, log.ref, {})) is None   # no link record
