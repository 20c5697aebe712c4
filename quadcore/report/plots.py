"""Plots people look at, as PNG bytes (matplotlib, no display needed).

Every function returns PNG bytes so that callers can write a file, embed it in HTML
or Markdown (:func:`quadcore.report.render.markdown_image`), or attach it to Dagster metadata.
"""

from __future__ import annotations

import io
import threading
from collections.abc import Callable

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import polars as pl  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import NullLocator  # noqa: E402

from quadcore.physics.dynamics import XYZ  # noqa: E402


def _png(fig, dpi: int = 80, tight: bool = True) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight" if tight else None)
    plt.close(fig)
    return buf.getvalue()


# Per-flight plots go into every materialisation's metadata: small and quick (about 0.1 s,
# 30 kB), with a fixed layout (a layout engine or a tight bounding box costs more than the drawing)
# and lines drawn without antialiasing (a third of the PNG's size for dense traces).
THUMB_DPI = 60
THUMB_POINTS = 600
THUMB_LINE = {"antialiased": False}


# Per-flight figures of one layout, built once per thread and redrawn with each flight's lines:
# making a fresh figure's axes and tick artists is about half the cost of a thumbnail.
_REUSED = threading.local()


def _reused(layout: str, build: Callable[[], tuple[Figure, list]]) -> tuple[Figure, list]:
    """The ``layout`` figure and its axes (built by ``build`` on first use in this thread),
    emptied of the previous flight's lines; the caller draws, rescales and names it again.
    Not closed after use (a plain ``Figure``, outside pyplot's registry)."""
    figures = _REUSED.__dict__.setdefault("figures", {})
    if layout not in figures:
        figures[layout] = build()
    fig, axes = figures[layout]
    for ax in axes:
        for line in list(ax.lines):
            line.remove()
    return fig, axes


def _thumbnail_png(fig: Figure, axes: list) -> bytes:
    """PNG of a reused figure, its axes rescaled to the lines now in them."""
    for ax in axes:
        ax.relim()
        ax.autoscale_view()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=THUMB_DPI)
    return buf.getvalue()


def _model_vs_measured_figure() -> tuple[Figure, list]:
    fig = Figure(figsize=(9, 5.5))
    grid = fig.subplots(3, 2, sharex=True)
    fig.subplots_adjust(left=0.09, right=0.98, top=0.92, bottom=0.09, wspace=0.3, hspace=0.15)
    for row, axis in enumerate(XYZ):
        for col, (symbol, unit) in enumerate((("F", "N"), ("τ", "mN m"))):
            grid[row, col].set_ylabel(f"{symbol}_{axis} body [{unit}]")
            grid[row, col].grid(alpha=0.3)
    grid[-1, 0].set_xlabel("t [s]")
    grid[-1, 1].set_xlabel("t [s]")
    return fig, list(grid.flat)


def model_vs_measured(res: pl.DataFrame, title: str = "", max_points: int = THUMB_POINTS) -> bytes:
    """Measured and modelled body force (N) and torque (mN m, the unit of every torque shown to
    people) over time, with the residual, per axis."""
    step = max(1, res.height // max_points)
    d = res.gather_every(step)
    t = d["t_s"].to_numpy()
    fig, axes = _reused("model_vs_measured", _model_vs_measured_figure)
    panels = [(axis, kind, unit, scale) for axis in XYZ for kind, unit, scale in (("f", "N", 1.0), ("tau", "Nm", 1e3))]
    for ax, (axis, kind, unit, scale) in zip(axes, panels):
        ax.set_prop_cycle(None)  # each flight's lines in the same colours
        ax.plot(t, d[f"{kind}_meas_b_{axis}_{unit}"] * scale, lw=0.8, label="measured", **THUMB_LINE)
        ax.plot(t, d[f"{kind}_model_b_{axis}_{unit}"] * scale, lw=0.8, label="model", **THUMB_LINE)
        ax.plot(t, d[f"{kind}_res_b_{axis}_{unit}"] * scale, lw=0.6, color="tab:red", alpha=0.7, label="residual",
                **THUMB_LINE)
    axes[0].legend(loc="upper right", fontsize=8)
    fig.suptitle(title or "model vs measurement")
    return _thumbnail_png(fig, axes)


_GROWTH_PANELS = (("pos_err_m", "position error [m]"), ("vel_err_mps", "velocity error [m/s]"),
                  ("att_err_deg", "attitude error [deg]"), ("rate_err_radps", "rate error [rad/s]"))


def _error_growth_figure() -> tuple[Figure, list]:
    fig = Figure(figsize=(11, 3))
    axes = list(fig.subplots(1, 4))
    fig.subplots_adjust(left=0.06, right=0.99, top=0.86, bottom=0.16, wspace=0.35)
    for ax, (_, label) in zip(axes, _GROWTH_PANELS):
        ax.set_xlabel("time ahead [s]")
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.yaxis.set_minor_locator(NullLocator())  # minor ticks of a log axis cost more than the plot
        ax.grid(alpha=0.3)
    return fig, axes


def error_growth(growth: pl.DataFrame, title: str = "") -> bytes:
    """Open-loop rollout error against time ahead, one line per horizon."""
    fig, axes = _reused("error_growth", _error_growth_figure)
    horizons = sorted(growth["horizon_s"].unique().to_list())
    longest = growth.filter(pl.col("horizon_s") == horizons[-1])
    for ax, (col, _) in zip(axes, _GROWTH_PANELS):
        ax.set_prop_cycle(None)  # each flight's lines in the same colours
        ax.plot(longest["t_ahead_s"], longest[col], lw=1.2, **THUMB_LINE)
        for h in horizons:
            end = growth.filter(pl.col("horizon_s") == h).sort("step").tail(1)
            ax.plot(end["t_ahead_s"], end[col], "o", ms=4, label=f"{h:.3g} s")
    axes[0].legend(fontsize=7, title="horizon")
    fig.suptitle(title or "open-loop rollout error growth")
    return _thumbnail_png(fig, axes)


def scaling(flights: list[int], series: dict[str, list[float]], peak_mb: list[float], title: str = "") -> bytes:
    """Cost against fleet size: seconds per flight of each named series (left; flat is the
    target: the cost grows with the flights, not faster) and peak memory (right), log x."""
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.5), layout="constrained")
    for name, values in series.items():
        left.plot(flights, values, "o-", label=name)
    left.set(xscale="log", xlabel="flights", ylabel="wall time per flight [s]", ylim=(0, None))
    left.legend(fontsize=7)
    right.plot(flights, peak_mb, "o-")
    right.set(xscale="log", xlabel="flights", ylabel="peak resident memory [MB]", ylim=(0, None))
    for ax in (left, right):
        ax.set_xticks(flights, [str(n) for n in flights])
        ax.xaxis.set_minor_locator(NullLocator())
        ax.grid(alpha=0.3)
    fig.suptitle(title or "time per flight and memory against the number of flights")
    return _png(fig)
