"""The workspace guard's compiled per-tick path against the batch workspace check."""
from __future__ import annotations

import numpy as np
import pytest

from falcon_plan.errors import SafetyStop
from falcon_plan.execution.safety import WorkspaceGuard
from falcon_plan.model.kinematics import counts_to_position, position_to_counts
from falcon_plan.model.workspace import check_workspace


def test_compiled_guard_agrees_with_the_batch_check_along_a_path_in_and_out(model):
    slack = np.radians(2.0)
    guard = WorkspaceGuard(model.params, model.limits, slack)
    assert guard.compiled
    # a straight walk in counts from the centre to far beyond the leg-angle range and back
    centre = position_to_counts(np.array([0.0, 0.0, 0.13]), model.params)
    far = centre + np.array([2000.0, -300.0, 200.0])
    s = np.concatenate([np.linspace(0, 1, 400), np.linspace(1, 0, 400)])
    counts = np.rint(centre + s[:, None] * (far - centre))
    truth_p = counts_to_position(counts, model.params)
    inside = check_workspace(truth_p, model.params, model.limits.scaled(-slack)).inside
    assert 100 < inside.sum() < 700          # both kinds are on the path
    for c, p, ok in zip(counts, truth_p, inside):
        if ok:
            np.testing.assert_allclose(guard.check(c), p, atol=1e-9)
        else:
            with pytest.raises(SafetyStop, match="left the workspace"):
                guard.check(c)
    assert guard.fast_checks >= 0.9 * inside.sum()   # the compiled path answered the ticks
