"""Speed of the model's kinematics and inverse dynamics, as ratios against named references.

Rows (each measured in this run, on the same points):

- batch forward kinematics (``forward_kinematics`` on N leg-angle triples, default 1e6: the
  compiled Newton iteration) against the guarded numpy Newton path on the same points (the
  previous implementation) and ``scipy.optimize.fsolve`` solving IK(p) = theta1 for one point
  at a time;
- single-point forward kinematics (``forward_kinematics_point``), cold (look-up-table seed)
  and warm-started (seed 0.5 mm away, as from the previous control sample), against fsolve
  cold (seeded at the workspace centre, (0, 0, 0.12) m; its misses are counted) and warm
  (the same 0.5 mm seed);
- one inverse-dynamics evaluation (``model.functions.inverse_dynamics``, the CasADi Function)
  against a plain-numpy reference (``tests/model/numpy_reference.py``: a numeric Lagrangian
  with finite-difference body Jacobians, so slow by construction), and the batched numpy face
  ``FalconModel.inverse_dynamics`` on (n, 3) arrays (compiled chunks) against CasADi's
  ``map`` of the same Function in the virtual machine (the previous implementation).

Usage: ``python benchmarks/bench_model.py [--points N] [--single M] [--out results.json]``.
Timings vary run to run (a shared 2-core machine); trust the ratios more than the absolutes.
The batch rows also give points per CPU second (process time), which other processes
sharing the cores do not inflate.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import statistics
import sys
import time
import warnings
from pathlib import Path
from types import ModuleType
from typing import Any, Callable

import numpy as np
from scipy.optimize import fsolve

from falcon_plan.commands.common import progress
from falcon_plan.model import kinematics
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.kinematics import forward_kinematics, forward_kinematics_point, inverse_kinematics
from falcon_plan.model.params import ACRA2009
from falcon_plan.model.workspace import sample_workspace

REFERENCE_PATH = Path(__file__).resolve().parents[1] / "tests" / "model" / "numpy_reference.py"


def load_reference() -> ModuleType:
    """The plain-numpy dynamics reference, loaded by path (the test tree is not a package)."""
    spec = importlib.util.spec_from_file_location("falcon_numpy_reference", REFERENCE_PATH)
    if spec is None or spec.loader is None:
        raise FileNotFoundError(f"numpy reference not found at {REFERENCE_PATH}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def time_per_call_us(fn: Callable[[], Any], calls: int, repeats: int = 3) -> float:
    """Median over ``repeats`` of the mean time of ``calls`` calls [microseconds]."""
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(calls):
            fn()
        runs.append((time.perf_counter() - start) / calls * 1e6)
    return statistics.median(runs)


def fsolve_fk(theta1: np.ndarray, seed_m: np.ndarray) -> np.ndarray:
    """Reference FK: scipy's fsolve (MINPACK hybrd, numeric Jacobian) on IK(p) - theta1 = 0."""
    def residual(p: np.ndarray) -> np.ndarray:
        return inverse_kinematics(p, strict=False).theta1 - theta1
    return fsolve(residual, seed_m, xtol=1e-13)


