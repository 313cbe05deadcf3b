"""Figure helpers shared by the plots: a pyplot-free Figure, leg colours, limit lines, saving."""
from __future__ import annotations

from pathlib import Path
from typing import Any

LEG_COLOURS = ("tab:blue", "tab:orange", "tab:green")
AXIS_COLOURS = ("tab:red", "tab:green", "tab:blue")  # x, y, z as in most robotics viewers


def new_figure(rows: int, cols: int, size: tuple[float, float], **kwargs: Any) -> tuple[Any, Any]:
    """A matplotlib Figure (Agg, no pyplot) of ``size`` (width, height) [inch] with a grid of
    ``rows`` x ``cols`` axes, and that grid (``kwargs`` go to ``Figure.subplots``, e.g.
    ``sharex``)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    return fig, fig.subplots(rows, cols, **kwargs)


def limit_lines(ax: Any, limit: float, label: str, colour: str = "k", style: str = "--") -> None:
    """Horizontal lines on the axes ``ax`` at +-``limit`` (in the axes' data units), in
    ``colour`` and line ``style`` (a matplotlib colour and line style), with ``label`` once in
    the legend and each value at the right edge."""
    ax.axhline(limit, color=colour, ls=style, lw=1.0, label=label)
    ax.axhline(-limit, color=colour, ls=style, lw=1.0)
    for value in (limit, -limit):
        ax.annotate(f"{value:+g}", xy=(1.0, value), xycoords=("axes fraction", "data"), xytext=(2, 0),
                    textcoords="offset points", va="center", fontsize=7, color=colour)


def save(fig: Any, path: str | Path, dpi: int = 110) -> Path:
    """Write the figure ``fig`` as a PNG at ``path`` with ``dpi`` dots per inch (atomic, mode
    0644) and return its path."""
    import io

    from falcon_plan.fileio import write_bytes

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    return write_bytes(path, buffer.getvalue(), "plot")
