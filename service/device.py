"""The service's hold on its device: one :class:`DeviceRunner` per instance.

Only the goal worker thread drives the device (homing, reading the start position,
executing). The runner hands the executor a thin recording proxy of the device, so every
reading of every tick is kept as the latest state for the state publisher, whatever the
executor reports itself. A simulated device does not move between exchanges (its time only
advances when driven), so it is not polled while idle; a real (or emulated) one is read with
zero force at the state rate so its state stays current.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Protocol

import numpy as np

from falcon_plan.errors import InvalidParameterError, KinematicsError

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device
    from falcon_plan.execution.executor import ExecutionReport
    from falcon_plan.falconlog import FalconLog
    from falcon_plan.model.params import FalconParams
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.trajectory import Trajectory

log = logging.getLogger(__name__)

DEVICE_KINDS = ("sim", "emulated", "usb", "none")
"""Values of ``serve --device``; ``none`` makes a planning-only instance."""


class ExecutorLike(Protocol):
    """What the runner needs from an executor (``falcon_plan.execution.executor.Executor``):
    ``run`` follows ``trajectory`` until done or ``cancel`` is set, calling ``progress``."""

    def run(self, trajectory: Trajectory, cancel: threading.Event | None = None,
            progress: Callable[..., None] | None = None) -> ExecutionReport: ...


ExecutorFactory = Callable[[Any, Any, Any], ExecutorLike]
"""``factory(device, log_path, sink) -> executor``: builds the executor for a run on
``device`` that writes its falcon log to ``log_path`` (a Path) and also hands its rows to
``sink`` (an executor RowSink, e.g. a recorder; None: none)."""

RUN_MAX_SAMPLES = 1000
"""A goal's run record keeps at most this many samples (every k-th row of its falcon log)."""


