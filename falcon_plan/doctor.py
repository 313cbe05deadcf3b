"""``falcon-plan doctor --device usb|emulated``: first contact with a Falcon, step by step.

In the spirit of libnifalcon's ``findfalcons`` and test tools, for a new owner. Each step is
a check that says what it found and, when something is wrong, what to fix:

1. ``usb``: pyusb and a libusb backend, the Falcon on the bus (0403:cb48), a hub in the
   path, permission to open it (the udev rule), the ftdi_sio kernel driver bound to it;
2. ``firmware``: the load, retried with close and reopen (``--load-retries``);
3. ``homing``: the user pulls the grip fully out and pushes it back in;
4. ``encoders``: the homed counts give a point inside the model's workspace;
5. ``reference-loop``: a bare deadline loop at the loop rate doing nothing (how well this
   machine keeps time at all, right now); ``loop-rate``: 1 s of holding the pose
   (encoder-space PD plus the model's gravity compensation) at the loop rate against it;
6. ``command-sign``: per leg, a gentle pulse of +``PULSE`` command units on top of the
   settled holding command must drive the leg angle down (counts down); the dead time of a
   fitted parabola is the command-to-encoder delay;
   ``latency``: a sine of ``PULSE`` command units on each leg (17, 20, 23 Hz) during 1 s of
   the hold; from each leg's phase at its frequency, against a held-command double
   integrator, the command-to-reading delay as the loop sees it, in fractional samples (the
   device's own 2 plus the USB path's frames); written with the model into
   ``doctor-model.json`` (``params.link_delay_samples``) for ``--model``;
7. ``encoder-direction``: zero force for at most ``STEP_S`` (gravity is an outside
   reference): the legs must accelerate the way the model's forward dynamics predicts, by
   about as much;
8. ``static-check``: two short tours of poses (``train`` and ``heldout``, quintic moves
   with feed-forward) followed by the paper's PD without a pause from the holding loop,
   holding each pose; the mean command while holding is compared with the model's gravity
   compensation there (the paper's static check). Their falcon logs are what
   ``falcon-plan discrepancy TRAIN --heldout HELDOUT`` takes. (Tours and their counts are
   computed before any force is applied: computing while holding would stall the loop.)

Every move is bounded (pulses and a fall of at most 50 ms, poses 15-20 mm from the start) and
the device is left at zero force on every exit. All force goes through
:class:`~falcon_plan.execution.paced.PacedLoop`, with the executor's per-tick guards (an
implausible encoder step or a reading outside the workspace stops the moves). The emulated device has real USB timing
(1 ms frames, FTDI latency) and uses the threaded I/O, as the real one does.

Writes ``doctor-report.json``, ``doctor-report.txt``, the falcon logs ``doctor-train.csv``,
``doctor-heldout.csv`` and the model file ``doctor-model.json`` into ``--out``. Exit code: 0
when no check failed, 1 otherwise (a failed step stops the ones that need it), 2 on bad usage.
"""
from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from falcon_plan.errors import FalconPlanError

if TYPE_CHECKING:
    from falcon_plan.devices.base import Device
    from falcon_plan.devices.emulated import FaultPlan
    from falcon_plan.devices.usb_falcon import UsbFalcon
    from falcon_plan.falconlog import LogWriter
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.trajectory import Trajectory

STATUSES = ("ok", "warn", "fail", "skipped")
"""Outcome of a check."""
PULSE = 400
"""Command pulse of the sign check [command units] (gravity compensation is ~1000-2000)."""
STEP_S = 0.05
"""Longest command step of the sign and direction checks (a pulse, zero force) [s]; each
stops earlier once a leg moved ``PULSE_STOP_COUNTS`` (sign) or 20 counts (direction)."""
PULSE_STOP_COUNTS = 25
BASELINE_S = 0.03
"""Open-loop hold before each step, whose trend the step's motion is measured against [s]."""
SETTLE_S = 1.0
"""PD hold before each step (the paper's PD rings for about a second) [s]."""
MOTION_COUNTS = 2
"""A leg counts as moving once it is this far from its trend [counts]."""
STATIC_TOLERANCE = (150.0, 0.2)
"""Holding command vs model: ok within max(abs, rel x |model|) [command units, -]."""
TOURS = {"train": ((0.0, 0.0, 0.02), (0.0, 0.02, 0.0), (0.02, 0.0, 0.0)),
         "heldout": ((-0.02, 0.0, 0.0), (0.0, -0.015, 0.01), (0.015, 0.015, -0.01))}
"""Poses of the static-check tours, relative to the start [m]."""
DOCTOR_WATCHDOG_S = 0.1
"""The bound of the watchdogs during the doctor, the device's and its force loop's [s]: the
widest allowed (``safety.WATCHDOG_MAX_S``), since a first run often happens on a busy desktop
and the moves are gentle (with the executor's 50 ms, a test run was stopped by 55 ms stalls
three times in a row on this shared machine)."""
HOLD_S = 0.8
"""Hold at each pose [s]; the mean command is taken over its second half."""


@dataclass
class Check:
    """One check.

    Attributes
    ----------
    name : the step's name (``usb``, ``firmware``, ``homing``, ..., ``static-check``).
    status : one of :data:`STATUSES`.
    detail : what was found, one line.
    fix : how to fix it ('' when nothing is wrong).
    figures : the measured values, JSON-ready, by name (units in the names).
    """

    name: str
    status: str
    detail: str
    fix: str = ""
    figures: dict[str, Any] = field(default_factory=dict)

    def line(self) -> str:
        """The check as human-readable lines."""
        text = f"[{self.status.upper():^7}] {self.name}: {self.detail}"
        return text + (f"\n          fix: {self.fix}" if self.fix else "")


