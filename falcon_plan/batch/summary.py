"""Batch results as files: the table (CSV, Markdown), the summary (JSON) and plots (PNG).

Files written by :func:`write_results` into the output folder:

- ``results.csv``: one row per problem and method, columns :data:`~falcon_plan.batch.runner.COLUMNS`
  (empty cell = no value);
- ``results.md``: the summary per method, then the same table for reading;
- ``summary.json``: :func:`summarise` (success rate per method, median duration ratio against
  the planner, median and p95 solve time, median tracking error, wall time);
- ``durations.png``: each solved problem's duration per method;
- ``solve_times.png``: the distribution of solve times per method.

Everything but the columns in :data:`~falcon_plan.batch.runner.TIMING_COLUMNS` (and the
timing figures of the summary) is a function of the problems and the seed.
"""
from __future__ import annotations

import csv
import io
import json
import math
import statistics
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from falcon_plan.batch.runner import COLUMNS, METHODS, PLANNER, STATUSES, BatchResult, ResultRow
from falcon_plan.fileio import write_text

RESULT_FILES = ("results.csv", "results.md", "summary.json", "durations.png", "solve_times.png")
"""Every file :func:`write_results` writes."""


def _values(rows: Sequence[ResultRow], column: str) -> list[float]:
    return [float(getattr(r, column)) for r in rows if getattr(r, column) is not None]


def _median(values: list[float]) -> float | None:
    return float(statistics.median(values)) if values else None


def _p95(values: list[float]) -> float | None:
    return float(np.percentile(values, 95)) if values else None


def summarise(result: BatchResult) -> dict[str, Any]:
    """Summary figures of the batch ``result``, per method and for the run (JSON-ready;
    ``None`` where no data).

    Per method: ``problems``; ``applicable`` (rows not ``skipped``); ``met`` (outcome as
    the problem expects) and ``success_rate`` (met / applicable); ``solved_rate`` (solved /
    applicable problems expected solved); a count per status; ``median_duration_s``;
    ``median_duration_ratio`` (duration over the planner's, problems both solved);
    ``median_solve_time_s`` and ``p95_solve_time_s``; ``median_track_rms_counts``,
    ``median_track_rms_mm``, ``median_track_max_mm`` (executed planner trajectories).
    """
    methods: dict[str, Any] = {}
    for method in METHODS:
        rows = [r for r in result.rows if r.method == method]
        applicable = [r for r in rows if r.met is not None]
        expected_solved = [r for r in applicable if r.expected == "solved"]
        met = sum(bool(r.met) for r in applicable)
        methods[method] = {
            "problems": len(rows),
            "applicable": len(applicable),
            "met": met,
            "success_rate": met / len(applicable) if applicable else None,
            "solved_rate": (sum(r.status == "solved" for r in expected_solved) / len(expected_solved)
                            if expected_solved else None),
            **{status: sum(r.status == status for r in rows) for status in STATUSES},
            "median_duration_s": _median(_values(rows, "duration_s")),
            "median_duration_ratio": _median(_values(rows, "duration_ratio")),
            "median_solve_time_s": _median(_values(rows, "solve_time_s")),
            "p95_solve_time_s": _p95(_values(rows, "solve_time_s")),
            "median_track_rms_counts": _median(_values(rows, "track_rms_counts")),
            "median_track_rms_mm": _median(_values(rows, "track_rms_mm")),
            "median_track_max_mm": _median(_values(rows, "track_max_mm")),
        }
    planner_rows = [r for r in result.rows if r.method == PLANNER]
    solved = [r for r in planner_rows if r.status == "solved"]
    unavailable = sorted({r.method for r in result.rows if r.status == "unavailable"})
    if result.options.execute and solved and all(r.track_rms_counts is None for r in solved):
        unavailable.append("tracking")
    return {
        "problems": len(planner_rows),
        "seed": result.options.seed,
        "jobs": result.options.workers,
        "quick": result.options.quick,
        "wall_time_s": result.wall_time_s,
        "all_met": all(r.met for r in planner_rows),
        "planner_fallbacks": [r.problem for r in solved if r.note.startswith("ruckig-fallback")],
        "not_met": [r.problem for r in planner_rows if not r.met],
        "unavailable": unavailable,
        "methods": methods,
    }


# --- table ---------------------------------------------------------------------------------
def _cell(value: Any) -> str:
    """CSV cell: empty for None, 9 significant digits for floats."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.9g}"
    return str(value)


def results_csv(rows: Sequence[ResultRow], columns: Sequence[str] = COLUMNS) -> str:
    """The results table as CSV text: a header of ``columns`` (names of :class:`ResultRow`
    fields, default all in :data:`~falcon_plan.batch.runner.COLUMNS` order), then one line
    per row of ``rows``."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_cell(getattr(row, c)) for c in columns])
    return buffer.getvalue()