def run(points: int, single: int) -> dict[str, Any]:
    """Measure everything; returns the results as a dict (times in microseconds)."""
    rng = np.random.default_rng(0)
    pts = sample_workspace(points, rng)
    theta1 = inverse_kinematics(pts).theta1
    forward_kinematics(theta1[:10])  # build the seed table outside the timing

    start, cpu = time.perf_counter(), time.process_time()
    batch = forward_kinematics(theta1)
    batch_s, batch_cpu_s = time.perf_counter() - start, time.process_time() - cpu
    batch_err = float(np.abs(batch - pts).max())
    n_np = min(points, 200_000)
    saved = kinematics.FK_COMPILED_MIN_POINTS
    kinematics.FK_COMPILED_MIN_POINTS = 10 ** 18           # force the numpy Newton path
    try:
        start = time.perf_counter()
        numpy_batch = forward_kinematics(theta1[:n_np])
        numpy_s = time.perf_counter() - start
    finally:
        kinematics.FK_COMPILED_MIN_POINTS = saved
    numpy_err = float(np.abs(numpy_batch - pts[:n_np]).max())

    sub_pts, sub_th = pts[:single], theta1[:single]
    warm_seeds = sub_pts + 0.5e-3 / np.sqrt(3)
    centre = np.array([0.0, 0.0, 0.12])

    def loop(fn: Callable[[int], Any]) -> Callable[[], None]:
        counter = iter(range(10 ** 12))
        return lambda: fn(next(counter) % single)

    th_tuples = [tuple(map(float, t)) for t in sub_th]
    seed_tuples = [tuple(map(float, s)) for s in warm_seeds]
    cold_us = time_per_call_us(loop(lambda i: forward_kinematics_point(th_tuples[i])), single)
    warm_us = time_per_call_us(loop(lambda i: forward_kinematics_point(th_tuples[i], seed_m=seed_tuples[i])), single)
    n_ref = min(single, 300)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        fsolve_cold_us = time_per_call_us(loop(lambda i: fsolve_fk(sub_th[i], centre)), n_ref, repeats=1)
        fsolve_warm_us = time_per_call_us(loop(lambda i: fsolve_fk(sub_th[i], warm_seeds[i])), n_ref, repeats=1)
    with warnings.catch_warnings():  # fsolve warns when it stalls; counted as failures below
        warnings.simplefilter("ignore", RuntimeWarning)
        fsolve_cold_err = np.array([np.abs(fsolve_fk(sub_th[i], centre) - sub_pts[i]).max() for i in range(n_ref)])
        fsolve_warm_err = np.array([np.abs(fsolve_fk(sub_th[i], warm_seeds[i]) - sub_pts[i]).max()
                                    for i in range(n_ref)])
    single_err = max(float(np.abs(np.array(forward_kinematics_point(th_tuples[i])) - sub_pts[i]).max())
                     for i in range(single))

    model = FalconModel(ACRA2009)
    fn = model.functions.inverse_dynamics
    eff = model.effect_vector
    vel = rng.normal(scale=0.3, size=(single, 3))
    acc = rng.normal(scale=5.0, size=(single, 3))
    casadi_us = time_per_call_us(loop(lambda i: fn(sub_pts[i], vel[i], acc[i], eff)), single)
    ref = load_reference()
    n_id = min(single, 200)
    numpy_us = time_per_call_us(loop(lambda i: ref.inverse_dynamics(sub_pts[i], vel[i], acc[i], ACRA2009)),
                                n_id, repeats=1)
    id_err = max(float(np.abs(ref.inverse_dynamics(sub_pts[i], vel[i], acc[i], ACRA2009)
                              - np.asarray(fn(sub_pts[i], vel[i], acc[i], eff)).ravel()).max()) for i in range(20))
    n_batch = min(points, 200_000)
    bp, bv, ba = pts[:n_batch], rng.normal(scale=0.3, size=(n_batch, 3)), rng.normal(scale=5.0, size=(n_batch, 3))
    model.inverse_dynamics(bp[:100], bv[:100], ba[:100])      # build / load the compiled chunk
    start, cpu = time.perf_counter(), time.process_time()
    batched = model.inverse_dynamics(bp, bv, ba)
    batched_s, batched_cpu_s = time.perf_counter() - start, time.process_time() - cpu
    n_vm = min(n_batch, 20_000)
    start = time.perf_counter()
    vm = np.asarray(fn.map(n_vm)(bp[:n_vm].T, bv[:n_vm].T, ba[:n_vm].T, np.repeat(eff[:, None], n_vm, 1))).T
    vm_s = time.perf_counter() - start
    batched_vs_vm = float(np.abs(batched[:n_vm] - vm).max())

    return {
        "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine()},
        "fk_batch": {"points": points, "seconds": batch_s, "points_per_s": points / batch_s,
                     "points_per_cpu_s": points / batch_cpu_s,
                     "max_error_m": batch_err, "numpy_path_points_per_s": n_np / numpy_s,
                     "numpy_path_max_error_m": numpy_err,
                     "ratio_vs_numpy_path": (points / batch_s) / (n_np / numpy_s),
                     "fsolve_points_per_s": 1e6 / fsolve_cold_us,
                     "ratio_vs_fsolve": (points / batch_s) / (1e6 / fsolve_cold_us)},
        "fk_single": {"cold_us": cold_us, "warm_us": warm_us, "max_error_m": single_err,
                      "fsolve_cold_us": fsolve_cold_us, "fsolve_warm_us": fsolve_warm_us,
                      "fsolve_points": n_ref,
                      "fsolve_cold_failures": int((fsolve_cold_err > 1e-9).sum()),
                      "fsolve_warm_max_error_m": float(fsolve_warm_err.max()),
                      "speedup_cold": fsolve_cold_us / cold_us, "speedup_warm": fsolve_warm_us / warm_us},
        "inverse_dynamics": {"casadi_function_us": casadi_us, "numpy_reference_us": numpy_us,
                             "speedup": numpy_us / casadi_us,
                             "batched_points": n_batch, "batched_points_per_s": n_batch / batched_s,
                             "batched_points_per_cpu_s": n_batch / batched_cpu_s,
                             "vm_map_points_per_s": n_vm / vm_s,
                             "ratio_batched_vs_vm_map": (n_batch / batched_s) / (n_vm / vm_s),
                             "batched_vs_vm_max_difference": batched_vs_vm,
                             "max_difference_commands": id_err},
    }


