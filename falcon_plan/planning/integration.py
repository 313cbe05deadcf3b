"""Integrating a command pattern's motion: the compiled RK4 step and the steps of its phases.

- **command rule** (:class:`CommandRule`): each leg's command at +-level (a constant limit),
  or riding the device's limit L(w_s) minus the reserve (solved inside the step,
  :func:`~falcon_plan.planning.bound.command_on_limit`);
- **the step** (:func:`compiled_step`): one RK4 step of the model's forward dynamics under a
  rule, with its Jacobian and adjoint, compiled once per parameter set and rule; a built step
  is recorded in the kernel cache by a recipe (a hash of its sources, parameters, rule and
  flags), so later processes load it with ``casadi.external`` instead of rebuilding its
  symbolics (~0.4 s a process);
- **the steps of a pattern's phases** (:func:`step_plan`; :func:`step_counts`, under the
  device's limit at most :data:`DEVICE_STEP_S` long), with a ramp step at every switch.

Friction with a sign (Coulomb, Stribeck: tanh(w / w_s)) does not change the bang-bang
structure (the command still enters affinely), but the friction torque changes sign within
~0.1 ms where a leg reverses (and sets in over as long at a start from rest): on the coarse
steps RK4 misses it and the output nodes straddle it (2.9 % over the bound on the dense
re-check of a calibrated model). So those places are found (:func:`find_reversals`) and the
steps and output nodes graded down to a fraction of that time there (:func:`phase_grid`).
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from falcon_plan.compiled import BufferedFunction, build_shared_library
from falcon_plan.compiled.build import record_recipe, recipe_file, recorded_recipe
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import LEG_COULOMB_FIELDS
from falcon_plan.model.saturation import SaturationModel
from falcon_plan.planning.bound import CommandBound, command_on_limit, leg_motion
from falcon_plan.planning.pattern import SWITCH_RAMP_S, CommandPattern, Phases


STEP_FLAGS = ("-O1", "-march=native")
"""Compiler options of the RK4 step and its adjoint (measured when the step's AD Jacobian was
compiled with them: 63 us a call against 74 us at -O1 alone and 83 us at -O2, which compiles
for longer still). The step and adjoint of the constant rule compile in about 28 s on this
machine, the device rule's in about 48 s (with the AD Jacobian, since dropped, the constant
rule's took about 155 s), so ``dev.py`` builds them at set-up
(:mod:`falcon_plan.compiled.prepare`)."""
DEVICE_STEP_S = 4e-3
"""Longest RK4 step under the device's limit [s]: the command follows L(w_s), which turns from
2500 to 4096 within a few ms of a leg's reversal and has kinks in its second derivative (at
w_s = 0 and at the release speed), so RK4 needs short steps there. With 2 steps per phase the
duration of the benchmark move (0, 0, 0.12) -> (0.03, 0.02, 0.14) m was 0.9 % off a
192-interval transcription; with at most 2 ms steps within 0.01 %. With at most 4 ms steps
the 37 benchmark problems' durations moved from those of 2 ms steps by 1.7e-4 at most
(moving_both), the rest by < 1e-4, all within 0.06 % of 192-interval solves (the returned
motion is re-solved on the output grid, nodes down to 0.25 ms apart where the limit changes,
:func:`.sampling.output_splits`), for about a quarter less time in the switching stage."""


# --- compiled pieces --------------------------------------------------------------------

_lock = threading.Lock()
_steppers: dict[Any, "_Stepper"] = {}


class _Stepper:
    """One RK4 step of a model's forward dynamics, x = (p, v) [m, m/s] -> x', with the command
    of a :class:`CommandRule` (constant: sign * level + delta; device: riding the device's
    limit, :func:`~falcon_plan.planning.bound.command_on_limit`), its sign ramping linearly
    from s0 to s1 over the step of h [s]; and its adjoint (mu -> mu^T d/dx, mu^T d/ddelta, the
    latter the check's figure): compiled once per parameter set and rule and called in place
    (:class:`~falcon_plan.compiled.BufferedFunction`), a run of steps mostly in compiled chunks
    of :data:`RUN_CHUNKS` steps (measured in a run of 2000 steps: 6.5 us a step under the
    constant rule, 8.5 us under the device's, against 14.5 and 16 us one call a step with the
    dynamics as they were before). (The shooting's terminal Jacobian comes from runs of the step itself,
    :meth:`~falcon_plan.planning.shooting.Shooting.linearise`: a compiled AD Jacobian of the step
    cost 12-20 steps a call and most of the build's compile time.)"""

    def __init__(self, model: FalconModel, rule: str, saturation: SaturationModel) -> None:
        self.rule = rule
        self.lock = threading.Lock()  # the buffers are shared: planner threads take turns per run
        name = f"falcon_rk4_{rule}_step"
        recipe = _recipe_file(model, rule, saturation)
        libraries = recorded_recipe(recipe, 2)
        self.runners: dict[int, BufferedFunction] = {}
        """Compiled runs of k steps in one call (k in :data:`RUN_CHUNKS`; none uncompiled)."""
        if libraries is not None:  # built before on this machine: load it without the ~0.4 s of symbolics
            step_lib, command_lib = (Path(p) for p in libraries)
            self.step, self.adjoint = (BufferedFunction(ca.external(n, str(step_lib)), step_lib)
                                       for n in (name, name + "_adj"))
            self.runners = _load_runners(name, step_lib)
            self.command = BufferedFunction(ca.external(name + "_command", str(command_lib)), command_lib)
            return
        fns = model.functions
        n_eff = fns.expressions.eff.numel()
        x, s0, s1 = ca.SX.sym("x", 6), ca.SX.sym("s0", 3), ca.SX.sym("s1", 3)
        h, eff, level, delta = ca.SX.sym("h"), ca.SX.sym("eff", n_eff), ca.SX.sym("level"), ca.SX.sym("delta", 3)

        def rate(state: ca.SX, sign: ca.SX) -> ca.SX:
            p, v = state[:3], state[3:]
            u = sign * level + delta if rule == "constant" else \
                command_on_limit(model, saturation, p, v, sign, eff, level, delta)
            return ca.vertcat(v, fns.forward_dynamics(p, v, u, eff))

        mid = 0.5 * (s0 + s1)
        k1 = rate(x, s0)
        k2 = rate(x + 0.5 * h * k1, mid)
        k3 = rate(x + 0.5 * h * k2, mid)
        k4 = rate(x + h * k3, s1)
        inputs = [x, s0, s1, h, eff, level, delta]
        out = ca.cse(x + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4))
        step = ca.Function(name, inputs, [out])
        mu = ca.SX.sym("mu", 6)
        adjoint = ca.Function(name + "_adj", inputs + [mu], [ca.jtimes(out, x, mu, True), ca.jtimes(out, delta, mu, True)])
        library = build_shared_library(name, [step, adjoint, *(_runner(step, name, k) for k in RUN_CHUNKS)],
                                       STEP_FLAGS)
        self.step, self.adjoint = BufferedFunction(step, library), BufferedFunction(adjoint, library)
        if library is not None:
            self.runners = _load_runners(name, library)
        zero = ca.DM.zeros(3)
        command = ca.Function(name + "_command", [x, s0, eff, level], [
            s0 * level if rule == "constant" else command_on_limit(model, saturation, x[:3], x[3:], s0, eff, level, zero)])
        command_library = build_shared_library(command.name(), [command], STEP_FLAGS)
        self.command = BufferedFunction(command, command_library)
        """The command [command units] at state x with sign s0 (no offset)."""
        if library is not None and command_library is not None:
            record_recipe(recipe, [str(library), str(command_library)])

    def commands(self, states: np.ndarray, signs: np.ndarray, eff: np.ndarray, level: float) -> np.ndarray:
        """The commands (n, 3) [command units] at ``states`` (n, 6) with ``signs`` (n, 3)."""
        buf = self.command
        out = np.empty((len(states), 3))
        with self.lock:
            buf.inputs[2][:] = eff
            buf.inputs[3][:] = level
            for n, (x, s) in enumerate(zip(states, signs)):
                buf.inputs[0][:] = x
                buf.inputs[1][:] = s
                buf()
                out[n] = buf.outputs[0]
        return out

    def adjoint_pass(self, states: np.ndarray, eff: np.ndarray, level: float, hs: np.ndarray, s0s: np.ndarray,
                     s1s: np.ndarray, mu: np.ndarray, jumps: dict[int, np.ndarray]) -> list[np.ndarray]:
        """Backward through the steps of a run (``states`` from :meth:`run`) from the costate
        ``mu`` (6,) at the end, adding ``jumps[n]`` (3,) to its position part at state n:
        per step, mu^T d x'/d delta (3,) (more command on the whole step), in time order."""
        buf = self.adjoint
        mu = np.array(mu, float)
        ddelta = []
        with self.lock:
            buf.inputs[4][:] = eff
            buf.inputs[5][:] = level
            buf.inputs[6][:] = 0.0
            for n in reversed(range(len(hs))):
                if n + 1 in jumps:
                    mu[:3] += jumps[n + 1]
                buf.inputs[0][:] = states[n]
                buf.inputs[1][:] = s0s[n]
                buf.inputs[2][:] = s1s[n]
                buf.inputs[3][:] = hs[n]
                buf.inputs[7][:] = mu
                buf()
                ddelta.append(buf.outputs[1].copy())
                mu = buf.outputs[0].copy()
        return ddelta[::-1]

    def run(self, x0: np.ndarray, eff: np.ndarray, level: float, hs: np.ndarray, s0s: np.ndarray,
            s1s: np.ndarray, deltas: np.ndarray | None = None) -> np.ndarray:
        """The states after each step (n + 1, 6), from ``x0``, with the rule's ``level`` and the
        signs ``s0s``, ``s1s`` (n, 3) at each step's ends (and ``deltas`` (n, 3) [command units]
        added to the commands; default none): as many steps as fit in the compiled runs of
        :data:`RUN_CHUNKS` steps a call, the rest one call a step."""
        states = np.empty((len(hs) + 1, 6))
        states[0] = x0
        done = 0
        with self.lock:
            for k, buf in self.runners.items():
                if len(hs) - done < k:
                    continue
                buf.inputs[4][:] = eff
                buf.inputs[5][:] = level
                buf.inputs[6][:] = 0.0
                while len(hs) - done >= k:
                    chunk = slice(done, done + k)
                    buf.inputs[0][:] = states[done]
                    buf.inputs[1][:] = np.asarray(s0s[chunk]).T
                    buf.inputs[2][:] = np.asarray(s1s[chunk]).T
                    buf.inputs[3][:] = hs[chunk]
                    if deltas is not None:
                        buf.inputs[6][:] = np.asarray(deltas[chunk]).T
                    buf()
                    states[done + 1:done + k + 1] = buf.outputs[0].T
                    done += k
            buf = self.step
            buf.inputs[4][:] = eff
            buf.inputs[5][:] = level
            buf.inputs[6][:] = 0.0
            for n, (h, s0, s1) in enumerate(zip(hs[done:], s0s[done:], s1s[done:]), start=done):
                buf.inputs[0][:] = states[n]
                buf.inputs[1][:] = s0
                buf.inputs[2][:] = s1
                buf.inputs[3][:] = h
                if deltas is not None:
                    buf.inputs[6][:] = deltas[n]
                buf()
                states[n + 1] = buf.outputs[0]
        return states


RUN_CHUNKS = (16, 4)
"""Steps per call of the compiled runs (:meth:`_Stepper.run`), largest first: a run of n steps
is n // 16 calls of 16, then of 4, then single steps (a padded call would compute its padding:
a step costs as much with h = 0). One call per step cost about as much in Python and ctypes as
the step itself (~5 us beside its ~6-9 us of C)."""


def _runner(step: ca.Function, name: str, k: int) -> ca.Function:
    """``step`` (x, s0, s1, h, eff, level, delta) -> x' applied k times in a row, as the Function
    ``{name}_run{k}``: (x0, s0 (3, k), s1 (3, k), h (1, k), eff, level, delta (3, k)) -> the
    states after each step (6, k)."""
    x0, s0, s1, h = ca.MX.sym("x0", 6), ca.MX.sym("s0", 3, k), ca.MX.sym("s1", 3, k), ca.MX.sym("h", 1, k)
    eff, level, delta = ca.MX.sym("eff", step.size1_in(4)), ca.MX.sym("level"), ca.MX.sym("delta", 3, k)
    states = step.mapaccum(f"{name}_acc{k}", k)(x0, s0, s1, h, ca.repmat(eff, 1, k), ca.repmat(level, 1, k), delta)
    return ca.Function(f"{name}_run{k}", [x0, s0, s1, h, eff, level, delta], [states])


def _load_runners(name: str, library: Path) -> dict[int, BufferedFunction]:
    """The compiled runs of :data:`RUN_CHUNKS` steps in ``library`` (built with :func:`_runner`)."""
    return {k: BufferedFunction(ca.external(f"{name}_run{k}", str(library)), library) for k in RUN_CHUNKS}


_RECIPE_SOURCES = ("planning/integration.py", "planning/bound.py", "compiled/build.py", "model")
"""The sources a step's expressions come from (relative to the package; a folder: every .py
in it): a change in any of them is a new recipe, built and compiled afresh."""


def _recipe_file(model: FalconModel, rule: str, saturation: SaturationModel | None) -> Path:
    """Where the libraries of the step of ``model``, ``rule`` and ``saturation`` are recorded once
    built (:func:`~falcon_plan.compiled.build.recipe_file`: the sources, the parameter set,
    limits, rule, saturation and flags)."""
    return recipe_file(f"falcon_rk4_{rule}_step", _RECIPE_SOURCES, model.params, model.limits,
                       model.functions.expressions.eff.numel(), rule, saturation if rule == "device" else None,
                       STEP_FLAGS)


def compiled_step(model: FalconModel, rule: CommandRule) -> _Stepper:
    """The :class:`_Stepper` of ``model``'s parameter set and ``rule`` (built and compiled once)."""
    saturation = rule.saturation if rule.kind == "device" else None
    key = (model.params, model.limits, model.functions.expressions.eff.numel(), rule.kind, saturation)
    with _lock:
        if key not in _steppers:
            _steppers[key] = _Stepper(model, rule.kind, rule.saturation)
        return _steppers[key]


@dataclass(frozen=True)
class CommandRule:
    """How a pattern's commands are set: ``kind`` "constant", +-``level`` (tc_max - reserve)
    [command units]; or "device", riding the device's limit ``saturation`` minus the reserve
    ``level`` [command units] (:func:`~falcon_plan.planning.bound.command_on_limit`)."""

    kind: str
    level: float
    saturation: SaturationModel

    @classmethod
    def of(cls, bound: CommandBound) -> "CommandRule":
        """The rule of a plan under ``bound``."""
        if bound.kind == "constant":
            return cls("constant", bound.tc_max - bound.reserve, bound.saturation)
        return cls("device", bound.reserve, bound.saturation)


@dataclass(frozen=True)
class StepPlan:
    """The integration steps of a phase sequence (one row per step): length h (n,) [s], the
    commands' signs at its start u0 and end u1 (n, 3) (+-1; between on a ramp), the phase it belongs to
    (n,) (-1 for a command ramp) and its share of that phase's regular span (n,) (dh/d of the
    phase's duration; 0 for a ramp); ``ends[j]`` is the index of the state at the end of
    phase j."""

    h: np.ndarray
    u0: np.ndarray
    u1: np.ndarray
    phase: np.ndarray
    share: np.ndarray
    ends: np.ndarray


@dataclass(frozen=True)
class Reversal:
    """Where a leg's speed passes zero (or starts or ends at rest) in a model with a
    friction sign (tanh(w / w_s), :mod:`falcon_plan.model.effects`): its friction torque
    changes sign within a few ``width`` there, so the steps are graded down to a fraction
    of it (:func:`phase_grid`). ``phase``: the phase it falls in; ``at`` and ``width``: its
    place and w_s / |dw/dt| as fractions of that phase's regular span (after any ramp)."""

    phase: int
    at: float
    width: float


GRADED_OFFSETS = np.array([0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0])
"""Nodes added on both sides of a :class:`Reversal`, in its widths (divided by the grid's
fineness): a linear acceleration between them follows the friction's tanh within ~0.2 % of
the command bound, and RK4 integrates through it; past 8 widths tanh is flat to 5e-7 and the
phase's own steps take over (offsets longer than them are left out)."""


def phase_grid(count: int, reversals: Any = (), fineness: float = 1.0) -> np.ndarray:
    """The step lengths of one phase as fractions of its regular span (summing to 1):
    ``count`` equal steps, plus the nodes of :data:`GRADED_OFFSETS` around each of
    ``reversals`` (:class:`Reversal` of this phase), their spacing divided by ``fineness``."""
    nodes = [np.linspace(0.0, 1.0, count + 1)]
    for rev in reversals:
        offsets = GRADED_OFFSETS * rev.width / fineness
        offsets = np.concatenate([[0.0], offsets[offsets < 1.0 / count]])
        nodes.append(rev.at + np.concatenate([offsets, -offsets]))
    x = np.unique(np.clip(np.concatenate(nodes), 0.0, 1.0))
    x = x[np.concatenate([[True], np.diff(x) > 1e-9])]
    x[-1] = 1.0
    return np.diff(x)


def same_reversals(a: tuple[Reversal, ...], b: tuple[Reversal, ...]) -> bool:
    """Whether the reversals ``a`` are those of ``b``, each within its width."""
    return len(a) == len(b) and all(x.phase == y.phase and abs(x.at - y.at) <= y.width
                                    for x, y in zip(sorted(a, key=lambda r: (r.phase, r.at)),
                                                    sorted(b, key=lambda r: (r.phase, r.at))))


def step_plan(phases: Phases, grid: list[np.ndarray]) -> StepPlan:
    """The steps of ``phases`` (their commands' signs) and the steps of each phase
    ``grid[j]`` (fractions of its regular span, :func:`phase_grid`); a phase that starts with
    a command change starts with the ramp (SWITCH_RAMP_S, from the previous phase's command
    to its own)."""
    commands = phases.signs.T                                 # (m, 3) signs
    counts = np.array([len(g) for g in grid], int)
    ramp = np.concatenate([[False], phases.ramp])             # phase j starts with a ramp
    per_phase = counts + ramp
    ends = np.cumsum(per_phase)
    phase = np.repeat(np.arange(len(counts)), per_phase)
    is_ramp = np.zeros(len(phase), bool)
    is_ramp[(ends - per_phase)[ramp]] = True
    share = np.zeros(len(phase))
    share[~is_ramp] = np.concatenate(grid)
    h = (phases.durations - SWITCH_RAMP_S * ramp)[phase] * share
    h[is_ramp] = SWITCH_RAMP_S
    u1 = commands[phase]
    u0 = u1.copy()
    u0[is_ramp] = commands[phase[is_ramp] - 1]
    return StepPlan(h, u0, u1, np.where(is_ramp, -1, phase), share, ends)


def has_friction_sign(model: FalconModel) -> bool:
    """Whether ``model``'s dynamics have a friction torque with a (smoothed) sign: Coulomb,
    per-leg Coulomb or Stribeck friction."""
    eff = model.effects
    return eff.coulomb_Nm + eff.stribeck_Nm + sum(getattr(eff, f) for f in LEG_COULOMB_FIELDS) > 0.0


def find_reversals(model: FalconModel, phases: Phases, steps: StepPlan, states: np.ndarray) -> tuple[Reversal, ...]:
    """The :class:`Reversal` s of a run of ``model`` (``states`` after each of ``steps`` of ``phases``):
    every sign change of a leg speed w = J(p) v (linear between states), and the ends of the
    motion where the legs are at rest, their width from the fastest leg's |dw/dt| there."""
    t = np.concatenate([[0.0], np.cumsum(steps.h)])
    w = leg_motion(model, states[:, :3], states[:, 3:], np.zeros_like(states[:, 3:]))[0]
    smoothing = model.effects.friction_smoothing_rad_s
    found = []  # (time [s], |dw/dt| [rad/s^2])
    rest = [bool(np.abs(w[k]).max() <= 0.1 * smoothing) for k in (0, -1)]
    for k, h in ((0, steps.h[0]), (-1, steps.h[-1])):  # at rest: the friction sets in (dies out) there
        if rest[k]:
            found.append((t[k], float(np.abs(w[1 if k == 0 else -2]).max()) / h))
    for leg in range(3):
        for k in np.nonzero(w[:-1, leg] * w[1:, leg] < 0.0)[0]:
            if (k == 0 and rest[0]) or (k == len(w) - 2 and rest[-1]):
                continue  # the rounding around rest itself
            dw = w[k + 1, leg] - w[k, leg]
            found.append((t[k] - steps.h[k] * w[k, leg] / dw, abs(dw) / steps.h[k]))
    regular = phases.bounds[:-1] + SWITCH_RAMP_S * np.concatenate([[False], phases.ramp])
    span = phases.bounds[1:] - regular
    out = []
    for time_s, rate in found:
        j = int(np.clip(np.searchsorted(phases.bounds, time_s, side="right") - 1, 0, len(span) - 1))
        out.append(Reversal(j, float(np.clip((time_s - regular[j]) / span[j], 0.0, 1.0)),
                            smoothing / max(rate, 1e-6) / span[j]))
    return tuple(out)


def step_counts(pattern: CommandPattern, rule: CommandRule, duration_s: float, steps_per_phase: int) -> list[int]:
    """RK4 steps of each phase of ``pattern`` in a solve with ``rule``: ``steps_per_phase``;
    under the device's limit at least one per :data:`DEVICE_STEP_S` of the phase (at T =
    ``duration_s`` [s], the guess: fixed for the solve, so its equations stay smooth)."""
    if rule.kind == "constant":
        return [steps_per_phase] * pattern.n_phases
    durations = np.maximum(pattern.phases(duration_s).durations, 0.0)
    return [max(steps_per_phase, math.ceil(d / DEVICE_STEP_S)) for d in durations]


__all__ = ["CommandRule", "StepPlan", "Reversal", "compiled_step", "phase_grid", "step_plan", "step_counts",
           "has_friction_sign", "find_reversals", "same_reversals", "DEVICE_STEP_S"]
