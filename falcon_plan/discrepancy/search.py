"""Scalar searches of the workflow whose every trial is costly (a closed-loop replay, or a refit
on a re-read log): successive parabolic interpolation from points already evaluated, and the
curvature of the criterion at its minimum (for a standard deviation)."""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

GOLDEN = 0.381966
"""Fraction of the larger side where a step goes when the parabola gives no usable vertex."""


def parabolic_minimum(f: Callable[[float], float], points: dict[float, float], lo: float, hi: float,
                      tol: float, max_evals: int) -> tuple[float, float]:
    """Minimise ``f`` on [lo, hi] starting from ``points`` ({x: f(x)}, at least 2, updated in
    place with every new evaluation). Each step puts a parabola through the best point and
    its two neighbours and evaluates its vertex (see :func:`_step`); while the best point is
    at an end, the step goes outward by twice the last spacing instead (clipped to the
    bounds); at a bound, one step inward (:func:`_inward`: the minimum may lie between the
    bound and its neighbour; if that step does not beat the bound, the search ends there).
    Stops when the best point's bracket is shorter than 2 ``tol`` on both sides (same unit as
    x) or after ``max_evals`` evaluations. Returns (x, f(x)) of the best point."""
    probed: set[float] = set()     # bounds already probed inward
    for _ in range(max_evals):
        xs = sorted(points)
        i = min(range(len(xs)), key=lambda j: points[xs[j]])
        if i in (0, len(xs) - 1):
            edge, inner = xs[i], xs[1 if i == 0 else -2]
            new = min(max(edge + 2 * (edge - inner), lo), hi)
            if abs(new - edge) < tol:
                new = None if edge in probed else _inward(xs if i == 0 else xs[::-1], points, tol)
                if new is None:
                    break
                probed.add(edge)
        else:
            new = _step(xs[i - 1], xs[i], xs[i + 1], points, tol)
            if new is None:
                break
        points[new] = f(new)
    best = min(points, key=lambda x: points[x])
    return best, points[best]


def _step(a: float, b: float, c: float, points: dict[float, float], tol: float) -> float | None:
    """The next trial inside the bracket a < b < c (b the best), or None once both sides of
    the bracket are shorter than 2 tol. The parabola's vertex, unless it is flat, outside the
    bracket or within tol / 2 of b (then it says nothing new): a golden-section step into the
    larger side instead."""
    if max(c - b, b - a) < 2 * tol:
        return None
    new = _vertex(a, b, c, points)
    if not (a + 0.5 * tol < new < c - 0.5 * tol and abs(new - b) >= 0.5 * tol):
        new = b + GOLDEN * (c - b) if c - b > b - a else b - GOLDEN * (b - a)
    return new


def _inward(xs: list[float], points: dict[float, float], tol: float) -> float | None:
    """The next trial between the best point ``xs[0]`` (at a bound; ``xs`` ordered away from
    it) and its neighbour ``xs[1]``, or None once they are closer than 2 tol: the vertex of the
    parabola through the three nearest the bound when it is convex and its vertex falls between
    them (tol / 2 clear of both), else a golden-section step from the bound. (Without it, a
    search whose outward step reached the bound stopped there: a backlash of 0.025 rad was
    fitted at the 0.04 bound from trials at 0.006 and 0.018, where 0.027 was the minimum.)"""
    edge, inner = xs[0], xs[1]
    if abs(inner - edge) < 2 * tol:
        return None
    if len(xs) > 2:
        a, b, c = sorted(xs[:3])
        convex = (points[c] - points[b]) / (c - b) > (points[b] - points[a]) / (b - a)
        vertex = _vertex(a, b, c, points)
        if convex and min(edge, inner) + 0.5 * tol < vertex < max(edge, inner) - 0.5 * tol:
            return vertex
    return edge + GOLDEN * (inner - edge)


def _vertex(a: float, b: float, c: float, points: dict[float, float]) -> float:
    """x of the vertex of the parabola through a < b < c and their values in ``points`` (nan
    when they are collinear)."""
    fa, fb, fc = points[a], points[b], points[c]
    num = (b - a) ** 2 * (fb - fc) - (b - c) ** 2 * (fb - fa)
    den = (b - a) * (fb - fc) - (b - c) * (fb - fa)
    return b - 0.5 * num / den if den != 0 else math.nan


def curvature(points: dict[float, float], x: float, n_nearest: int = 4) -> float:
    """Second derivative of the criterion at ``x``: a least-squares parabola through the
    ``n_nearest`` evaluated points closest to x (more if it comes out flat or concave); 0 when
    none is convex."""
    xs = np.array(sorted(points, key=lambda p: abs(p - x)))
    for n in range(min(n_nearest, xs.size), xs.size + 1):
        if n < 3:
            continue
        near = xs[:n]
        a = np.polyfit(near - x, [points[p] for p in near], 2)[0]
        if a > 0:
            return 2.0 * float(a)
    return 0.0
