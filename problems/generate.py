"""Generate the benchmark problem files of this folder (deterministic).

Run ``python problems/generate.py`` to (re)write ``problems/<name>.json``, or with ``--check``
to verify that the files on disk are exactly what this script makes (exit code 1 if not).

Every problem is checked before it is written:

- a problem expected to be solved has its start, goal and via points inside the workspace
  with a margin of ``MARGIN_DEG`` on every leg-angle limit (``check_workspace`` with
  ``limits.scaled``), its straight-line segments inside the workspace, and holding commands
  against gravity (with its payload) at every point below ``HOLD_FRACTION`` of its tc_max,
  so that there is authority left to accelerate;
- a refusal is refused for exactly its stated reason: ``outside_workspace`` has the start or
  goal outside the workspace; ``via_unreachable`` has start and goal inside but a via point
  outside; ``tc_max_too_small`` has every point inside but the model's holding commands at
  the start exceed tc_max.

Coordinates are rounded to 0.1 mm (velocities to 1 mm/s) before the checks, so the files hold
exactly the numbers that were checked.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from falcon_plan.batch.loader import Expectation, Problem, load_problems
from falcon_plan.model.dynamics import FalconModel
from falcon_plan.model.effects import Effects
from falcon_plan.model.workspace import DEFAULT_LIMITS, check_workspace
from falcon_plan.planning.problem import PlanProblem

HERE = Path(__file__).resolve().parent
SEED = 20091202
"""Seed of the random moves (the ACRA 2009 conference date)."""
MARGIN_DEG = 3.0
"""Margin on every workspace angle limit for the points of solvable problems [deg]."""
HOLD_FRACTION = 0.8
"""Largest holding command, as a fraction of tc_max, allowed in a solvable problem."""
CENTRE_M = np.array([0.0, 0.0, 0.125])
"""Middle of the usable workspace [m] (mean of a uniform sample of it)."""
EDGE_FRACTION = 0.9
"""Edge points sit at this fraction of the distance from the centre to the margin boundary."""

_MODEL = FalconModel()


def _round_point(p: np.ndarray | tuple[float, ...], decimals: int = 4) -> tuple[float, float, float]:
    x, y, z = (round(float(v), decimals) + 0.0 for v in p)
    return (x, y, z)


def edge_point(azimuth_deg: float, elevation_deg: float = 0.0) -> tuple[float, float, float]:
    """A point near the workspace edge in the given direction from :data:`CENTRE_M`:
    :data:`EDGE_FRACTION` of the way to where the margin-tightened limits end (bisection)."""
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    direction = np.array([math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)])
    limits = DEFAULT_LIMITS.scaled(math.radians(MARGIN_DEG))
    lo, hi = 0.0, 0.15
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if check_workspace(CENTRE_M + mid * direction, limits=limits).inside:
            lo = mid
        else:
            hi = mid
    return _round_point(CENTRE_M + EDGE_FRACTION * lo * direction)


def random_moves(count: int, min_length_m: float) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
    """``count`` start/goal pairs drawn uniformly from the margin-tightened workspace, at least
    ``min_length_m`` apart (seeded with :data:`SEED`)."""
    from falcon_plan.model.workspace import sample_workspace

    rng = np.random.default_rng(SEED)
    limits = DEFAULT_LIMITS.scaled(math.radians(MARGIN_DEG))
    moves = []
    while len(moves) < count:
        a, b = sample_workspace(2, rng, limits=limits)
        if np.linalg.norm(a - b) >= min_length_m:
            moves.append((_round_point(a), _round_point(b)))
    return moves


def build_problems() -> list[Problem]:
    """The whole suite, in the order the files are written."""
    problems: list[Problem] = []

    def add(name: str, description: str, start, goal, tags: list[str], *, tc_max: float = 2500,
            via=(), v0=(0.0, 0.0, 0.0), v1=(0.0, 0.0, 0.0), payload_kg: float = 0.0,
            n_intervals: int | None = None, refused: str | None = None) -> None:
        motion = PlanProblem(_round_point(start), _round_point(goal), _round_point(v0, 3), _round_point(v1, 3),
                             tuple(_round_point(p) for p in via), payload_kg)
        problems.append(Problem(
            name=name, description=description, motion=motion, tc_max=float(tc_max), n_intervals=n_intervals,
            tags=tuple(tags),
            expect=Expectation("refused", refused) if refused else Expectation("solved")))

    c = tuple(CENTRE_M)
    cx, cy, cz = c
    # --- short moves, rest to rest ------------------------------------------------------
    add("short_x", "15 mm to the right from the centre", c, (cx + 0.015, cy, cz), ["short", "rest"])
    add("short_y_up", "15 mm up from the centre, against gravity", c, (cx, cy + 0.015, cz), ["short", "rest"])
    add("short_y_down", "15 mm down from the centre, with gravity", c, (cx, cy - 0.015, cz), ["short", "rest"])
    add("short_z", "15 mm toward the user from the centre", c, (cx, cy, cz + 0.015), ["short", "rest"])
    add("short_diagonal", "a 17 mm diagonal move off-centre", (cx - 0.01, cy - 0.01, cz - 0.005),
        (cx, cy, cz + 0.005), ["short", "rest"])
    add("tiny_step", "a 3 mm step, the shortest move of the set", c, (cx + 0.002, cy + 0.002, cz + 0.001),
        ["short", "rest"])
    # --- long moves across the workspace ------------------------------------------------
    add("across_x", "90 mm from left to right through the centre", (cx - 0.045, cy, cz), (cx + 0.045, cy, cz),
        ["long", "across", "rest"])
    add("across_y", "90 mm from bottom to top through the centre", (cx, cy - 0.045, cz), (cx, cy + 0.045, cz),
        ["long", "across", "rest"])
    add("across_z", "80 mm from the back to the front along the axis", (cx, cy, cz - 0.035), (cx, cy, cz + 0.045),
        ["long", "across", "rest"])
    add("across_diagonal", "a 3-D diagonal across the workspace", (cx - 0.025, cy - 0.025, cz - 0.02),
        (cx + 0.025, cy + 0.025, cz + 0.02), ["long", "across", "rest"])
    add("regression_notes", "the displacement (0.03, 0.02, 0.04) m of PLANNING-NOTES' regression case",
        (cx - 0.015, cy - 0.01, cz - 0.02), (cx + 0.015, cy + 0.01, cz + 0.02), ["long", "rest"])
    # --- along and across the edge ------------------------------------------------------
    add("edge_top_to_right", "along the edge from the top to the upper right", edge_point(90), edge_point(30),
        ["edge", "long", "rest"])
    add("edge_left_to_bottom", "along the edge from the left to the lower left", edge_point(180),
        edge_point(240), ["edge", "long", "rest"])
    add("edge_to_edge_x", "from the left edge to the right edge", edge_point(180), edge_point(0),
        ["edge", "across", "long", "rest"])
    add("edge_front_back", "from the back edge to the front edge on the axis", edge_point(0, -90),
        edge_point(0, 90), ["edge", "across", "long", "rest"])
    add("edge_lower_front", "from the lower front edge to the lower right", edge_point(-90, 35),
        edge_point(-30, 20), ["edge", "rest"])
    # --- via points ---------------------------------------------------------------------
    add("via_over_top", "left to right passing over the top", (cx - 0.035, cy, cz), (cx + 0.035, cy, cz),
        ["via", "long", "rest"], via=[(cx, cy + 0.03, cz)])
    add("via_two_points", "a zig-zag through two via points", (cx - 0.03, cy - 0.02, cz),
        (cx + 0.03, cy + 0.02, cz), ["via", "long", "rest"],
        via=[(cx - 0.01, cy + 0.02, cz + 0.01), (cx + 0.01, cy - 0.02, cz - 0.01)])
    add("via_depth", "centre to the right, dipping toward the user", c, (cx + 0.03, cy, cz),
        ["via", "rest"], via=[(cx + 0.015, cy, cz + 0.03)])
    # --- payloads -----------------------------------------------------------------------
    add("payload_50g", "a 40 mm move carrying 50 g", (cx - 0.02, cy, cz), (cx + 0.02, cy, cz),
        ["payload", "rest"], payload_kg=0.05)
    add("payload_100g_up", "a 40 mm lift carrying 100 g", (cx, cy - 0.02, cz), (cx, cy + 0.02, cz),
        ["payload", "rest"], tc_max=3500, payload_kg=0.1)
    add("payload_200g_diag", "a diagonal move carrying 200 g at the full command range",
        (cx - 0.02, cy - 0.015, cz - 0.01), (cx + 0.02, cy + 0.015, cz + 0.01), ["payload", "rest"],
        tc_max=4096, payload_kg=0.2)
    # --- one move at every command limit ------------------------------------------------
    for tc_max in (1500, 2000, 2500, 3500, 4096):
        add(f"tc_sweep_{tc_max}", f"the same 69 mm diagonal move with |Tc| <= {tc_max}",
            (cx - 0.02, cy + 0.02, cz - 0.02), (cx + 0.02, cy - 0.02, cz + 0.02), ["tc_sweep", "rest"],
            tc_max=tc_max)
    # --- from motion --------------------------------------------------------------------
    add("moving_start", "starts moving right at 0.2 m/s, stops 30 mm further", (cx - 0.015, cy, cz),
        (cx + 0.015, cy, cz), ["motion"], v0=(0.2, 0.0, 0.0))
    add("moving_start_reverse", "starts moving left at 0.15 m/s, must turn and go right",
        (cx - 0.01, cy, cz), (cx + 0.03, cy, cz), ["motion"], v0=(-0.15, 0.0, 0.0))
    add("moving_goal", "from rest, arrives moving up at 0.2 m/s", (cx, cy - 0.02, cz), (cx, cy + 0.01, cz),
        ["motion"], v1=(0.0, 0.2, 0.0))
    add("moving_both", "a pass-through segment, moving at both ends", (cx - 0.02, cy - 0.01, cz),
        (cx + 0.02, cy + 0.01, cz), ["motion"], v0=(0.1, 0.0, 0.05), v1=(0.1, 0.05, 0.0))
    # --- grid resolution ----------------------------------------------------------------
    add("coarse_grid", "a 54 mm move on a coarse grid (25 intervals)", (cx - 0.025, cy, cz - 0.01),
        (cx + 0.025, cy, cz + 0.01), ["grid", "rest"], n_intervals=25)
    add("fine_grid", "the same 54 mm move on a fine grid (100 intervals)", (cx - 0.025, cy, cz - 0.01),
        (cx + 0.025, cy, cz + 0.01), ["grid", "rest"], n_intervals=100)
    # --- random moves -------------------------------------------------------------------
    for i, (a, b) in enumerate(random_moves(4, 0.03), start=1):
        add(f"random_{i:02d}", f"random move {i} (seed {SEED}), uniform in the workspace", a, b,
            ["random", "rest"])
    # --- refusals -----------------------------------------------------------------------
    add("refuse_goal_outside", "goal 220 mm out on the axis, past the legs' reach", c, (cx, cy, 0.22),
        ["refusal"], refused="outside_workspace")
    add("refuse_start_outside", "start 100 mm to the right, beyond the legs' reach", (0.1, cy, cz), c,
        ["refusal"], refused="outside_workspace")
    add("refuse_goal_singular", "goal 75 mm to the right, too close to a singular configuration", c,
        (0.075, cy, cz), ["refusal", "edge"], refused="outside_workspace")
    add("refuse_goal_leg_range", "goal 65 mm from the base, the legs would fold below their range", c,
        (cx, cy, 0.065), ["refusal"], refused="outside_workspace")
    add("refuse_via_unreachable", "a via point 120 mm above the centre", (cx - 0.02, cy, cz),
        (cx + 0.02, cy, cz), ["refusal", "via"], via=[(cx, 0.12, cz)], refused="via_unreachable")
    add("refuse_tc_heavy_payload", "300 g payload with |Tc| <= 1500: cannot even hold still", c,
        (cx + 0.02, cy, cz), ["refusal", "payload"], tc_max=1500, payload_kg=0.3, refused="tc_max_too_small")
    add("refuse_tc_low_start", "500 g payload, low start, |Tc| <= 2500: cannot hold still", (cx, cy - 0.03, cz),
        (cx, cy, cz), ["refusal", "payload"], tc_max=2500, payload_kg=0.5, refused="tc_max_too_small")
    return problems


# --- checks ---------------------------------------------------------------------------------
def _inside(points: list[tuple[float, float, float]], margin_deg: float = 0.0) -> bool:
    limits = DEFAULT_LIMITS.scaled(math.radians(margin_deg))
    return bool(np.all(check_workspace(np.asarray(points, dtype=float), limits=limits).inside))


def _holding_max(problem: Problem, point: tuple[float, float, float]) -> float:
    payload_kg = problem.motion.payload_kg
    model = _MODEL.with_effects(Effects(payload_kg=payload_kg)) if payload_kg else _MODEL
    return float(np.max(np.abs(model.holding_commands(np.asarray(point)))))


def check_problem(problem: Problem) -> None:
    """Raise ``AssertionError`` saying why if ``problem`` does not behave as it claims."""
    motion = problem.motion
    ends = [motion.start_m, motion.goal_m]
    if problem.expect.status == "solved":
        waypoints = [motion.start_m, *motion.via_m, motion.goal_m]
        assert _inside(waypoints, MARGIN_DEG), f"{problem.name}: a point is not inside with {MARGIN_DEG} deg margin"
        segments = [np.linspace(a, b, 41) for a, b in zip(waypoints[:-1], waypoints[1:])]
        assert _inside(np.concatenate(segments).tolist()), f"{problem.name}: a straight segment leaves the workspace"
        for p in waypoints:
            hold = _holding_max(problem, p)
            assert hold < HOLD_FRACTION * problem.tc_max, \
                f"{problem.name}: holding needs {hold:.0f} > {HOLD_FRACTION} x tc_max at {p}"
        return
    reason = problem.expect.reason
    if reason == "outside_workspace":
        assert not _inside(ends), f"{problem.name}: start and goal are both inside the workspace"
    elif reason == "via_unreachable":
        assert _inside(ends, MARGIN_DEG), f"{problem.name}: start or goal outside (wrong reason)"
        assert motion.via_m and not _inside(list(motion.via_m)), f"{problem.name}: every via point is inside"
    elif reason == "tc_max_too_small":
        assert _inside(ends + list(motion.via_m), MARGIN_DEG), f"{problem.name}: a point is outside (wrong reason)"
        hold = _holding_max(problem, motion.start_m)
        assert hold > problem.tc_max, f"{problem.name}: holding at the start needs only {hold:.0f} <= tc_max"
    else:
        raise AssertionError(f"{problem.name}: no check for refusal reason {reason!r}")


def problem_text(problem: Problem) -> str:
    """The file content for ``problem``: one key per line, values on one line, trailing
    newline."""
    lines = [f"  {json.dumps(key)}: {json.dumps(value)}" for key, value in problem.to_dict().items()]
    return "{\n" + ",\n".join(lines) + "\n}\n"


def main(argv: list[str] | None = None) -> int:
    """Write (or with --check, verify) the problem files; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="verify the files instead of writing them")
    parser.add_argument("--out", type=Path, default=HERE, help="folder to write to (default: this one)")
    args = parser.parse_args(argv)
    problems = build_problems()
    for problem in problems:
        check_problem(problem)
    names = [p.name for p in problems]
    assert len(set(names)) == len(names), "duplicate problem names"
    stale = sorted(p.name for p in args.out.glob("*.json") if p.stem not in set(names))
    if args.check:
        bad = [p.name for p in problems
               if not (args.out / f"{p.name}.json").is_file()
               or (args.out / f"{p.name}.json").read_text() != problem_text(p)]
        if bad or stale:
            print(f"out of date: {bad}; not generated: {stale}", file=sys.stderr)
            return 1
        print(f"{len(problems)} problem files up to date")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    for path in (args.out / f"{name}.json" for name in stale):
        path.unlink()
    for problem in problems:
        (args.out / f"{problem.name}.json").write_text(problem_text(problem))
    loaded = load_problems([args.out])
    assert [p.name for p in loaded] == sorted(names), "the written files do not load back"
    print(f"wrote {len(problems)} problem files to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
