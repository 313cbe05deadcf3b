"""EncoderPD: the conventions' PD law, filter, rounding and clamp."""
from __future__ import annotations

import math

import numpy as np
import pytest

from falcon_plan.errors import InvalidParameterError
from falcon_plan.control import EncoderPD, velocity_filter_alpha


def test_alpha_is_the_50hz_first_order_low_pass() -> None:
    assert velocity_filter_alpha(800.0) == pytest.approx(1 - math.exp(-2 * math.pi * 50 / 800))
    assert EncoderPD(1000.0).alpha == pytest.approx(1 - math.exp(-math.pi / 10))


def test_first_update_has_no_derivative_kick_and_is_proportional() -> None:
    pd = EncoderPD(800.0)
    tc = pd.update([10, -20, 0], [0.0, 0.0, 0.25])
    assert tc.dtype == np.int64
    assert tc.tolist() == [100, -200, -2]  # round half up of -2.5 is -2


def test_velocity_is_the_filtered_first_difference() -> None:
    pd = EncoderPD(800.0, kp=0.0, kd=1.0)
    pd.update([0, 0, 0], [0, 0, 0])
    alpha = pd.alpha
    v = 0.0
    for k in range(1, 6):  # a ramp of 1 count per period: raw velocity 800 counts/s
        tc = pd.update([k, 0, -k], [0, 0, 0])
        v += alpha * (800.0 - v)
        assert pd.velocity_counts_s[0] == pytest.approx(v)
        assert tc[0] == math.floor(v + 0.5) and tc[2] == math.floor(-v + 0.5)


def test_feedforward_adds_and_the_output_is_clamped() -> None:
    pd = EncoderPD(800.0)
    assert pd.update([0, 0, 0], [0, 0, 0], [12.4, -7.6, 0]).tolist() == [12, -8, 0]
    assert pd.update([1000, -1000, 0], [0, 0, 0]).tolist()[:2] == [4096, -4096]


def test_reset_and_metadata() -> None:
    pd = EncoderPD(1000.0, kp=12.0, kd=0.05)
    pd.update([5, 5, 5], [0, 0, 0])
    pd.reset()
    assert pd.n_prev is None and not pd.velocity_counts_s.any()
    assert pd.metadata == "pd kp=12 kd=0.05"


def test_rejects_bad_values() -> None:
    with pytest.raises(InvalidParameterError):
        EncoderPD(0.0)
    with pytest.raises(InvalidParameterError):
        EncoderPD(800.0, limit=5000)
    with pytest.raises(InvalidParameterError):
        EncoderPD(800.0).update([0, 0, 0], [np.nan, 0, 0])
