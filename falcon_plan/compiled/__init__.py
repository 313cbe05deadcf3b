"""Compiled CasADi Functions: the one home of the plumbing that turns a CasADi Function into
fast machine code, used by the model (batched inverse dynamics, forward kinematics), the
simulated plant (its per-period step), the discrepancy workflow and the planner's kernels.

- :mod:`falcon_plan.compiled.build`: generate C, compile it once per machine, keep the shared
  library in a disk cache keyed by a hash of the Functions' serialisation, the compiler, its
  flags and the CasADi version, with a lock so that concurrent processes compile it only once;
- :mod:`falcon_plan.compiled.inplace`: call a compiled Function through :mod:`ctypes` on
  numpy buffers filled and read in place (:class:`BufferedFunction`), with the CasADi
  virtual machine as the fallback when there is no compiler;
- :mod:`falcon_plan.compiled.external`: a Function and its Jacobian compiled and loaded back
  with ``casadi.external`` (:func:`compile_with_jacobian`), so that it still maps and
  differentiates inside MX graphs (the planner's per-point kernels).
"""
from falcon_plan.compiled.build import (COMPILE_TIMEOUT_S, build_shared_library, cache_dir, compiler,
                                        generate_source, load_functions, merged, with_companions)
from falcon_plan.compiled.external import compile_with_jacobian
from falcon_plan.compiled.inplace import BufferedFunction, build_library, compiled_points

__all__ = ["BufferedFunction", "COMPILE_TIMEOUT_S", "build_library", "build_shared_library", "cache_dir",
           "compile_with_jacobian", "compiled_points", "compiler", "generate_source", "load_functions", "merged", "with_companions"]
