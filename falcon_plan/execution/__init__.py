"""Streaming trajectories to a device and measuring how well they are tracked."""
