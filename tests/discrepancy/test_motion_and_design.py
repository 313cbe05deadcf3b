"""Motion estimation from counts, excitation designs, and metadata errors."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.discrepancy.excitation import KINDS, design_trajectory
from falcon_plan.discrepancy.motion import estimate_motion, log_rate_hz, motion_phases, PHASES
from falcon_plan.errors import InvalidParameterError, LogFormatError
from falcon_plan.falconlog import FalconLog
from falcon_plan.model.workspace import in_workspace


@pytest.mark.parametrize("kind", KINDS)
def test_designs_stay_in_workspace_and_start_and_end_at_rest(kind: str) -> None:
    traj = design_trajectory(kind, 3.0, seed=5, rate_hz=800.0)
    assert in_workspace(traj.position_m).all()
    assert np.allclose(traj.position_m[0], traj.position_m[-1], atol=1e-9)
    assert np.abs(traj.velocity_m_s[:200]).max() < 1e-9
    assert np.abs(traj.velocity_m_s).max() > 0.02          # it does move
    other = design_trajectory(kind, 3.0, seed=6, rate_hz=800.0)
    assert not np.allclose(traj.position_m, other.position_m)


def test_unknown_kind_is_a_clear_error() -> None:
    with pytest.raises(InvalidParameterError, match="fourier"):
        design_trajectory("chirp")


def test_motion_estimate_recovers_velocity_from_whole_counts() -> None:
    """Counts of a known motion, rounded: the estimated velocity matches the true one to a
    small fraction of its range."""
    traj = design_trajectory("fourier", 4.0, seed=2, rate_hz=800.0)
    counts = np.rint(traj.counts).astype(np.int64)
    log = FalconLog(traj.t_s, counts, np.zeros_like(counts), traj.counts, {"rate_hz": "800"})
    motion = estimate_motion(log)
    sel = motion.valid
    err = motion.velocity_m_s[sel] - traj.velocity_m_s[sel]
    assert np.sqrt(np.mean(err ** 2)) < 0.02 * np.abs(traj.velocity_m_s).max()
    labels = motion_phases(motion)
    assert set(np.unique(labels)) <= set(PHASES) and "hold" in set(labels[:, 0])


def test_gaps_split_runs_and_are_left_out() -> None:
    traj = design_trajectory("holds", 2.0, seed=2, rate_hz=800.0)
    counts = np.rint(traj.counts).astype(np.int64)
    keep = np.ones(len(traj.t_s), dtype=bool)
    keep[1000:1005] = False                                  # five lost packets
    log = FalconLog(traj.t_s[keep], counts[keep], np.zeros_like(counts[keep]), None, {"rate_hz": "800"})
    motion = estimate_motion(log)
    assert not motion.valid[995:1005].any() and motion.valid[300:900].all()


def test_rate_comes_from_metadata_or_option() -> None:
    log = FalconLog(np.arange(5) / 800.0, np.zeros((5, 3)), np.zeros((5, 3)), None, {})
    with pytest.raises(LogFormatError, match="--rate"):
        log_rate_hz(log)
    assert log_rate_hz(log, 1000.0) == 1000.0
