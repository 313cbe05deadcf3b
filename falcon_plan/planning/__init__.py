"""Minimum-time planning: problems, the CasADi planner, cross-checks, trajectories."""
