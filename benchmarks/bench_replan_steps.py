"""Steps from rest along a moving target's path (issue 24 item 5): the plans a moving target's
goals get once the device rests at each goal (``replan_from_rest``).

The demo's circle (``circle_target`` about the home point) sampled as the demo sends its goals
(``MOVING_UPDATE_HZ``, ``MOVING_LEAD_S`` ahead: service/commands/demo.py); each step plans from
the last goal, at rest, warm-started from the last step's plan.
Per search (``replan_search`` "shortest" and "first"): how many steps were planned warm (the
running pattern, then the leg-space model's guesses) or by the pipeline, the replan time p50 /
p90 against a cold rest-to-rest plan timed in the same run, and every step's gap to an
independent refined solve (the pipeline with refinement: its converged duration).

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_replan_steps.py [--steps 79]
"""
from __future__ import annotations

import argparse
import collections
import json
import time

import numpy as np

from falcon_plan.model.kinematics import counts_to_position
from falcon_plan.moving_target import circle_target
from falcon_plan.planning.api import default_model, plan_problem
from falcon_plan.planning.problem import PlanOptions, PlanProblem
from falcon_plan.planning.replan import Replan, replan_from_rest
from service.commands.demo import MOVING_LEAD_S, MOVING_UPDATE_HZ


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=79)
    args = parser.parse_args()
    model = default_model()
    home = counts_to_position(np.zeros(3))
    target = circle_target(home)
    precise = PlanOptions.of(crosscheck=False, plant_check=False)
    reference = PlanProblem(tuple(home), tuple(target(0.0)))
    plan_problem(reference, PlanOptions.fast(), model)
    cold = []
    for _ in range(5):
        t0 = time.perf_counter()
        plan_problem(reference, PlanOptions.fast(), model)
        cold.append(time.perf_counter() - t0)
    ref_ms = 1e3 * float(np.median(cold))
    for search in ("shortest", "first"):
        options = PlanOptions.fast(replan_search=search)
        running = Replan.of_plan(plan_problem(reference, options, model))
        here = target(0.0)
        times, gaps, methods = [], [], collections.Counter()
        for k in range(1, args.steps + 1):
            goal = target(k / MOVING_UPDATE_HZ + MOVING_LEAD_S)
            made = replan_from_rest(running, here, goal, options=options, model=model)
            best = plan_problem(made.problem, precise, model).report
            times.append(1e3 * made.solve_time_s)
            gaps.append(made.duration_s / (best.converged_duration_s or best.duration_s) - 1.0)
            methods[made.method] += 1
            running, here = made, goal
        t, g = np.array(times), np.array(gaps)
        print(json.dumps({"search": search, "steps": len(t), "methods": dict(methods), "cold_plan_ms": ref_ms,
                          "p50_ms": float(np.median(t)), "p90_ms": float(np.percentile(t, 90)),
                          "p50_over_cold_plan": float(np.median(t)) / ref_ms,
                          "p90_over_cold_plan": float(np.percentile(t, 90)) / ref_ms,
                          "gap_max_percent": 100 * float(g.max()), "gap_median_percent": 100 * float(np.median(g)),
                          "gap_over_0.3_percent": int(np.sum(g > 0.003))}))


if __name__ == "__main__":
    main()