@dataclass
class DoctorReport:
    """Every check in order and the files written.

    Attributes
    ----------
    device : the device kind checked (``usb`` or ``emulated``).
    checks : the checks, in the order they ran.
    files : path of each file written, by role (``report``, ``text``, ``falcon_log_train``,
        ``falcon_log_heldout``, ``model``).
    """

    device: str
    checks: list[Check] = field(default_factory=list)
    files: dict[str, str] = field(default_factory=dict)

    @property
    def failed(self) -> bool:
        """True if any check failed."""
        return any(c.status == "fail" for c in self.checks)

    def add(self, check: Check) -> Check:
        self.checks.append(check)
        return check

    def to_dict(self) -> dict[str, Any]:
        return {"device": self.device, "failed": self.failed,
                "checks": [asdict(c) for c in self.checks], "files": self.files}

    def text(self) -> str:
        head = f"falcon-plan doctor, device {self.device}: " + \
            ("FAILED" if self.failed else "all checks passed" if all(
                c.status == "ok" for c in self.checks) else "passed with warnings")
        return "\n".join([head, *(c.line() for c in self.checks)]) + "\n"


@dataclass(frozen=True)
class DoctorOptions:
    """What :func:`diagnose` runs against.

    Attributes
    ----------
    device : ``usb`` (a real Falcon) or ``emulated`` (the emulated one, real USB timing).
    out_dir : folder for the report files and the falcon logs (created if needed).
    firmware : firmware image to load; ``None``: a dummy image for the emulated device, and
        for usb the firmware must be running already.
    rate_hz : loop rate [Hz], 800 or 1000.
    load_retries : whole firmware-load attempts (close and reopen between them), >= 1.
    home_timeout_s : how long to wait for the user to home the legs [s].
    moves : apply force (steps 5-8); False stops after the encoders check.
    faults : for the emulated device, the faults it injects (default none).
    backend : a whole pyusb backend to use instead (e.g. an ``EmulatedFalconBackend`` with a
        hub or no device); ``None``: pyusb's own for usb, an emulated Falcon for emulated.
    model : the model the checks compare against and that ``doctor-model.json`` extends with
        the measured delay (e.g. a calibrated one); ``None``: the nominal acra2009 model (the
        emulated Falcon always simulates the nominal one).
    """

    device: str
    out_dir: Path
    firmware: Path | None = None
    rate_hz: float = 1000.0
    load_retries: int = 10
    home_timeout_s: float = 60.0
    moves: bool = True
    faults: FaultPlan | None = None
    backend: Any = None
    model: FalconModel | None = None


# --- step 1: the USB stack -----------------------------------------------------------------
def check_usb(kind: str, backend: Any, report: DoctorReport) -> bool:
    """Find the Falcon through the pyusb ``backend`` (``None``: pyusb's default) and what
    stands in the way, adding the ``usb`` check to ``report``; for ``kind`` ``usb`` also
    the libusb library and the permission of the device node. True if the driver can try to
    open it."""
    from falcon_plan.devices.protocol import FALCON_PID, FALCON_VID
    from falcon_plan.devices.usb_falcon import INSTALL_LIBUSB_HINT, UDEV_RULE_HINT

    try:
        import usb.core
    except ImportError:
        report.add(Check("usb", "fail", "pyusb is not installed", "`pip install pyusb`"))
        return False
    if kind == "usb":
        import usb.backend.libusb1

        if usb.backend.libusb1.get_backend() is None:
            report.add(Check("usb", "fail", "no libusb-1.0 library found", INSTALL_LIBUSB_HINT))
            return False
    found = list(usb.core.find(find_all=True, idVendor=FALCON_VID, idProduct=FALCON_PID,
                               backend=backend))
    if not found:
        report.add(Check("usb", "fail", f"no Falcon on the bus ({FALCON_VID:04x}:{FALCON_PID:04x})",
                         "plug in its USB cable and its power supply; `lsusb` must list "
                         "0403:cb48; connect it directly, not through a hub"))
        return False
    dev = found[0]
    ports = tuple(getattr(dev, "port_numbers", None) or ())
    figures = {"falcons": len(found), "bus": dev.bus, "address": dev.address,
               "port_path": list(ports)}
    notes = [f"{len(found)} Falcon(s); using bus {dev.bus} address {dev.address}"]
    fixes: list[str] = []
    status = "ok"
    if len(found) > 1:
        status = "warn"
        fixes.append("unplug the other Falcons, or expect the first one to be used")
    if len(ports) > 1:
        status = "warn"
        notes.append(f"behind a hub (port path {'.'.join(map(str, ports))})")
        fixes.append("connect the Falcon directly to a port of the computer: firmware loads "
                     "through hubs are reported flaky (libnifalcon issue #33)")
    node = Path(f"/dev/bus/usb/{dev.bus:03d}/{dev.address:03d}")
    if kind == "usb" and node.exists() and not os.access(node, os.R_OK | os.W_OK):
        report.add(Check("usb", "fail", f"no permission to open {node}", UDEV_RULE_HINT, figures))
        return False
    try:
        driver_bound = bool(dev.is_kernel_driver_active(0))
    except (NotImplementedError, usb.core.USBError):
        driver_bound = False
    figures["kernel_driver_bound"] = driver_bound
    if driver_bound:
        status = "warn" if status == "ok" else status
        notes.append("the ftdi_sio kernel driver is bound to it (the driver detaches it)")
        fixes.append("to keep ftdi_sio off the Falcon: a udev rule or `echo 'blacklist "
                     "ftdi_sio' | sudo tee /etc/modprobe.d/falcon.conf` if no other FTDI "
                     "serial device is used")
    import usb.util

    usb.util.dispose_resources(dev)
    report.add(Check("usb", status, "; ".join(notes), "; ".join(fixes), figures))
    return True


