"""A real-time host in front of the independent world (:mod:`.independent_world`): falcon
logs as ``experiment run`` writes them on a busy machine, made deterministically.

The world lives on a grid of ``SUB`` steps per control period; the host runs the executor's
loop (the paper's PD as the executor computes it: the count difference over the slots
between the exchanges that returned the two readings) with its own timing, drawn from a
seeded :class:`HostTiming`:

- tick k is due at slot k; it starts late by a random jitter (a share of the period), and now
  and then the host stalls for several periods: the ticks it missed are skipped (the log
  shows a gap and ``skipped``), the first tick after a stall runs on the current slot;
- a tick reads the newest status: the counts the device sampled ``in_delay`` before the
  status arrived at the host (``read_us``), computes, and hands its command to the driver
  (``sent_us``); the command reaches the motors ``out_delay`` later and acts until the
  next one arrives (the firmware holds it through skipped ticks); the device answers only
  commands, so the first tick after a stall has only the status that answered the tick
  before the stall (it arrived a period after that tick's reading);
- effects outside the library, for the open-world cases: a dead band on the command (the
  motors do not move below ``deadband`` command units; the rest passes reduced by it) and a
  motor gain that drifts linearly over the run (``gain_drift``: the relative change at the
  end).

All times are on the world's grid, so every command acts exactly over its interval.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from falcon_plan.discrepancy.replay import TRANSPORT_DELAY_KEY
from falcon_plan.falconlog import FalconLog

from .independent_world import SUBSTEP_TARGET_HZ, World, _Layout, _period, _start_point

SUB = 4
"""World steps per control period (the host's times are multiples of a quarter period)."""


@dataclass(frozen=True)
class HostTiming:
    """The host's timing, in world steps (1 / SUB of a period) unless named otherwise.

    ``jitter``: a tick starts late by 0..jitter steps (uniform); ``stall_every_s``: a stall
    starts about this often [s] (exponential gaps; inf: never); ``stall_periods``: its length
    is 2..this many periods (uniform); ``compute``: steps from the reading's arrival to the
    command's send; ``in_delay``: steps from the device's sample to the status's arrival;
    ``out_delay``: steps from the send to the command acting.
    """

    jitter: int = 2
    stall_every_s: float = 0.25
    stall_periods: int = 12
    compute: int = 1
    in_delay: int = 2
    out_delay: int = 7

    @property
    def loop_delay_periods(self) -> float:
        """Device sample to command acting [periods]."""
        return (self.in_delay + self.compute + self.out_delay) / SUB


QUIET = HostTiming(jitter=1, stall_every_s=math.inf)
BUSY = HostTiming()


def simulate_host_log(world: World, ref_counts: np.ndarray, rate_hz: float = 1000.0, *,
                      timing: HostTiming = BUSY, seed: int = 0, kp: float = 10.0, kd: float = 0.1,
                      cutoff_hz: float = 50.0, deadband: float = 0.0, gain_drift: float = 0.0,
                      measured_delay: bool = True) -> FalconLog:
    """The falcon log (with timing columns) of the PD tracking ``ref_counts`` (N, 3) on
    ``world`` through a host with ``timing`` (seeded by ``seed``); ``deadband`` [command
    units] and ``gain_drift`` [relative, at the end of the run] as in the module docstring.
    The device starts at rest where its counts read ref_counts[0]."""
    params = world.params
    rng = np.random.default_rng(seed)
    fine_hz = SUB * rate_hz
    layout = _Layout(params, world.two_mass, max(1, int(round(SUBSTEP_TARGET_HZ / fine_hz))))
    fn = _period(layout)
    fn.inputs[2][:] = world.vector(1.0 / (fine_hz * layout.substeps))
    cpr = params.counts_per_rad
    home = params.theta_home_rad + world.encoder_offset_rad
    theta0 = home + np.asarray(ref_counts[0], float) / cpr
    x = np.zeros(12 if world.two_mass else 6)
    x[0:3] = _start_point(theta0, params)
    if world.two_mass:
        x[6:9] = theta0
    n_rows = ref_counts.shape[0]
    total = SUB * n_rows
    # the host's ticks: (slot, send step); a stall skips the slots it covers
    ticks: list[tuple[int, int]] = []
    stall_at = _next_stall(rng, timing, rate_hz, 0)
    slot = 0
    while slot < n_rows:
        start = SUB * slot + int(rng.integers(0, timing.jitter + 1))
        if slot >= stall_at:
            start += SUB * int(rng.integers(2, timing.stall_periods + 1)) + int(rng.integers(0, SUB))
            stall_at = _next_stall(rng, timing, rate_hz, slot + 1)
        slot = max(slot, start // SUB)  # a late tick runs on the current slot
        if slot >= n_rows:
            break
        ticks.append((slot, max(start, SUB * slot) + timing.compute))
        slot += 1
    sends = np.array([s for _, s in ticks])
    acting_from = sends + timing.out_delay + SUB * world.extra_delay  # the world's extra delay is the device's
    # counts per world step (filled as the world runs) and the loop, tick by tick
    counts_at = np.zeros((total + 1, 3))
    counts_at[0] = np.floor((theta0 - home) * cpr + 0.5)
    enc = np.zeros((len(ticks), 3), dtype=np.int64)
    tc = np.zeros((len(ticks), 3), dtype=np.int64)
    alpha = 1.0 - math.exp(-2.0 * math.pi * cutoff_hz / rate_hz)
    prev, vel, prev_slot, gap = None, np.zeros(3), None, 1
    step, acting, nxt = 0, np.zeros(3), 0
    read_steps = np.zeros(len(ticks), dtype=np.int64)
    for i, (slot, send) in enumerate(ticks):
        read_steps[i] = send - timing.compute
        if prev_slot is not None and slot - prev_slot > 1:  # after a stall: the status of the tick before it
            read_steps[i] = read_steps[i - 1] + SUB
        sample_step = read_steps[i] - timing.in_delay
        while step < send:  # run the world up to this tick's send (its reading is older)
            while nxt < i and acting_from[nxt] <= step:
                acting = tc[nxt].astype(float)
                nxt += 1
            x = _world_step(fn, x, _motor_command(acting, deadband, gain_drift, step / total))
            motor = x[6:9] if world.two_mass else fn.outputs[1]
            step += 1
            counts_at[step] = np.floor((np.asarray(motor).ravel() - home) * cpr + 0.5)
        counts = counts_at[max(sample_step, 0)]
        vel = vel + alpha * ((counts - (counts if prev is None else prev)) * rate_hz / gap - vel)
        tc[i] = np.clip(np.floor(kp * (counts - ref_counts[slot]) + kd * vel + 0.5), -4096, 4096)
        gap = 1 if prev_slot is None else slot - prev_slot  # the executor's next count difference spans this
        enc[i], prev, prev_slot = counts, counts, slot
    slots_run = np.array([s for s, _ in ticks])
    us_per_step = 1e6 / fine_hz
    origin = 1_000_000_000
    sent_us = origin + np.rint(sends * us_per_step).astype(np.int64)
    read_us = origin + np.rint(read_steps * us_per_step).astype(np.int64)
    skipped = np.diff(slots_run, prepend=-1) - 1
    meta = {"rate_hz": f"{rate_hz:g}", "controller": f"pd kp={kp:g} kd={kd:g}", "params": params.name,
            "source": "tests/discrepancy/host_world.py", "paced": "true"}
    if measured_delay:  # as doctor measures it: from handing a command over to its acting, seen from the readings
        meta[TRANSPORT_DELAY_KEY] = f"{(timing.out_delay + timing.in_delay) / SUB:g}"
    return FalconLog(slots_run / rate_hz, enc, tc, np.asarray(ref_counts, float)[slots_run], meta,
                     sent_us, read_us, skipped)


def _next_stall(rng: np.random.Generator, timing: HostTiming, rate_hz: float, after: int) -> float:
    """The slot of the next stall after slot ``after`` (inf: none)."""
    if not math.isfinite(timing.stall_every_s):
        return math.inf
    return after + rng.exponential(timing.stall_every_s * rate_hz)


def _motor_command(acting: np.ndarray, deadband: float, gain_drift: float, progress: float) -> np.ndarray:
    """The command the motors act on: through the dead band, scaled by the drifting gain at
    ``progress`` (0..1) of the run."""
    out = acting
    if deadband:
        out = np.sign(out) * np.maximum(np.abs(out) - deadband, 0.0)
    if gain_drift:
        out = out * (1.0 + gain_drift * progress)
    return out


def _world_step(fn, x: np.ndarray, command: np.ndarray) -> np.ndarray:
    fn.inputs[0][:] = x
    fn.inputs[1][:] = command
    fn()
    out = fn.outputs[0].copy()
    if not np.all(np.isfinite(out)):
        raise RuntimeError("the host world diverged")
    return out