MARKDOWN_COLUMNS = (("problem", "problem", None), ("method", "method", None),
                    ("expected", "expected", None), ("status", "status", None), ("reason", "reason", None),
                    ("met", "met", None), ("duration_s", "T [ms]", 1e3), ("duration_ratio", "T/T_casadi", 1.0),
                    ("solve_time_s", "solve [ms]", 1e3), ("command_margin", "Tc margin", 1.0),
                    ("workspace_margin", "ws margin", 1.0),
                    ("track_rms_counts", "rms [cnt]", 1.0), ("track_max_counts", "max [cnt]", 1.0),
                    ("track_rms_mm", "rms [mm]", 1.0), ("track_max_mm", "max [mm]", 1.0))
"""(column, heading, scale) of the Markdown table; numbers are shown times ``scale``."""


def _md_number(value: float | None, scale: float) -> str:
    if value is None:
        return "-"
    scaled = value * scale
    return f"{scaled:.3g}" if abs(scaled) < 1000 else f"{scaled:.0f}"


def results_markdown(result: BatchResult, summary: dict[str, Any]) -> str:
    """The summary per method and the full results table of ``result``, as Markdown;
    ``summary`` is :func:`summarise` of ``result``."""
    lines = [f"# Benchmark results ({summary['problems']} problems)", "",
             f"seed {summary['seed']}, {summary['jobs']} job(s), quick={summary['quick']}, "
             f"wall time {summary['wall_time_s']:.1f} s; all expectations met: "
             f"{'yes' if summary['all_met'] else 'no ' + str(summary['not_met'])}"]
    if summary["unavailable"]:
        lines.append(f"unavailable: {', '.join(summary['unavailable'])}")
    lines += ["", "| method | met | solved | median T [ms] | median T/T_casadi | median solve [ms] | "
              "p95 solve [ms] | median rms [cnt] | median rms [mm] |", "|" + "---|" * 9]
    for method, s in summary["methods"].items():
        lines.append(f"| {method} | {s['met']}/{s['applicable']} | {s['solved']} | "
                     f"{_md_number(s['median_duration_s'], 1e3)} | {_md_number(s['median_duration_ratio'], 1.0)} | "
                     f"{_md_number(s['median_solve_time_s'], 1e3)} | {_md_number(s['p95_solve_time_s'], 1e3)} | "
                     f"{_md_number(s['median_track_rms_counts'], 1.0)} | {_md_number(s['median_track_rms_mm'], 1.0)} |")
    lines += ["", "| " + " | ".join(h for _, h, _ in MARKDOWN_COLUMNS) + " |",
              "|" + "---|" * len(MARKDOWN_COLUMNS)]
    for row in result.rows:
        cells = []
        for column, _, scale in MARKDOWN_COLUMNS:
            value = getattr(row, column)
            if scale is not None:
                cells.append(_md_number(value, scale))
            elif column == "met":
                cells.append("n/a" if value is None else "yes" if value else "**no**")
            else:
                cells.append(str(value) or "-")
        lines.append("| " + " | ".join(cells) + " |")
    notes = [f"- {r.problem} / {r.method}: {r.note}" for r in result.rows
             if r.note and (r.method == PLANNER or r.status in ("failed", "error", "unavailable"))]
    if notes:
        lines += ["", "Notes:", *notes]
    return "\n".join(lines) + "\n"