# --- the holding loop ----------------------------------------------------------------------
Row = tuple[np.ndarray, np.ndarray]
"""One tick of the holding loop: (counts read, command sent)."""


class Hold:
    """The doctor's force, all of it sent through one
    :class:`~falcon_plan.execution.paced.PacedLoop` (:attr:`loop`: paced at the device's rate,
    with the executor's per-tick guards, zero force on leaving it) to ``device``: holding
    counts ``ref_counts`` with the paper's PD plus the gravity compensation of ``model`` at
    ``position_m`` [m], or sending any command law given to :meth:`run`. A context manager
    (the loop's). The PD's ticks (holding, tracking a tour) are held to the tracking bound
    against their reference as an executor's are; a command law of the caller's is not."""

    def __init__(self, device: Device, model: FalconModel, ref_counts: np.ndarray, position_m: np.ndarray) -> None:
        from falcon_plan.control import EncoderPD
        from falcon_plan.execution.paced import PacedLoop
        from falcon_plan.execution.safety import SafetyConfig

        self.device = device
        self.loop = PacedLoop(device, model, SafetyConfig(watchdog_timeout_s=DOCTOR_WATCHDOG_S))
        self.ref = np.asarray(ref_counts, dtype=float)
        self.gravity = np.asarray(model.holding_commands(position_m), dtype=float)
        self.pd = EncoderPD(rate_hz=device.rate_hz)

    def run(self, ticks: int, command: Callable[[np.ndarray], np.ndarray] | None = None,
            until: Callable[[np.ndarray], bool] | None = None,
            excitation: np.ndarray | None = None) -> list[Row]:
        """``ticks`` paced ticks of the PD hold (plus row i of ``excitation`` (ticks, 3)
        [command units] on tick i, if given), or of ``command(counts)`` if given (stops early
        once ``until(counts)``, read after each tick); returns their (counts read, command
        sent) rows."""
        loop, rows = self.loop, []
        for i in range(ticks):
            slot = loop.wait(loop.slot)
            ff = self.gravity if excitation is None else self.gravity + excitation[i]
            tc = (self.pd.update(loop.counts, self.ref, ff) if command is None
                  else np.asarray(command(loop.counts), dtype=np.int64))
            if command is not None:
                self.pd.update(loop.counts, self.ref, self.gravity)   # keep its filter warm
            rows.append((loop.counts.copy(), tc.copy()))
            loop.send(tc, slot, self.ref if command is None else None)
            loop.slot = slot + 1
            if until is not None and until(loop.counts):
                break
        return rows

    def track(self, ref_counts: np.ndarray, feedforward: np.ndarray, writer: LogWriter) -> int:
        """Follow ``ref_counts`` (n, 3) with the PD plus ``feedforward`` (n, 3), one row per
        period from now, logging each tick's (t, counts, command, ref) to ``writer``; a late
        tick skips to the current row, as the executor does. Returns the rows run."""
        loop = self.loop
        period = 1.0 / self.device.rate_hz
        first = loop.slot
        done = 0
        while True:
            loop.slot = loop.wait(loop.slot)
            k = loop.slot - first
            if k >= len(ref_counts):
                return done
            tc = self.pd.update(loop.counts, ref_counts[k], feedforward[k])
            writer.write(k * period, loop.counts.astype(np.int64), tc, ref_counts[k])
            loop.send(tc, loop.slot, ref_counts[k])
            loop.slot += 1
            done += 1

    def holding_command(self, settle_ticks: int) -> np.ndarray:
        """Hold for ``settle_ticks``; the mean command over the second half [command units]."""
        rows = self.run(settle_ticks)
        return np.mean([tc for _, tc in rows[len(rows) // 2:]], axis=0)

    @property
    def counts(self) -> np.ndarray:
        """The latest reading [counts] (3,)."""
        return self.loop.counts

    def __enter__(self) -> "Hold":
        self.loop.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.loop.__exit__(*exc)


def check_reference_loop(rate_hz: float, report: DoctorReport) -> float:
    """A bare deadline loop for 1 s at ``rate_hz`` [Hz], at zero force, added to ``report``
    as the ``reference-loop`` check; returns its achieved rate [Hz] (ticks per slot)."""
    from falcon_plan.timing import REALTIME_ENV, REALTIME_HINT, realtime_allowed, run_bare_loop

    bare = run_bare_loop(rate_hz, int(rate_hz))
    achieved = bare.ticks / ((bare.ticks + bare.skipped_slots) / rate_hz)
    share = bare.missed_deadlines / max(bare.ticks, 1)
    realtime = realtime_allowed()
    fixes = ["this machine is busy: close other programs before driving the Falcon"] if share > 0.01 else []
    if realtime == "refused":   # a busy neighbour then holds the loop and the USB threads back
        fixes.append(REALTIME_HINT)
    said = {"granted": "at real-time priority", "off": f"real-time priority off ({REALTIME_ENV}=0)",
            "refused": "real-time priority refused: the loop and the USB threads wait behind other programs"}
    report.add(Check("reference-loop", "warn" if fixes else "ok",
                     f"a bare deadline loop ran {achieved:.0f} Hz ({bare.missed_deadlines} "
                     f"missed deadlines, p99 start error {bare.p99_us or 0:.0f} us; {said[realtime]})",
                     "; ".join(fixes), {"rate_hz": achieved, "missed_deadlines": bare.missed_deadlines,
                                        "missed_share": share, "p99_us": bare.p99_us,
                                        "realtime_priority": realtime}))
    return achieved


def check_loop_rate(device: Device, holder: Hold, bare_rate: float, report: DoctorReport) -> None:
    """1 s of holding the pose with ``holder`` on ``device`` against ``bare_rate``, the
    reference loop's rate measured just before force was applied (a pause with force on
    would trip the watchdog) [Hz]; adds the ``loop-rate`` check to ``report``."""
    rate = device.rate_hz
    n = int(rate)
    stats0 = getattr(device, "stats", None)
    statuses0 = stats0.statuses if stats0 is not None else 0
    missed0 = holder.loop.timer.missed_deadlines
    t0 = time.perf_counter()
    holder.run(n)
    wall = time.perf_counter() - t0
    missed = holder.loop.timer.missed_deadlines - missed0
    achieved = n / wall
    figures = {"rate_hz": achieved, "nominal_hz": rate, "missed_deadlines": missed,
               "reference_rate_hz": bare_rate, "ratio_to_reference": achieved / bare_rate}
    if stats0 is not None:
        figures["status_packets_per_s"] = (device.stats.statuses - statuses0) / wall
    status = "ok" if achieved >= 0.95 * rate and missed <= 0.01 * n else \
        "fail" if achieved < 0.5 * rate else "warn"
    fix = "" if status == "ok" else (
        "close other programs, use a power profile without CPU throttling, connect the Falcon "
        "directly; if the reference loop also misses deadlines the machine is busy, not the bus")
    report.add(Check("loop-rate", status,
                     f"{achieved:.0f} Hz over {n} ticks ({missed} missed deadlines), "
                     f"{achieved / bare_rate:.2f} x the reference loop",
                     fix, figures))


LATENCY_HZ = (17.0, 20.0, 23.0)
"""Frequencies of the latency check's sine excitation on legs 0, 1, 2 [Hz]: well above the
holding loop's ~6 Hz, where the leg is a double integrator, and slow enough for a few counts
of motion at ``PULSE``."""
LATENCY_S, LATENCY_LEAD_S = 1.0, 0.3
"""The latency check's analysed window and the lead-in before it (not analysed) [s]."""
LATENCY_SPREAD_WARN = 0.5
"""Legs disagreeing by more than this [samples] make the latency check a warning."""
ONSET_RESOLUTION = 0.01
"""Grid step of the dead time searched by :func:`fit_onset` [ticks]."""


def fit_onset(deviation: Any) -> tuple[float, float] | None:
    """Dead time and acceleration of a motion from rest: the least-squares fit of
    ``0.5 a (k - d)^2`` for k > d (zero before) to a leg's deviation from its trend after a
    command step, samples k = 1, 2, ...; d is fractional (searched on a grid of
    :data:`ONSET_RESOLUTION`). Returns (d [ticks], a [counts/tick^2]), or None if it never
    moves ``MOTION_COUNTS``."""
    y = np.asarray(deviation, dtype=float)
    if y.size < 3 or np.abs(y).max() < MOTION_COUNTS:
        return None
    k = np.arange(1, y.size + 1, dtype=float)
    steps = int(round(1.0 / ONSET_RESOLUTION))
    dead = np.arange((y.size - 2) * steps + 1) / steps               # integers land exactly
    x = 0.5 * np.clip(k[None, :] - dead[:, None], 0.0, None) ** 2      # (candidates, samples)
    a = (x @ y) / np.einsum("ij,ij->i", x, x)
    sse = np.einsum("ij,ij->i", y[None, :] - a[:, None] * x, y[None, :] - a[:, None] * x)
    best = int(np.argmin(sse))
    return float(dead[best]), float(a[best])


def _step_response(holder: Hold, before: np.ndarray, after: np.ndarray,
                   until: Callable[[np.ndarray], bool]) -> np.ndarray:
    """Hold, then apply ``before`` open loop for a baseline, then ``after`` (for at most
    ``STEP_S`` or until ``until(counts - start)``); returns the counts' deviation (n, 3) from
    the baseline's linear trend over the step [counts]. Ends holding again."""
    rate = holder.device.rate_hz
    base = np.array([c for c, _ in holder.run(int(BASELINE_S * rate), lambda _c: before)])
    k = np.arange(len(base), dtype=float)
    slope, intercept = np.polyfit(k, base, 1)                # per leg, (2, 3)
    start = holder.counts.copy()
    rows = holder.run(int(STEP_S * rate), lambda _c: after, until=lambda c: until(c - start))
    seen = np.array([c for c, _ in rows[1:]] + [holder.counts])
    trend = intercept + slope * (len(base) - 1 + np.arange(1, len(seen) + 1))[:, None]
    holder.run(int(0.3 * rate))                              # back to holding
    return seen - trend


def check_command_sign(device: Device, holder: Hold, report: DoctorReport) -> None:
    """Per leg of ``device``: settled holding command H (from ``holder``), then H + PULSE on
    that leg; counts must go down. Adds the ``command-sign`` check to ``report``."""
    rate = device.rate_hz
    deviations = []
    for leg in range(3):
        hold = np.rint(holder.holding_command(int(SETTLE_S * rate)))
        pulse = hold.copy()
        pulse[leg] += PULSE
        deviations.append(_step_response(
            holder, hold, pulse, lambda d, leg=leg: abs(d[leg]) >= PULSE_STOP_COUNTS)[:, leg])
    moved = [float(d[-1]) for d in deviations]
    fits = [fit_onset(d) for d in deviations]               # after the moves: no stall in them
    delays = [None if f is None else round(f[0], 1) for f in fits]
    figures = {"pulse": PULSE, "leg_motion_counts": moved, "delay_ticks": delays}
    down = [m <= -MOTION_COUNTS for m in moved]
    up = [m >= MOTION_COUNTS for m in moved]
    known = [d for d in delays if d is not None]
    delay_text = (f"; the angles answered {min(known):.1f}-{max(known):.1f} ticks after the command (the "
                  "transport delay plus the legs' own start under a small force: the latency check below measures "
                  "the delay alone)") if known else ""
    if all(down):
        report.add(Check("command-sign", "ok", f"+{PULSE} on each leg drove its angle down "
                         f"(counts {np.round(moved, 1).tolist()}){delay_text}", "", figures))
    elif any(up):
        report.add(Check("command-sign", "fail",
                         f"a positive command drove leg(s) {[i for i, u in enumerate(up) if u]} "
                         f"UP (counts {np.round(moved, 1).tolist()}): the motor sign is the "
                         "opposite of the model's",
                         "do not execute plans on this unit; report the unit and this output",
                         figures))
    else:
        report.add(Check("command-sign", "warn",
                         f"too little motion to tell on leg(s) "
                         f"{[i for i, d in enumerate(down) if not d]} "
                         f"(counts {np.round(moved, 1).tolist()}){delay_text}",
                         "hold the grip loosely (not at all) and run doctor again", figures))


def check_encoder_direction(device: Device, holder: Hold, model: FalconModel, p: np.ndarray,
                            report: DoctorReport) -> None:
    """From the settled holding command of ``holder`` at pose ``p`` [m] to zero force for at
    most ``STEP_S`` on ``device``: the legs must accelerate the way the forward dynamics of
    ``model`` predicts (gravity is a reference from outside the device), by about as much.
    Adds the ``encoder-direction`` check to ``report``."""
    from falcon_plan.model.kinematics import jacobian

    params, rate = model.params, device.rate_hz
    # computed before holding starts, so that the loop never stalls for it
    accel = model.forward_dynamics(p, np.zeros(3), np.zeros(3))
    predicted = jacobian(p, params) @ accel * params.counts_per_rad / rate ** 2   # [counts/tick^2]
    hold = np.rint(holder.holding_command(int(SETTLE_S * rate)))
    deviation = _step_response(holder, hold, np.zeros(3), lambda d: np.abs(d).max() >= 20)
    fits = [fit_onset(deviation[:, leg]) for leg in range(3)]
    measured = np.array([np.nan if f is None else f[1] for f in fits])
    strong = np.abs(predicted) * STEP_S ** 2 * rate ** 2 / 2 >= 3 * MOTION_COUNTS
    figures = {"fall_ticks": len(deviation), "measured_accel_counts_per_tick2": measured.tolist(),
               "predicted_accel_counts_per_tick2": predicted.tolist()}
    if not strong.any():
        report.add(Check("encoder-direction", "skipped",
                         "gravity moves no leg enough at this pose to tell", "", figures))
        return
    legs = np.flatnonzero(strong).tolist()
    got = np.nan_to_num(measured[strong])
    agree = np.sign(got) == np.sign(predicted[strong])
    ratio = float(np.sum(got * predicted[strong]) / np.sum(predicted[strong] ** 2))
    figures["scale_ratio"] = ratio
    if not agree.all():
        report.add(Check("encoder-direction", "fail",
                         f"under gravity legs {legs} accelerated {np.round(got, 3).tolist()} "
                         f"counts/tick^2, the model predicts "
                         f"{np.round(predicted[strong], 3).tolist()}: the encoder direction "
                         "differs from the model's", "do not execute plans on this unit; report "
                         "the unit and this output", figures))
    elif not 0.5 <= ratio <= 2.0:
        report.add(Check("encoder-direction", "warn",
                         f"directions agree but the legs accelerated {ratio:.2f} x the predicted "
                         "rate", "the counts per radian or the moving mass differ from the "
                         "model: run the calibration loop on the falcon logs", figures))
    else:
        report.add(Check("encoder-direction", "ok",
                         f"at zero force legs {legs} accelerated the predicted way, {ratio:.2f} x "
                         "the predicted rate", "", figures))


def loop_delay_from_sine(counts: np.ndarray, commands: np.ndarray, frequency_hz: float,
                         rate_hz: float) -> float:
    """Command-to-reading delay [samples] of one leg from a sine excitation at
    ``frequency_hz`` [Hz] in a loop at ``rate_hz`` [Hz]: ``counts`` read and ``commands``
    sent at ticks 0, 1, ... (n,). The plant's response P = N(f) / U(f) (their windowed
    Fourier coefficients: the ratio to the commands actually sent, so a feedback loop around
    it does not matter) is, for a leg driven by a held command (an inertia: a sampled double
    integrator G(z) = (z + 1) / (2 (z - 1)^2)) that counts down for a positive command, a
    negative real number times z^-d: d = -angle(-P / G) / (2 pi f / rate), taken in
    [-0.5, rate / f - 0.5). d is what :func:`fit_onset` calls the dead time: a command sent
    at tick 0 acts from tick d on in the readings."""
    k = np.arange(counts.shape[0], dtype=float)
    window = np.hanning(k.size)
    omega = 2.0 * np.pi * frequency_hz / rate_hz
    basis = window * np.exp(-1j * omega * k)

    def coefficient(x: np.ndarray) -> complex:
        trend = np.polyval(np.polyfit(k, x, 1), k)             # the slow drift leaks otherwise
        return complex(np.sum((x - trend) * basis))

    z = np.exp(1j * omega)
    ratio = -coefficient(counts) / coefficient(commands) / ((z + 1.0) / (2.0 * (z - 1.0) ** 2))
    period = 2.0 * np.pi / omega
    return float((-np.angle(ratio) / omega + 0.5) % period - 0.5)


def check_latency(device: Device, holder: Hold, model: FalconModel, report: DoctorReport) -> None:
    """The command-to-reading delay as the control loop on ``device`` sees it:
    ``LATENCY_LEAD_S`` + ``LATENCY_S`` of ``holder``'s hold with a sine of ``PULSE`` command
    units added on each leg (at
    ``LATENCY_HZ``, a few counts of motion), the delay of each leg by
    :func:`loop_delay_from_sine`, their mean in samples at the loop rate and in ms. The part
    beyond the device's own command delay (``model``'s) is the link delay: USB frames, the
    FTDI latency timer, the I/O threads. Adds the ``latency`` check to ``report``; its
    figures go into the doctor's model file (:func:`write_latency_model`)."""
    rate = device.rate_hz
    lead, n = int(LATENCY_LEAD_S * rate), int(LATENCY_S * rate)
    ticks = np.arange(lead + n, dtype=float)[:, None]
    excitation = np.rint(PULSE * np.sin(2.0 * np.pi * np.asarray(LATENCY_HZ) * ticks / rate))
    rows = holder.run(lead + n, excitation=excitation)
    holder.run(int(0.2 * rate))                                # back to a plain hold
    counts = np.array([c for c, _ in rows[lead:]])
    commands = np.array([u for _, u in rows[lead:]], dtype=float)
    legs = [loop_delay_from_sine(counts[:, i], commands[:, i], LATENCY_HZ[i], rate) for i in range(3)]
    delay = float(np.mean(legs))
    spread = float(np.max(legs) - np.min(legs))
    device_delay = model.params.command_delay_samples + float(model.effects.extra_delay_samples)
    link = max(0.0, delay - device_delay)
    figures = {"loop_delay_samples": delay, "loop_delay_ms": delay / rate * 1e3,
               "device_delay_samples": device_delay, "link_delay_samples": link, "rate_hz": rate,
               "per_leg_samples": legs, "spread_samples": spread,
               "excitation": {"amplitude": PULSE, "frequencies_hz": list(LATENCY_HZ), "seconds": LATENCY_S}}
    detail = (f"a command shows in the readings {delay:.2f} samples ({delay / rate * 1e3:.2f} ms) after it "
              f"is sent at {rate:g} Hz: the device's {device_delay:g} + {link:.2f} of the USB path "
              f"(legs {np.round(legs, 2).tolist()})")
    if spread > LATENCY_SPREAD_WARN:
        report.add(Check("latency", "warn", detail, "the legs disagree: a busy machine delays some "
                         "readings; close other programs and run doctor again", figures))
    else:
        report.add(Check("latency", "ok", detail, "", figures))


def write_latency_model(report: DoctorReport, model: FalconModel, out_dir: Path) -> None:
    """``out_dir/doctor-model.json``: ``model`` with the link delay of the report's
    ``latency`` check (``params.link_delay_samples``), the model file that ``--model`` gives
    ``execute``, ``plan``, ``calibrate`` and ``serve``, so that the controller and the
    feed-forward lead use the measured delay. Nothing when the check did not run."""
    from falcon_plan.model.modelfile import save_model

    latency = next((c for c in report.checks if c.name == "latency" and c.status != "skipped"), None)
    if latency is None:
        return
    measured = model.params.replace(link_delay_samples=round(latency.figures["link_delay_samples"], 3))
    path = out_dir / "doctor-model.json"
    save_model(path, type(model)(measured, model.effects, model.limits),
               {"source": "falcon-plan doctor", "latency": latency.figures})
    report.files["model"] = str(path)
    latency.detail += f"; written to {path} (pass --model {path} at --rate {latency.figures['rate_hz']:g})"


# --- step 8: tours and the static check ----------------------------------------------------
HoldWindow = tuple[float, float, np.ndarray]
"""(start, end [s, trajectory time], pose [m]) of one hold in a tour."""


def tour_trajectory(start_m: np.ndarray, offsets: Any, model: FalconModel,
                    rate_hz: float) -> tuple[Trajectory, list[HoldWindow]]:
    """Start ``start_m`` [m] -> each pose ``start_m + offset`` for the ``offsets`` (n, 3) [m]
    (held ``HOLD_S``) -> start: one Trajectory of quintic moves with the feed-forward of
    ``model``, sampled at ``rate_hz`` [Hz], and the hold windows (t0, t1 [s, trajectory
    time], pose [m]) of all poses but the final return to the start."""
    from falcon_plan.planning.quintic import quintic_trajectory
    from falcon_plan.trajectory import Trajectory

    points = [start_m] + [start_m + np.asarray(o) for o in offsets] + [start_m]
    parts: list[tuple[np.ndarray, ...]] = []
    holds = []
    t_end = 0.0
    for a, b in zip(points[:-1], points[1:]):
        move = quintic_trajectory(a, b, model, rate_hz=rate_hz, tc_max=1500.0)
        parts.append((move.t_s[1:] + t_end, move.position_m[1:], move.velocity_m_s[1:],
                      move.acceleration_m_s2[1:], move.commands[1:]))
        t_end += move.duration_s
        n = int(round(HOLD_S * rate_hz))
        t = t_end + np.arange(1, n + 1) / rate_hz
        still = np.repeat(b[None], n, axis=0)
        parts.append((t, still, np.zeros_like(still), np.zeros_like(still),
                      np.repeat(model.holding_commands(b)[None], n, axis=0)))
        holds.append((t_end, t[-1], b))
        t_end = float(t[-1])
    first = (np.array([0.0]), start_m[None], np.zeros((1, 3)), np.zeros((1, 3)),
             model.holding_commands(start_m)[None])
    arrays = [np.concatenate([p[i] for p in [first, *parts]]) for i in range(5)]
    return Trajectory(*arrays, params_name=model.params.name, source="doctor"), holds[:-1]


def check_static(device: Device, holder: Hold, model: FalconModel,
                 tours: dict[str, tuple[Trajectory, list[HoldWindow]]], out_dir: Path,
                 report: DoctorReport) -> None:
    """Each of the ``tours`` (name -> :func:`tour_trajectory`, starting where ``holder``
    holds) tracked on ``device`` by the holder's PD plus the tour's feed-forward, logged as
    the falcon log ``out_dir/doctor-<name>.csv``; the mean command while holding each pose
    against the gravity compensation of ``model`` there. Adds the ``static-check`` check and
    the log files to ``report``."""
    from falcon_plan.falconlog import LogWriter, read_log
    from falcon_plan.model.kinematics import PositionTracker

    guard = PositionTracker(model.params)
    rows = []
    for name, (trajectory, holds) in tours.items():
        path = out_dir / f"doctor-{name}.csv"
        meta = {"rate_hz": f"{device.rate_hz:g}", "controller": holder.pd.metadata,
                "params": model.params.name, "trajectory_source": trajectory.source,
                "device": type(device).__name__, "derivative": "kd*v",
                "feedforward": "plan"}
        writer = LogWriter(path, meta, with_ref=True)
        try:
            holder.track(trajectory.counts, trajectory.commands, writer)
        finally:
            writer.close()
        report.files[f"falcon_log_{name}"] = str(path)
        log = read_log(path)
        for t0, t1, _pose in holds:
            window = (log.t_s >= 0.5 * (t0 + t1)) & (log.t_s <= t1)
            measured = log.tc[window].mean(axis=0)
            p = guard.position(log.enc[window].mean(axis=0))
            rows.append({"tour": name, "pose_mm": (p * 1e3).round(2).tolist(),
                         "holding_command": measured.round(1).tolist(),
                         "model_gravity_compensation": np.round(model.holding_commands(p), 1).tolist()})
    worst, bad = 0.0, []
    for row in rows:
        diff = np.subtract(row["holding_command"], row["model_gravity_compensation"])
        allowed = np.maximum(STATIC_TOLERANCE[0], STATIC_TOLERANCE[1] *
                             np.abs(row["model_gravity_compensation"]))
        worst = max(worst, float(np.abs(diff).max()))
        if np.any(np.abs(diff) > allowed):
            bad.append(row["pose_mm"])
    detail = (f"{len(rows)} poses held; holding command vs the model's gravity compensation: "
              f"largest difference {worst:.0f} command units")
    figures = {"poses": rows}
    if bad:
        report.add(Check("static-check", "warn", detail + f" (outside tolerance at {bad} mm)",
                         "run the calibration loop: falcon-plan discrepancy "
                         f"{report.files['falcon_log_train']} --heldout "
                         f"{report.files['falcon_log_heldout']} --out DIR", figures))
    else:
        report.add(Check("static-check", "ok", detail, "", figures))


# --- the whole run -------------------------------------------------------------------------
def _open(options: DoctorOptions, backend: Any) -> UsbFalcon:
    from falcon_plan.devices.usb_falcon import UsbFalcon
    from falcon_plan.execution.device_factory import write_dummy_firmware

    firmware, dummy = options.firmware, None
    if firmware is None and options.device == "emulated":
        firmware = dummy = write_dummy_firmware()
    try:
        device = UsbFalcon(firmware, backend=backend, rate_hz=options.rate_hz, realtime=False,
                           io="threaded", load_retries=options.load_retries,
                           watchdog_s=DOCTOR_WATCHDOG_S)
        device.open()
    finally:
        if dummy is not None:
            dummy.unlink(missing_ok=True)
    return device


def diagnose(options: DoctorOptions, say: Callable[[str], None] | None = None) -> DoctorReport:
    """Run every check (see the module docstring) on the device of ``options`` and write the
    report files; ``say`` tells the user what to do and what runs (default: a line on
    stderr). The garbage collector's full collections wait for the end (a real-time session:
    :func:`~falcon_plan.timing.gc_paused`)."""
    from falcon_plan.timing import gc_paused

    with gc_paused():
        return _diagnose(options, say)


def _diagnose(options: DoctorOptions, say: Callable[[str], None] | None) -> DoctorReport:
    """:func:`diagnose` itself."""
    from falcon_plan.devices.emulated import EmulatedFalconBackend, FaultPlan, UsbTiming
    from falcon_plan.execution.device_factory import read_position
    from falcon_plan.model.dynamics import FalconModel
    from falcon_plan.model.params import ACRA2009

    say = say or (lambda text: print(text, file=sys.stderr, flush=True))
    report = DoctorReport(options.device)
    options.out_dir.mkdir(parents=True, exist_ok=True)
    model = options.model or FalconModel(ACRA2009)
    backend = options.backend
    if options.device == "emulated" and backend is None:
        from falcon_plan.sim.plant import SimPlant

        backend = EmulatedFalconBackend(SimPlant(FalconModel(ACRA2009), rate_hz=options.rate_hz),
                                        options.faults or FaultPlan(), timing=UsbTiming())
    elif options.device == "usb" and options.firmware is None:
        say("no --firmware given: expecting the firmware to be running already")
    try:
        if not check_usb(options.device, backend, report):
            return report
        say("loading the firmware (it may take several attempts)...")
        try:
            t0 = time.monotonic()
            device = _open(options, backend)
        except FalconPlanError as exc:
            report.add(Check("firmware", "fail", str(exc), _open_fix(exc)))
            return report
        with device:
            attempts = device.load_attempts
            report.add(Check("firmware", "ok" if attempts == 1 else "warn",
                             f"running after {attempts} load attempt(s), {device.check_attempts} "
                             f"check send(s), {time.monotonic() - t0:.1f} s",
                             "" if attempts == 1 else "loads are flaky: connect directly, use "
                             "another USB port or cable",
                             {"load_attempts": attempts, "check_sends": device.check_attempts,
                              "kernel_driver_detached": device.kernel_driver_detached}))
            say("homing: pull the grip fully out, then push it back in...")
            try:
                t0 = time.monotonic()
                device.home(timeout_s=options.home_timeout_s)
            except FalconPlanError as exc:
                report.add(Check("homing", "fail", str(exc),
                                 "pull the grip all the way out, then push it straight in"))
                return report
            report.add(Check("homing", "ok", f"all legs homed in {time.monotonic() - t0:.1f} s"))
            try:
                start = read_position(device, model.params)
            except FalconPlanError as exc:
                report.add(Check("encoders", "fail", str(exc), "home again; if it persists the "
                                 "encoder counts do not match the model's geometry"))
                return report
            counts = device.exchange(np.zeros(3, dtype=np.int64)).counts
            report.add(Check("encoders", "ok", f"counts {counts.tolist()} -> position "
                             f"{np.round(start * 1e3, 1).tolist()} mm, inside the workspace",
                             figures={"counts": counts.tolist(), "position_mm": (start * 1e3).tolist()}))
            if not options.moves:
                report.add(Check("moves", "skipped", "--no-moves: no force was applied"))
                return report
            _moves(device, model, start, options, report, say)
        write_latency_model(report, model, options.out_dir)    # at zero force: file I/O
    finally:
        _write(report, options.out_dir)
    return report


def _moves(device: Device, model: FalconModel, start: np.ndarray, options: DoctorOptions,
           report: DoctorReport, say: Callable[[str], None]) -> None:
    """Steps 5-8, each stopping the rest if it raises."""
    from falcon_plan.model.kinematics import angles_to_counts, inverse_kinematics

    say("checking the loop and the conventions with small moves: keep your hand off the grip")
    ref = angles_to_counts(inverse_kinematics(start, model.params).theta1, model.params)
    bare_rate = check_reference_loop(device.rate_hz, report)    # at zero force
    steps = [("loop-rate", lambda h: check_loop_rate(device, h, bare_rate, report)),
             ("command-sign", lambda h: check_command_sign(device, h, report)),
             ("latency", lambda h: check_latency(device, h, model, report)),
             ("encoder-direction", lambda h: check_encoder_direction(device, h, model, start, report))]
    current = "static-check"
    try:
        # planned before any force is applied: planning would stall a holding loop
        tours = {name: tour_trajectory(start, offsets, model, device.rate_hz)
                 for name, offsets in TOURS.items()}
        current = "loop-rate"
        with Hold(device, model, ref, start) as holder:
            holder.holding_command(int(0.5 * device.rate_hz))     # settle first
            for name, step in steps:
                current = name
                step(holder)
            current = "static-check"
            say("holding a few poses (the static check)...")
            check_static(device, holder, model, tours, options.out_dir, report)
    except FalconPlanError as exc:
        report.add(Check(current, "fail", f"{type(exc).__name__}: {exc}",
                         "see the message; the device was left at zero force"))


def _open_fix(exc: Exception) -> str:
    from falcon_plan.devices.base import DevicePermissionError

    if isinstance(exc, DevicePermissionError):
        return "see the message: install the udev rule"
    return "see the message"


def _write(report: DoctorReport, out_dir: Path) -> None:
    """doctor-report.json and doctor-report.txt, each written whole or not at all."""
    json_path, text_path = out_dir / "doctor-report.json", out_dir / "doctor-report.txt"
    report.files.update(report=str(json_path), text=str(text_path))
    for path, content in ((json_path, json.dumps(report.to_dict(), indent=1, default=json_default)),
                          (text_path, report.text())):
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(content, encoding="utf-8")
        os.replace(tmp, path)


def json_default(value: Any) -> Any:
    """``default=`` of :func:`json.dumps` for a report's figures: a numpy scalar or array
    ``value`` as a number or a list; TypeError for anything else."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