def print_table(res: dict[str, Any]) -> None:
    """A small human-readable table of the results."""
    fb, fs, inv = res["fk_batch"], res["fk_single"], res["inverse_dynamics"]
    rows = [
        ("FK batch", f"{fb['points_per_s']:.3g} pts/s", f"fsolve {fb['fsolve_points_per_s']:.3g} pts/s",
         f"{fb['ratio_vs_fsolve']:.0f}x"),
        ("FK batch", f"{fb['points_per_s']:.3g} pts/s", f"numpy Newton {fb['numpy_path_points_per_s']:.3g} pts/s",
         f"{fb['ratio_vs_numpy_path']:.1f}x"),
        ("FK single, cold", f"{fs['cold_us']:.1f} us", f"fsolve {fs['fsolve_cold_us']:.0f} us",
         f"{fs['speedup_cold']:.0f}x"),
        ("FK single, warm", f"{fs['warm_us']:.1f} us", f"fsolve {fs['fsolve_warm_us']:.0f} us",
         f"{fs['speedup_warm']:.0f}x"),
        ("inverse dynamics", f"{inv['casadi_function_us']:.1f} us", f"numpy ref {inv['numpy_reference_us']:.0f} us",
         f"{inv['speedup']:.0f}x"),
        ("inverse dyn., batched", f"{inv['batched_points_per_s']:.3g} pts/s",
         f"VM map {inv['vm_map_points_per_s']:.3g} pts/s", f"{inv['ratio_batched_vs_vm_map']:.0f}x"),
    ]
    print(f"{'measure':24s} {'ours':>18s} {'reference':>24s} {'ratio':>7s}")
    for name, ours, reference, ratio in rows:
        print(f"{name:24s} {ours:>18s} {reference:>24s} {ratio:>7s}")
    print(f"per CPU second (process time; wall time is inflated when other processes share the cores): "
          f"FK batch {fb['points_per_cpu_s']:.3g} pts/s, inverse dynamics batched "
          f"{inv['batched_points_per_cpu_s']:.3g} pts/s")
    print(f"max errors: FK batch {fb['max_error_m']:.1e} m, FK single {fs['max_error_m']:.1e} m, "
          f"fsolve warm {fs['fsolve_warm_max_error_m']:.1e} m; fsolve from the centre (0, 0, 0.12) missed "
          f"{fs['fsolve_cold_failures']}/{fs['fsolve_points']} points (> 1e-9 m); inverse dynamics vs reference "
          f"{inv['max_difference_commands']:.1e} command units; batched vs VM map "
          f"{inv['batched_vs_vm_max_difference']:.1e}; FK numpy path {fb['numpy_path_max_error_m']:.1e} m")


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark, print the table, write JSON to ``--out`` if given."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=1_000_000, help="batch FK size (default 1e6)")
    parser.add_argument("--single", type=int, default=2000, help="points for the per-call timings (default 2000)")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = parser.parse_args(argv)
    if args.points < 1 or args.single < 20:
        parser.error("--points must be >= 1 and --single >= 20")
    with progress("timing forward kinematics and inverse dynamics against the references"):
        res = run(args.points, args.single)
    print_table(res)
    if args.out is not None:
        args.out.write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
