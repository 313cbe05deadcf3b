"""Compiled CasADi Functions: same numbers as CasADi, cached once, graceful fallback."""
from __future__ import annotations

import logging
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from falcon_plan.model.dynamics import FalconModel
from falcon_plan.compiled import cache_dir, compiler
from falcon_plan.compiled import BufferedFunction, build_library
from falcon_plan.sim.plant import SimPlant

needs_cc = pytest.mark.skipif(compiler() is None, reason="no C compiler")


def _small() -> ca.Function:
    x, m = ca.SX.sym("x", 3), ca.SX.sym("m", 2, 2)
    return ca.Function("fp_test_small", [x, m], [ca.sin(x) * ca.sum1(ca.vec(m)), m @ x[0:2]])


@needs_cc
def test_compiled_matches_casadi_and_is_cached(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FALCON_PLAN_CACHE", str(tmp_path))
    assert cache_dir() == tmp_path
    fn = _small()
    library = build_library(fn)
    assert library is not None and library.parent == tmp_path
    stamp = library.stat().st_mtime_ns
    assert build_library(fn) == library and library.stat().st_mtime_ns == stamp  # not rebuilt
    fast, slow = BufferedFunction(fn, library), BufferedFunction(fn)
    assert fast.compiled and not slow.compiled
    for buf in (fast, slow):
        buf.inputs[0][:] = [0.1, 0.2, 0.3]
        buf.inputs[1][:] = [[1.0, 2.0], [3.0, 4.0]]
        buf()
    expected = [np.asarray(v) for v in fn([0.1, 0.2, 0.3], ca.DM([[1.0, 2.0], [3.0, 4.0]]))]
    for buf in (fast, slow):
        assert np.allclose(buf.outputs[0], expected[0].ravel(), rtol=1e-14)
        assert np.allclose(buf.outputs[1], expected[1].ravel(), rtol=1e-14)


def test_a_library_for_another_processor_is_never_loaded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Kernels built with -march=native run only on their processor: a cache shared with a
    machine whose processor differs keys (and so builds) its own libraries and recipes."""
    from falcon_plan.compiled import build

    monkeypatch.setenv("FALCON_PLAN_CACHE", str(tmp_path))
    here = build.processor()
    assert here.split("|")[0] and len(here.split("|")) == 3
    fn, flags = [_small()], ("-O2", "-march=native")
    key, recipe = build.cache_key(fn, (), "cc", flags), build.recipe_file("fp_test", ["control.py"], flags)
    assert build.cache_key(fn, (), "cc", flags) == key          # stable on one machine
    monkeypatch.setattr(build, "processor", lambda: here + "-another")
    assert build.cache_key(fn, (), "cc", flags) != key
    assert build.recipe_file("fp_test", ["control.py"], flags) != recipe


def test_no_compiler_falls_back(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("FALCON_PLAN_NO_COMPILE", "1")
    assert compiler() is None and build_library(_small()) is None


@needs_cc
def test_compiler_failure_falls_back_with_a_warning(monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
                                                    caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.setenv("FALCON_PLAN_CACHE", str(tmp_path))
    monkeypatch.setenv("CC", "false")  # a "compiler" that always fails
    with caplog.at_level(logging.WARNING):
        assert build_library(_small()) is None
    assert "failed" in caplog.text and not list(tmp_path.glob("*.part"))


def test_uncompiled_plant_gives_the_same_counts(model: FalconModel) -> None:
    fast, slow = SimPlant(model), SimPlant(model, compile=False)
    assert not slow.compiled
    for plant in (fast, slow):
        plant.reset((0.0, 0.0, 0.125))
    cmds = np.tile([900.0, -400.0, 300.0], (60, 1))
    assert np.array_equal(fast.run_open_loop(cmds), slow.run_open_loop(cmds))
    assert np.allclose(fast.position_m, slow.position_m, rtol=0, atol=1e-12)


@pytest.mark.parametrize("compiled", [False, pytest.param(True, marks=needs_cc)])
def test_map_columns_covers_any_number_of_points(compiled: bool) -> None:
    """A Function mapped over 4 columns, evaluated on 10 points (two full calls and a padded
    one): every column equals the point-by-point evaluation, and the fixed input is kept."""
    x, k = ca.SX.sym("x", 3), ca.SX.sym("k")
    one = ca.Function("fp_test_point", [x, k], [ca.vertcat(k * ca.sin(x[0]) + x[1] * x[2], ca.sum1(x))])
    mapped = one.map("fp_test_map4", "serial", 4, [1], [])
    fn = BufferedFunction(mapped, build_library(mapped) if compiled else None)
    assert fn.compiled == compiled
    fn.inputs[1][...] = 2.5
    points = np.random.default_rng(3).normal(size=(3, 10))
    (out,) = fn.map_columns([points])
    expected = np.hstack([np.asarray(one(points[:, j], 2.5)) for j in range(10)])
    assert out.shape == (2, 10)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-14)


@needs_cc
def test_a_cached_library_is_found_without_generating_c(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The cache key comes from the Functions' serialisation: once built, a library is found
    again without generating C or deriving its companions, and the companions loaded back
    from it give the derived Functions' values; another Function gets another library."""
    from falcon_plan.compiled import build

    monkeypatch.setenv("FALCON_PLAN_CACHE", str(tmp_path))
    fn, companions = _small(), ("jacobian", "reverse")
    library = build.build_shared_library(fn.name(), [fn], ("-O1",), companions)
    assert library is not None

    def refuse(*args: object) -> None:
        raise AssertionError("C generated or companions derived for a cached library")

    with monkeypatch.context() as patch:
        patch.setattr(build, "generate_source", refuse)
        patch.setitem(build.COMPANIONS, "jacobian", ("jac_", refuse))
        assert build.build_shared_library(fn.name(), [fn], ("-O1",), companions) == library
        loaded = build.load_functions(library, [fn], companions)
    derived = build.with_companions([fn], companions)
    assert [f.name() for f in loaded] == [f.name() for f in derived] == build.companion_names([fn], companions)
    rng = np.random.default_rng(0)
    for mine, theirs in zip(loaded, derived):
        args = [rng.normal(size=theirs.size_in(i)) for i in range(theirs.n_in())]
        for a, b in zip(mine.call(args), theirs.call(args)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-13)
    x, m = ca.SX.sym("x", 3), ca.SX.sym("m", 2, 2)
    other = ca.Function("fp_test_small", [x, m], [ca.cos(x) * ca.sum1(ca.vec(m)), m @ x[0:2]])  # same name
    assert build.build_shared_library(other.name(), [other], ("-O1",), companions) != library


@needs_cc
def test_a_fed_input_reads_the_callers_memory_and_a_held_call_keeps_the_gil() -> None:
    """``feed`` points an input at the caller's memory (one matrix of a stack, picked per call,
    nothing copied; a row-major matrix read column-major is its transpose); ``hold_gil`` loads
    the library so that calls keep the interpreter lock (ctypes.PyDLL), the default releases it;
    uncompiled, a fed input reads the same memory."""
    import ctypes

    a, b = ca.SX.sym("a", 2, 2), ca.SX.sym("b", 2)
    fn = ca.Function("fp_test_feed", [a, b], [ca.mtimes(a, b)])
    held = BufferedFunction(fn, build_library(fn), hold_gil=True)
    stack = np.random.default_rng(5).normal(size=(4, 2, 2))
    held.inputs[1][:] = (0.5, -2.0)
    for g in (2, 0, 3):
        held.feed(0, stack.ctypes.data + g * stack.strides[0])
        held()
        np.testing.assert_allclose(held.outputs[0], stack[g].T @ [0.5, -2.0], rtol=0, atol=1e-14)
    assert held._lib._func_flags_ & ctypes._FUNCFLAG_PYTHONAPI
    assert not BufferedFunction(fn, build_library(fn))._lib._func_flags_ & ctypes._FUNCFLAG_PYTHONAPI
    uncompiled = BufferedFunction(fn)           # the fallback: a fed input is copied in per call
    uncompiled.inputs[1][:] = (0.5, -2.0)
    for g in (1, 3):
        uncompiled.feed(0, stack.ctypes.data + g * stack.strides[0])
        uncompiled()
        np.testing.assert_allclose(uncompiled.outputs[0], stack[g].T @ [0.5, -2.0], rtol=0, atol=1e-14)


@needs_cc
def test_the_inverse_dynamics_evaluator_is_loaded_by_its_recipe(model: FalconModel,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Once built, the identification's evaluator of the inverse dynamics and its Jacobian is
    loaded in a later process from its recipe without deriving the Jacobian, and it gives
    what the derived Function gives (the CasADi virtual machine on the same expressions)."""
    from falcon_plan.discrepancy import identify

    monkeypatch.setattr(identify, "_evaluators", {})
    built = identify._chunk_evaluator(model)        # built, or already loaded by its recipe
    monkeypatch.setattr(identify, "_evaluators", {})   # a later process
    identify._id_jacobian.cache_clear()

    def refuse(*args: object) -> None:
        raise AssertionError("the Jacobian was derived though the recipe records its library")

    with monkeypatch.context() as patch:
        patch.setattr(identify.ca, "jacobian", refuse)
        loaded = identify._chunk_evaluator(model)
    assert loaded.compiled and loaded.name == built.name
    ex = model.functions.expressions
    tc = model.functions.inverse_dynamics(ex.p, ex.v, ex.a, ex.eff)
    reference = ca.Function("id_reference", [ex.p, ex.v, ex.a, ex.eff], [tc, ca.densify(ca.jacobian(tc, ex.eff))])
    rng = np.random.default_rng(7)
    rows = identify.CHUNK_ROWS
    p = np.array([0.0, 0.0, 0.125])[:, None] + rng.uniform(-0.02, 0.02, (3, rows))
    v, a = rng.normal(0.0, 0.2, (3, rows)), rng.normal(0.0, 3.0, (3, rows))
    eff = model.effect_vector
    for i, value in enumerate((p, v, a)):
        loaded.inputs[i][:] = value
    loaded.inputs[3][:] = eff
    loaded()
    n_eff = eff.size
    for k in (0, 17, rows - 1):
        tc_k, jac_k = (np.asarray(x) for x in reference(p[:, k], v[:, k], a[:, k], eff))
        np.testing.assert_allclose(loaded.outputs[0][:, k], tc_k.ravel(), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(loaded.outputs[1].reshape(3, rows, n_eff)[:, k], jac_k, rtol=1e-9, atol=1e-9)
