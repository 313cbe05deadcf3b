"""Recordings that robotics tools open: MCAP files and a live Foxglove view of runs.

- :mod:`~falcon_plan.recording.channels`: the topics, their JSON Schemas (Foxglove's
  well-known ones where one fits) and the messages made from falcon-log rows;
- :mod:`~falcon_plan.recording.mcapfile`: the one MCAP writer (chunked, finished on every exit
  path), the one reader (an MCAP recording read back as a FalconLog), the converter;
- :mod:`~falcon_plan.recording.recorder`: :class:`RunRecorder`, the executor's row sink (a row
  into a shared-memory ring in the loop: :mod:`~falcon_plan.recording.ring`), and
  :class:`RecorderProcess`, the recording process that does the work
  (:mod:`~falcon_plan.recording.worker`);
- :mod:`~falcon_plan.recording.live`: :class:`LiveView`, the Foxglove WebSocket server (in a
  recording process).

``falcon_plan.falconlog.read_log`` and ``write_log`` read and write MCAP recordings as they do
CSV falcon logs (by the file's magic bytes, and a ``.mcap`` name), so every command that reads
a falcon log reads a recording.
"""
from falcon_plan.recording.mcapfile import McapRecording, copy_recording, read_mcap, write_mcap_log
from falcon_plan.recording.recorder import RecorderProcess, RunRecorder, open_recorder

__all__ = ["McapRecording", "RecorderProcess", "RunRecorder", "copy_recording", "open_recorder", "read_mcap", "write_mcap_log"]
