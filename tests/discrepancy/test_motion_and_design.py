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


def test_short_gaps_are_bridged_and_long_ones_split_runs() -> None:
    """Issue 26: a few skipped ticks (a busy host) are bridged, the motion across them is
    still right; a gap longer than BRIDGE_S splits the log and its edges are left out."""
    traj = design_trajectory("fourier", 3.0, seed=2, rate_hz=800.0)
    counts = np.rint(traj.counts).astype(np.int64)
    keep = np.ones(len(traj.t_s), dtype=bool)
    keep[1000:1005] = False                                  # five skipped ticks: bridged
    keep[1600:1650] = False                                  # 62 ms lost: split
    log = FalconLog(traj.t_s[keep], counts[keep], np.zeros_like(counts[keep]), None, {"rate_hz": "800"})
    motion = estimate_motion(log)
    rows = np.flatnonzero(keep)
    near_short = (rows >= 960) & (rows < 1045)
    near_long = (rows >= 1560) & (rows < 1690)
    assert motion.valid[near_short].all() and not motion.valid[near_long].any()
    err = motion.velocity_m_s[near_short] - traj.velocity_m_s[rows[near_short]]
    assert np.sqrt(np.mean(err ** 2)) < 0.03 * np.abs(traj.velocity_m_s).max()
    commands, ok = motion.shifted_commands(2.5, smooth=False)   # held through the short gap
    assert ok[near_short].all()


def test_a_log_with_too_many_gaps_says_how_much_is_needed() -> None:
    from falcon_plan.discrepancy.identify import IdentificationError, ResidualProblem
    from falcon_plan.model.dynamics import FalconModel

    traj = design_trajectory("fourier", 3.0, seed=2, rate_hz=800.0)
    counts = np.rint(traj.counts).astype(np.int64)
    keep = (np.arange(len(traj.t_s)) % 100) < 60          # 50 ms lost every 125 ms
    log = FalconLog(traj.t_s[keep], counts[keep], np.zeros_like(counts[keep]), None, {"rate_hz": "800"})
    with pytest.raises(IdentificationError, match=r"identification needs at least 80 \(0.10 s\).*gap longer than 25 ms"):
        ResidualProblem(FalconModel(), estimate_motion(log), 2.5)


def test_rate_comes_from_metadata_or_option() -> None:
    log = FalconLog(np.arange(5) / 800.0, np.zeros((5, 3)), np.zeros((5, 3)), None, {})
    with pytest.raises(LogFormatError, match="--rate"):
        log_rate_hz(log)
    assert log_rate_hz(log, 1000.0) == 1000.0


def test_the_reversals_design_takes_every_legs_load_through_zero() -> None:
    """Issue 26: gravity keeps every leg's load on one side through the smooth designs, so a
    training log of them never crosses the cable's slop. In the ``reversals`` design every
    leg's nominal command (the model's inverse dynamics) swings through zero again and again,
    within the command saturation; the smooth designs change no sign."""
    from falcon_plan.model.dynamics import FalconModel

    saturation = FalconModel().params.command_saturation
    sign_changes = lambda c: (np.diff(np.sign(c), axis=0) != 0).sum(axis=0)  # noqa: E731
    for seed in (11, 12):
        reversals = design_trajectory("reversals", 1.0, seed=seed, rate_hz=1000.0)
        assert (sign_changes(reversals.commands) >= 8).all()
        assert np.abs(reversals.commands).max() < 0.8 * saturation
        for kind in ("sweep", "fourier"):
            assert (sign_changes(design_trajectory(kind, 6.0, seed=seed, rate_hz=1000.0).commands) == 0).all()
