"""The simulated plant over many periods in a few compiled calls: BATCH_CHUNK periods of the
open loop or of the encoder PD closed loop per Function (mapaccum over the period of
:mod:`falcon_plan.sim.equations`), compiled once per machine (:mod:`falcon_plan.compiled`), and
the loop that runs them chunk by chunk. :meth:`~falcon_plan.sim.plant.SimPlant.run_open_loop`
and :meth:`~falcon_plan.sim.plant.SimPlant.run_pd` use them.

The wrappers are MX, so the generated C keeps the loop (an SX wrapper would unroll 200 copies
of the period).
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from types import SimpleNamespace

import casadi as ca
import numpy as np

from falcon_plan.compiled import BufferedFunction, build_shared_library
from falcon_plan.compiled.build import library_by_recipe, recipe_file
from falcon_plan.control import pd_law
from falcon_plan.model.symbolic import N_EFFECTS
from falcon_plan.sim.equations import BUILDING, PLANT_PARAMETERS, PlantLayout, plant_functions

BATCH_CHUNK = 200
"""Periods per call of the compiled batched functions."""
PD_PARAMETERS = ("kp", "kd", "alpha", "rate_hz", "limit")
"""Order of the PD gains vector of :func:`pd_chunk`."""
_CASADI_OPS = SimpleNamespace(floor=ca.floor, fmin=ca.fmin, fmax=ca.fmax)


@lru_cache(maxsize=None)
def open_loop_chunk(layout: PlantLayout, merged: bool = True) -> ca.Function:
    """BATCH_CHUNK periods of the plant of ``layout`` under given acting commands (mapaccum
    of the period): (x0, TC (3, B), eff, pp) -> (X (n, B), ENC (3, B), THETA1 (3, B));
    ``merged`` as for :func:`plant_functions`."""
    fns = plant_functions(layout, merged)
    n, b = layout.n_states, BATCH_CHUNK
    eff, pp = ca.MX.sym("eff", N_EFFECTS), ca.MX.sym("pp", len(PLANT_PARAMETERS))
    x0, tcs = ca.MX.sym("x0", n), ca.MX.sym("tc", 3, b)
    acc = fns.period.mapaccum("plant_open_loop_acc", b, [0], [0])
    xs, enc, theta, _ = acc(x0, tcs, eff, pp)
    return ca.Function(f"falcon_plant_open_loop_{_tag(layout)}", [x0, tcs, eff, pp],
                       [xs, enc, theta], ["x0", "tc", "eff", "pp"], ["x", "enc", "theta1"])


def _tag(layout: PlantLayout) -> str:
    return "c" if layout.compliant else "r"


@lru_cache(maxsize=None)
def pd_chunk(layout: PlantLayout, d: int, merged: bool = True) -> ca.Function:
    """BATCH_CHUNK periods of the encoder PD closed loop (:func:`~falcon_plan.control.pd_law`)
    with a command delay line of ``d`` periods, for the plant of ``layout``: one period maps
    z = [x, v_filtered, n_prev, delay line (3 d)] with per-step ref and ff to the next z,
    looped with mapaccum. (z0, REF (3, B), FF (3, B), eff, pp, gains (PD_PARAMETERS)) -> (Z,
    COUNTS (3, B), TC (3, B)); ``merged`` as for :func:`plant_functions`."""
    fns = plant_functions(layout, merged)
    n, b = layout.n_states, BATCH_CHUNK
    eff, pp = ca.MX.sym("eff", N_EFFECTS), ca.MX.sym("pp", len(PLANT_PARAMETERS))
    z = ca.SX.sym("z", n + 6 + 3 * d)
    ref, ff = ca.SX.sym("ref", 3), ca.SX.sym("ff", 3)
    eff_s, pp_s = ca.SX.sym("eff", N_EFFECTS), ca.SX.sym("pp", len(PLANT_PARAMETERS))
    gains = ca.SX.sym("gains", len(PD_PARAMETERS))
    x, v, n_prev, line = z[0:n], z[n:n + 3], z[n + 3:n + 6], z[n + 6:]
    enc, _ = fns.encoder(x, eff_s)
    counts = ca.floor(enc + 0.5)
    g = {name: gains[i] for i, name in enumerate(PD_PARAMETERS)}
    tc, v_new = pd_law(counts, n_prev, v, ref, ff, g["kp"], g["kd"], g["alpha"], g["rate_hz"],
                       g["limit"], ops=_CASADI_OPS)
    x_next = fns.period(x, line[0:3], eff_s, pp_s)[0]
    z_next = ca.vertcat(x_next, v_new, counts, line[3:], tc)
    step = ca.Function("plant_pd_period", [z, ref, ff, eff_s, pp_s, gains], [z_next, counts, tc])
    acc = step.mapaccum("plant_pd_acc", b, [0], [0])
    z0 = ca.MX.sym("z0", z.numel())
    refs, ffs = ca.MX.sym("ref", 3, b), ca.MX.sym("ff", 3, b)
    gains_mx = ca.MX.sym("gains", len(PD_PARAMETERS))
    zs, counts_out, tcs_out = acc(z0, refs, ffs, eff, pp, gains_mx)
    return ca.Function(f"falcon_plant_pd_{_tag(layout)}_d{d}", [z0, refs, ffs, eff, pp, gains_mx],
                       [zs, counts_out, tcs_out], ["z0", "ref", "ff", "eff", "pp", "gains"],
                       ["z", "counts", "tc"])


TIMED_LINE = 12
"""Commands the timed PD chunk remembers (:func:`timed_pd_chunk`): a command still acts at
most this many ticks after it was computed (a transport delay of up to ~10 periods)."""
TIMED_PD_PARAMETERS = ("kp", "kd", "alpha", "limit")
"""Order of the PD gains vector of :func:`timed_pd_chunk` (the rate comes per tick)."""


@lru_cache(maxsize=None)
def timed_pd_chunk(layout: PlantLayout, merged: bool = True) -> ca.Function:
    """BATCH_CHUNK periods of the encoder PD closed loop with ticks at given periods and a
    command path given as weights (the discrepancy replay's real timing). Per period j:

    - the reading is the counts of (1 - w) enc_{j-1} + w enc_j (enc the plant's fractional
      counts at the period boundaries: a reading that arrived a share w of the period
      after the previous boundary), rounded half up; or, for a tick that used the previous
      tick's reading again (fresh 0: no new status had arrived), that reading's counts;
    - if a tick runs in it (flag 1), the PD (:func:`~falcon_plan.control.pd_law`, its count
      difference scaled by the tick's rate) computes a command from that reading, which
      enters a line of the last :data:`TIMED_LINE` commands (newest first); else nothing
      changes;
    - the command acting over the period is sum_m W[m] line[m] (W given per period: the
      shares of the period each remembered command acted in, zero-order hold included).

    z = [x, v_filtered, n_prev, enc_prev, line (3 TIMED_LINE)]. (z0, REF (3, B), FF (3, B),
    TICK (4, B) = [flag, rate [Hz], w, fresh], W (TIMED_LINE, B), eff, pp, gains
    (TIMED_PD_PARAMETERS)) -> (Z, COUNTS (3, B), TC (3, B)); ``merged`` as for
    :func:`plant_functions`."""
    fns = plant_functions(layout, merged)
    n, b, lines = layout.n_states, BATCH_CHUNK, TIMED_LINE
    eff, pp = ca.MX.sym("eff", N_EFFECTS), ca.MX.sym("pp", len(PLANT_PARAMETERS))
    z = ca.SX.sym("z", n + 9 + 3 * lines)
    ref, ff, tick, weights = ca.SX.sym("ref", 3), ca.SX.sym("ff", 3), ca.SX.sym("tick", 4), ca.SX.sym("w", lines)
    eff_s, pp_s = ca.SX.sym("eff", N_EFFECTS), ca.SX.sym("pp", len(PLANT_PARAMETERS))
    gains = ca.SX.sym("gains", len(TIMED_PD_PARAMETERS))
    x, v, n_prev, enc_prev, line = z[0:n], z[n:n + 3], z[n + 3:n + 6], z[n + 6:n + 9], z[n + 9:]
    enc, _ = fns.encoder(x, eff_s)
    flag, rate, share, fresh = tick[0], tick[1], tick[2], tick[3]
    counts = ca.if_else(fresh > 0.5, ca.floor((1 - share) * enc_prev + share * enc + 0.5), n_prev)
    g = {name: gains[i] for i, name in enumerate(TIMED_PD_PARAMETERS)}
    tc, v_new = pd_law(counts, n_prev, v, ref, ff, g["kp"], g["kd"], g["alpha"], rate, g["limit"],
                       ops=_CASADI_OPS)
    ticked = flag > 0.5
    line_new = ca.if_else(ticked, ca.vertcat(tc, line[:-3]), line)
    acting = sum(weights[m] * line_new[3 * m:3 * m + 3] for m in range(lines))
    x_next = fns.period(x, acting, eff_s, pp_s)[0]
    z_next = ca.vertcat(x_next, ca.if_else(ticked, v_new, v), ca.if_else(ticked, counts, n_prev), enc, line_new)
    step = ca.Function("plant_timed_pd_period", [z, ref, ff, tick, weights, eff_s, pp_s, gains],
                       [z_next, counts, tc])
    acc = step.mapaccum("plant_timed_pd_acc", b, [0], [0])
    z0 = ca.MX.sym("z0", z.numel())
    refs, ffs, ticks = ca.MX.sym("ref", 3, b), ca.MX.sym("ff", 3, b), ca.MX.sym("tick", 4, b)
    ws = ca.MX.sym("w", lines, b)
    gains_mx = ca.MX.sym("gains", len(TIMED_PD_PARAMETERS))
    zs, counts_out, tcs_out = acc(z0, refs, ffs, ticks, ws, eff, pp, gains_mx)
    return ca.Function(f"falcon_plant_timed_pd_{_tag(layout)}", [z0, refs, ffs, ticks, ws, eff, pp, gains_mx],
                       [zs, counts_out, tcs_out], ["z0", "ref", "ff", "tick", "w", "eff", "pp", "gains"],
                       ["z", "counts", "tc"])


KINDS = ("period", "open_loop", "pd", "timed_pd")
"""The plant's compiled Functions: one period, the open-loop chunk, the PD chunk and the
timed PD chunk."""


def plant_function(layout: PlantLayout, kind: str, delay_samples: int, merged: bool = True) -> ca.Function:
    """The Function of ``kind`` (one of KINDS) for the plant of ``layout``; ``delay_samples``
    is the PD chunk's command delay line [periods] (ignored by the other kinds); ``merged``
    as for :func:`plant_functions`."""
    if kind == "period":
        return plant_functions(layout, merged).period
    if kind == "open_loop":
        return open_loop_chunk(layout, merged)
    if kind == "timed_pd":
        return timed_pd_chunk(layout, merged)
    return pd_chunk(layout, delay_samples, merged)


LIBRARY_SOURCES = ("sim/equations.py", "sim/batch.py", "control.py", "compiled/build.py", "model")
"""The sources a plant Function is made from (relative to the package): a change in any of
them is a new recipe (:func:`_library`)."""
FLAGS = ("-O2", "-march=native")
"""Compiler options of the plant's libraries. Measured on the identification of a Stribeck case
recorded on a busy host (whole workflow, quiet machine): 4.5 s at ``-O2``, 4.8 s at ``-O3``,
4.3 s at ``-O3 -march=native -ffp-contract=off`` and 4.0 s at ``-O2 -march=native``: the gain
is the machine's fused multiply-add, as for the planner's step. (So the compiled PD's filtered
velocity differs from the same law stepped in Python in the last bits; counts and commands
do not.)"""


@lru_cache(maxsize=None)
def _library(layout: PlantLayout, kind: str, delay_samples: int) -> tuple[Path, str] | None:
    """(the compiled shared object of a plant function, its symbol), built once per machine,
    then found: named by the unmerged Function, compiled from the merged one, and recorded by
    a recipe (:func:`~falcon_plan.compiled.build.recipe_file`) so that later processes load it
    without building the Function (0.1-0.5 s a layout); None without a compiler."""
    def build() -> tuple[Path | None, str]:
        unmerged = plant_function(layout, kind, delay_samples, merged=False)
        return build_shared_library(unmerged.name(), [unmerged], FLAGS,
                                    cse=lambda: [plant_function(layout, kind, delay_samples)]), unmerged.name()

    return library_by_recipe(recipe_file(f"falcon_plant_{kind}", LIBRARY_SOURCES, layout, kind, delay_samples, FLAGS),
                             build)


def buffered_plant_function(layout: PlantLayout, kind: str, delay_samples: int, *,
                            compile: bool = True) -> BufferedFunction:
    """:func:`plant_function` ready to call in place: compiled to C when ``compile`` (and a
    compiler is there), else evaluated by CasADi. ``layout``, ``kind``, ``delay_samples`` as
    for :func:`plant_function`."""
    with BUILDING:
        built = _library(layout, kind, delay_samples) if compile else None
        if built is None:
            return BufferedFunction(plant_function(layout, kind, delay_samples))
        # a compiled library gives the Function's sizes itself: nothing built in this process
        library, symbol = built
        return BufferedFunction(ca.external(symbol, str(library)), library=library)


def run_chunks(fn: BufferedFunction, z0: np.ndarray, per_step: list[np.ndarray], fixed: list[np.ndarray]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run a chunked plant Function (:func:`open_loop_chunk` or :func:`pd_chunk`) over all K
    columns of its per-step inputs, BATCH_CHUNK at a time, carrying the state across chunks.

    ``fn``: the Function, inputs (z0, per-step arrays (3, B)..., fixed inputs...); ``z0``: the
    initial state; ``per_step``: arrays (3, K), one column per period; ``fixed``: the inputs
    that do not change (eff, pp, then e.g. the PD gains). Returns its three outputs, each
    (rows, K)."""
    k_total = per_step[0].shape[1]
    n_step = len(per_step)
    for j, value in enumerate(fixed):
        fn.inputs[n_step + 1 + j][:] = value
    outs = [np.empty((fn.outputs[j].shape[0], k_total)) for j in range(3)]
    fn.inputs[0][:] = z0
    for start in range(0, k_total, BATCH_CHUNK):
        used = min(BATCH_CHUNK, k_total - start)
        for i, arr in enumerate(per_step):
            fn.inputs[1 + i][:, :used] = arr[:, start:start + used]
            fn.inputs[1 + i][:, used:] = arr[:, start + used - 1:start + used]
        fn()
        for out, result in zip(outs, fn.outputs):
            out[:, start:start + used] = result[:, :used]
        fn.inputs[0][:] = fn.outputs[0][:, used - 1]
    return outs[0], outs[1], outs[2]
