"""Pictures of plans and runs (matplotlib PNGs, no pyplot state: safe in threads and servers).

- :func:`plot_plan`: a planned trajectory: position, velocity, leg angles against their
  allowed range, leg speeds, commands against the limit, workspace margins.
- :func:`plot_run`: a falcon log with its reference: reference against measured counts,
  tracking error per leg [counts] and in the base frame [mm], commands against the limit.
- :func:`plot_gains`: the tracking LQR's gains along a plan (:class:`falcon_plan.lqr.GainSchedule`).

Units follow the command line: positions in mm, times in ms (plans) or s (runs).
"""
from __future__ import annotations

from falcon_plan.plots.plan import plot_plan
from falcon_plan.plots.gains import plot_gains
from falcon_plan.plots.run import plot_run

__all__ = ["plot_gains", "plot_plan", "plot_run"]