# --- plots ---------------------------------------------------------------------------------
def plot_durations(result: BatchResult, path: Path) -> Any:
    """PNG at ``path``: every problem of ``result``, its duration [ms] per method as grouped
    bars (left; x where a method did not run, and for a problem the planner did not solve,
    e.g. a refusal, its outcome and reason), and each reference's duration over the planner's
    (right, 1 = as fast as the planner). Returns the matplotlib Figure."""
    from matplotlib.figure import Figure  # no pyplot: no global backend or figure state

    problems = list(dict.fromkeys(r.problem for r in result.rows))
    rows = {(r.problem, r.method): r for r in result.rows}
    height = 0.8 / len(METHODS)
    fig = Figure(figsize=(11, 1.2 + 0.3 * max(len(problems), 1)))
    ax, ax_ratio = fig.subplots(1, 2, sharey=True, gridspec_kw={"width_ratios": [3, 2]})
    y = np.arange(len(problems))
    for i, method in enumerate(METHODS):
        offset = (i - (len(METHODS) - 1) / 2) * height
        values = [rows[(p, method)].duration_s if (p, method) in rows else None for p in problems]
        missing = [yy + offset for yy, v in zip(y, values) if v is None]
        ax.barh(y + offset, [1e3 * v if v is not None else 0.0 for v in values], height, color=f"C{i}",
                label=f"{method}" + (f" (not run on {len(missing)})" if missing else ""))
        ax.plot(np.zeros(len(missing)), missing, "x", ms=7, mew=2, color=f"C{i}", clip_on=False)  # not run
        if method != PLANNER:
            ratios = [rows[(p, method)].duration_ratio if (p, method) in rows else None for p in problems]
            shown = [(yy + offset, r) for yy, r in zip(y, ratios) if r is not None]
            # every method gets a legend entry, also one that was skipped on every problem
            ax_ratio.plot([r for _, r in shown], [yy for yy, _ in shown], "o", ms=4, color=f"C{i}",
                          label=f"{method}: {len(shown)}/{len(problems)}" + ("" if shown else " (skipped)"))
    for yy, problem in zip(y, problems):
        planner = rows.get((problem, PLANNER))
        if planner is not None and planner.status != "solved":
            outcome = f"planner: {planner.status}" + (f" ({planner.reason})" if planner.reason else "")
            ax.annotate(outcome, xy=(0.0, yy), xytext=(10, 0), textcoords="offset points", va="center",
                        fontsize=7, color="0.25")
    ax.set_yticks(y, problems, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("duration [ms]")
    ax.set_title("Motion duration per method (x: not run: refused, skipped, failed or unavailable)")
    ax.legend(fontsize=7, loc="best")
    ax.grid(axis="x", alpha=0.3)
    ax_ratio.axvline(1.0, color="C0", lw=1, label="planner (1)")
    ax_ratio.set_xlabel("duration / planner's duration")
    ax_ratio.set_title("Against the planner (1 = equal)")
    ax_ratio.legend(fontsize=7, loc="best", title="method: problems with a ratio", title_fontsize=7)
    ax_ratio.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return fig


def plot_solve_times(result: BatchResult, path: Path) -> Any:
    """PNG at ``path``: solve time [ms] per method in ``result``, one dot per problem over a
    box plot (log scale, labelled at 1, 2, 5 times each power of ten). Returns the matplotlib
    Figure."""
    from matplotlib.figure import Figure  # no pyplot: no global backend or figure state
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    data = [[v * 1e3 for v in _values([r for r in result.rows if r.method == m], "solve_time_s") if v > 0]
            for m in METHODS]
    positions = [i for i, d in enumerate(data, start=1) if d]
    if positions:
        ax.boxplot([d for d in data if d], positions=positions, widths=0.5, showfliers=False)
        for pos in positions:
            d = data[pos - 1]
            jitter = np.linspace(-0.12, 0.12, len(d)) if len(d) > 1 else [0.0]
            ax.plot(pos + np.asarray(jitter), d, "o", ms=3, alpha=0.6)
        ax.set_yscale("log")
        # every decade labelled at 1, 2 and 5, as plain numbers (0.5, 20, 100), whatever the
        # span: the default labels only the powers of ten, or none within a decade
        ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
        ax.yaxis.set_minor_formatter(NullFormatter())
    else:
        ax.text(0.5, 0.5, "no solve times", ha="center", va="center", transform=ax.transAxes)
    ax.set_xticks(range(1, len(METHODS) + 1), [m if d else f"{m}\n(n/a)" for m, d in zip(METHODS, data)],
                  fontsize=8)
    ax.set_ylabel("solve time [ms]")
    ax.set_title("Solve time per method")
    ax.grid(axis="y", alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return fig


def _write_text(path: Path, text: str) -> None:
    """Write atomically with mode 0644 (:func:`falcon_plan.fileio.write_text`)."""
    write_text(path, text, "bench result")


def write_results(result: BatchResult, out_dir: str | Path,
                  summary: dict[str, Any] | None = None) -> dict[str, Path]:
    """Write :data:`RESULT_FILES` into ``out_dir`` (created if needed); returns name -> path.
    ``summary`` is :func:`summarise` of ``result`` (computed if not given)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(result) if summary is None else summary
    paths = {name: out / name for name in RESULT_FILES}
    _write_text(paths["results.csv"], results_csv(result.rows))
    _write_text(paths["results.md"], results_markdown(result, summary))
    _write_text(paths["summary.json"], json.dumps(_json_safe(summary), indent=2) + "\n")
    plot_durations(result, paths["durations.png"])
    plot_solve_times(result, paths["solve_times.png"])
    return paths


def _json_safe(value: Any) -> Any:
    """Replace non-finite floats by None (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