class _DropMessagesNaming(logging.Filter):
    """A log filter dropping the records whose message contains ``text``."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.text = text

    def filter(self, record: logging.LogRecord) -> bool:
        return self.text not in record.getMessage()


def run_record(log: FalconLog, max_samples: int = RUN_MAX_SAMPLES) -> dict[str, Any]:
    """The falcon log of a run in short, for the goal result's ``run``: every k-th sample
    (k the smallest giving at most ``max_samples``) of ``t_s`` [s], ``enc``, ``ref`` [counts]
    and ``tc`` [command units], and the log's metadata; :func:`run_log` reads it back."""
    step = max(1, -(-len(log.t_s) // max_samples))
    rows = slice(None, None, step)
    return {"t_s": log.t_s[rows].tolist(), "enc": log.enc[rows].tolist(), "tc": log.tc[rows].tolist(),
            "ref": None if log.ref is None else log.ref[rows].tolist(), "every": step, "meta": dict(log.meta)}


def run_log(record: dict[str, Any]) -> FalconLog:
    """The FalconLog of a goal result's ``run`` record (:func:`run_record`)."""
    from falcon_plan.falconlog import FalconLog

    ref = record.get("ref")
    return FalconLog(np.asarray(record["t_s"], float), np.asarray(record["enc"], np.int64),
                     np.asarray(record["tc"], np.int64), None if ref is None else np.asarray(ref, float),
                     {str(k): str(v) for k, v in record.get("meta", {}).items()})


@dataclass(frozen=True)
class StateSnapshot:
    """The latest reading: counts (3 ints), buttons, per-leg homed flags, and the wall time
    ``wall_t_s`` it was taken [s, UNIX]; ``position_m`` by forward kinematics (None if it
    failed)."""

    counts: tuple[int, int, int]
    buttons: int
    homed: tuple[bool, bool, bool]
    wall_t_s: float
    position_m: tuple[float, float, float] | None


class RunFeedback:
    """A row sink in front of another, ``inner`` (or of none), that keeps the last row's feedback for the
    progress of a running goal: the tracking error |measured - planned| [mm] and the command
    margin, ``limit`` less the largest |command| [command units]."""

    def __init__(self, inner: Any = None) -> None:
        self.inner = inner
        self.limit = 0.0
        self._last: tuple[float, float] | None = None

    def start(self, meta: dict[str, str], model: Any) -> None:
        """Pass the run's start (``meta``, ``model``) on."""
        if self.inner is not None:
            self.inner.start(meta, model)

    def row(self, t_s: float, enc: Any, tc: Any, ref: Any, measured_m: Any, planned_m: Any, timing: Any) -> None:
        """Keep the row's feedback (a few microseconds: ``measured_m`` against ``planned_m``, the
        commands ``tc``) and pass the row (``t_s``, ``enc``, ``ref``, ``timing`` too) on."""
        error_mm = 1e3 * float(np.linalg.norm(np.subtract(measured_m, planned_m)))
        self._last = (error_mm, float(self.limit - np.abs(tc).max()))
        if self.inner is not None:
            self.inner.row(t_s, enc, tc, ref, measured_m, planned_m, timing)

    def finish(self, report: Any) -> None:
        """Pass the run's end (its ``report``) on."""
        if self.inner is not None:
            self.inner.finish(report)

    def now(self) -> dict[str, float]:
        """The last row's ``tracking_error_mm`` and ``command_margin`` (empty before the first row)."""
        last = self._last
        return {} if last is None else {"tracking_error_mm": last[0], "command_margin": last[1]}


class _RecordingDevice:
    """Delegates everything to the device and records each reading with the runner."""

    def __init__(self, device: Device, record: Callable[[Any], None]) -> None:
        self._device = device
        self._record = record

    def exchange(self, commands: Any, leds: int = 0) -> Any:
        """One tick on the real device; the reading is recorded, then returned."""
        reading = self._device.exchange(commands, leds)
        self._record(reading)
        return reading

    def __getattr__(self, name: str) -> Any:
        return getattr(self._device, name)

    def __enter__(self) -> "_RecordingDevice":
        return self

    def __exit__(self, *exc: Any) -> None:
        """The runner owns the device's lifetime: leaving a run does not close it."""


def _progress_dict(args: tuple[Any, ...]) -> dict[str, Any]:
    """The executor's ``progress(done, total)`` call (sample counts) as a dict."""
    if len(args) == 2 and all(isinstance(a, (int, np.integer)) for a in args):
        return {"samples_done": int(args[0]), "samples_total": int(args[1])}
    return _to_dict(args[0]) if len(args) == 1 else {"values": [repr(a) for a in args]}


def _to_dict(value: Any) -> dict[str, Any]:
    """A report or progress value as a JSON-ready dict."""
    if hasattr(value, "to_dict"):
        return value.to_dict()
    if isinstance(value, dict):
        return value
    if isinstance(value, (int, float)):
        return {"value": float(value)}
    return {"value": repr(value)}


class DeviceRunner:
    """Owns one opened device and runs trajectories on it (from one thread at a time).

    Parameters
    ----------
    device : a :class:`falcon_plan.devices.base.Device` (opened by :meth:`open`).
    executor_factory : builds the executor for each run.
    kind : "sim", "emulated" or "usb" (for the state and info bodies).
    poll_when_idle : read the device with zero force while idle (see the module docstring).
    params : the kinematic parameter set for counts -> position.
    home_timeout_s : longest wait for homing before a goal [s].
    """

    def __init__(self, device: Device, executor_factory: ExecutorFactory, kind: str, *,
                 poll_when_idle: bool | None = None, params: FalconParams | None = None, home_timeout_s: float = 30.0) -> None:
        if kind not in DEVICE_KINDS or kind == "none":
            raise InvalidParameterError(f"device kind must be one of {DEVICE_KINDS[:-1]}, got {kind!r}")
        from falcon_plan.model.params import ACRA2009

        self.device = device
        self.kind = kind
        self.poll_when_idle = (kind != "sim") if poll_when_idle is None else poll_when_idle
        self.home_timeout_s = home_timeout_s
        self._executor_factory = executor_factory
        self._params = params if params is not None else ACRA2009
        # counts -> position, warm-started from the previous reading (only its FK is used)
        from falcon_plan.model.kinematics import PositionTracker  # loaded with the runner, not with the CLI

        self._kinematics = PositionTracker(self._params)
        self.is_open = False
        self._lock = threading.Lock()
        self._latest: Any = None
        self._latest_wall = 0.0
        self._snapshot: StateSnapshot | None = None

    # --- lifetime ---------------------------------------------------------------------------
    def open(self) -> None:
        """Open the device and take a first reading (zero force)."""
        self.device.open()
        self.is_open = True
        self.poll()

    def close(self) -> None:
        """Close the device (it leaves zero force); never raises."""
        self.is_open = False
        try:
            self.device.close()
        except Exception:  # noqa: BLE001 - shutdown must go on
            log.exception("closing the device failed")

    # --- readings ---------------------------------------------------------------------------
    def _record(self, reading: Any) -> None:
        with self._lock:
            self._latest = reading
            self._latest_wall = time.time()
            self._snapshot = None

    def poll(self) -> None:
        """One zero-force tick to refresh the latest reading."""
        self._record(self.device.exchange([0, 0, 0]))

    def snapshot(self) -> StateSnapshot | None:
        """The latest reading with its position (computed once per reading), or None."""
        with self._lock:
            if self._snapshot is not None or self._latest is None:
                return self._snapshot
            reading, wall = self._latest, self._latest_wall
        try:  # scalar FK, warm-started from the last position (~10 us)
            position: tuple[float, float, float] | None = tuple(
                float(v) for v in self._kinematics.position(reading.counts))
        except KinematicsError:  # a reading outside the FK's reach still has counts
            position = None
        snap = StateSnapshot(tuple(int(c) for c in reading.counts), int(reading.buttons),
                             tuple(bool(h) for h in reading.homed), wall, position)
        with self._lock:
            if self._latest is reading:
                self._snapshot = snap
        return snap

    def position_m(self) -> tuple[float, float, float]:
        """Where the end effector is now [m] (reads the device first if it is polled)."""
        if self.poll_when_idle or self.snapshot() is None:
            self.poll()
        snap = self.snapshot()
        if snap is None or snap.position_m is None:
            from falcon_plan.errors import DeviceError

            counts = None if snap is None else list(snap.counts)
            raise DeviceError(f"the device's position cannot be computed from its encoder counts {counts} (forward "
                              "kinematics has no solution: the grip is against its stops, or the device is not "
                              "homed): move the grip into the workspace and send the goal again")
        return snap.position_m

    def require_start(self, position_m: tuple[float, float, float]) -> None:
        """Raise ``outside_workspace`` (a RequestError) when the device's ``position_m`` [m] is
        outside the workspace, where no goal can start (a released real Falcon sags onto its
        stops): where it is, why, and what to do."""
        from falcon_plan.errors import WorkspaceError
        from falcon_plan.model.workspace import require_in_workspace
        from service.codec import RequestError

        try:
            require_in_workspace(position_m, self._params, what="the device's position")
        except WorkspaceError as exc:
            raise RequestError("outside_workspace", f"{exc}; a goal starts where the device is: move the grip into "
                               "the workspace and send the goal again", field="start_m",
                               allowed="a device inside the workspace") from None

    # --- running ----------------------------------------------------------------------------
    def ensure_homed(self) -> None:
        """Home the device if it is not homed yet (blocks up to ``home_timeout_s``)."""
        if not self.device.homed:
            log.info("homing the %s device", self.kind)
            self.device.home(self.home_timeout_s)
            self.poll()

    def execute(self, trajectory: Trajectory, cancel: threading.Event,
                progress: Callable[[dict[str, Any]], None], sink: Any = None,
                release: bool = False, *, progress_period_s: float | None = None,
                splices: Callable[[Any], Any] | None = None) -> tuple[dict[str, Any], dict[str, Any] | None]:
        """Run ``trajectory`` to the end or until ``cancel`` is set; returns the executor's
        report as a dict and the run's falcon log in short (:func:`run_record`; None when no
        sample was logged). ``progress`` gets each executor progress call as a dict
        (``samples_done``, ``samples_total``, the sample where the trajectory starts after the
        pre-roll, ``motion_start_sample``, and the loop's ``rate_hz``); ``sink`` (an executor RowSink, e.g. the goal's
        recorder, or None) gets every row; ``release``: a cancel drops to zero force at once
        instead of the executor's safe stop (brake to rest, hold); ``progress_period_s``: how
        often ``progress`` is called [s of loop time] (None: the executor's default), each
        call with the run's feedback (:class:`RunFeedback`: tracking error, command margin);
        ``splices(executor) -> SpliceSlot | None`` is called with the executor before the run
        (to replan it while it goes: :class:`falcon_plan.execution.splice.SpliceCoordinator`)."""
        import tempfile
        from pathlib import Path

        from falcon_plan.errors import LogFormatError
        from falcon_plan.falconlog import read_log

        with tempfile.TemporaryDirectory(prefix="falcon-goal-") as folder:
            log_path = Path(folder) / "run.csv"
            feedback = RunFeedback(sink)
            executor = self._executor_factory(_RecordingDevice(self.device, self._record), log_path, feedback)
            executor.release = bool(release)
            feedback.limit = executor.controller.command_limit
            if progress_period_s is not None:
                executor.progress_period_s = float(progress_period_s)
            slot = splices(executor) if splices is not None else None
            timing = {"motion_start_sample": executor.plan_start_tick(), "rate_hz": float(executor.rate_hz)}
            report = executor.run(trajectory, cancel=cancel, splices=slot,
                                  progress=lambda *a: progress({**_progress_dict(a), **timing, **feedback.now()}))
            # its gaps (missed deadlines) are in the report already: no warning naming a temporary file
            quiet = _DropMessagesNaming(folder)
            logging.getLogger("falcon_plan.falconlog").addFilter(quiet)
            try:
                run = run_record(read_log(log_path)) if log_path.exists() else None
            except LogFormatError:  # a run stopped before its first sample
                run = None
            finally:
                logging.getLogger("falcon_plan.falconlog").removeFilter(quiet)
        body = _to_dict(report)
        body["log_path"] = None  # the log was temporary: the result carries it as "run"
        return body, run


def make_runner(kind: str, model: FalconModel | None = None, *, firmware_path: str | None = None,
                controller: str = "lqr") -> DeviceRunner | None:
    """The runner for ``serve --device KIND`` (``kind``; None for ``none``), executing with
    ``model`` (nominal if None) under the tracking ``controller`` ("lqr" or "pd", the
    Executor's ``kind``).

    ``sim``: the simulated plant at 800 Hz (the paper's rate); ``emulated``: the real USB
    driver over the emulated pyusb backend (the whole USB path, no hardware) at 1 kHz, in
    wall-clock time with its released grip held between goals (:class:`~falcon_plan.devices.emulated.UsbTiming`);
    ``usb``: the real Falcon at 1 kHz (firmware already running unless ``firmware_path`` is
    given). Devices come from :func:`falcon_plan.execution.device_factory.open_device` with
    their own pacing off; the executor paces every run to wall-clock deadlines, once, so a
    goal on the simulated device takes as long as it would on the real one.
    """
    if kind not in DEVICE_KINDS:
        raise InvalidParameterError(f"device must be one of {DEVICE_KINDS}, got {kind!r}")
    if kind == "none":
        return None
    from falcon_plan.commands.common import DEFAULT_RATE_HZ, FRAME_RATE_HZ
    from falcon_plan.execution.device_factory import open_device
    from falcon_plan.execution.executor import Executor
    from falcon_plan.model.dynamics import FalconModel

    model = model if model is not None else FalconModel()
    # a simulated device is the nominal world: the model's effects are the controller's belief
    rate_hz = DEFAULT_RATE_HZ if kind == "sim" else FRAME_RATE_HZ       # a USB device moves in 1 ms frames
    timing = None
    if kind == "emulated":
        # the emulated Falcon keeps wall-clock time, as a real one does, and its released grip is
        # held still between goals, as a user holds a real one: stepped once per idle state poll
        # instead, its grip fell onto its stops within seconds and no goal could start there
        from falcon_plan.devices.emulated import UsbTiming

        timing = UsbTiming(clock="wall", released_grip="held")
    device = open_device(kind, rate_hz=rate_hz, model=FalconModel(model.params),
                         firmware=firmware_path, firmware_running=firmware_path is None, usb_timing=timing)
    return DeviceRunner(device, lambda dev, log_path, sink: Executor(dev, model, log_path=log_path, pace=True,
                                                                     controller_kind=controller, sink=sink),
                        kind, params=model.params)
