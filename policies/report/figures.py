"""The report's figures, rendered in memory as PNG bytes: the utility CDF, the throughput,
delay and PLR CDFs (alone and side by side, as the paper's figure), utility by heterogeneity
bin, and the learning curve.

matplotlib's object API with the Agg canvas: no pyplot, no global state. matplotlib is
imported only when drawing, so that importing the package (the trainer does) does not load it.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from policies.evaluation.evaluation import HETEROGENEITY_BIN_WIDTH
from policies.report.curves import LearningCurves
from policies.report.inputs import ORACLE_POLICY, PolicyResult
from policies.report.stats import heterogeneity_bins

_DPI = 150
_PALETTE = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#9467bd",
    "#e377c2",
    "#17becf",
    "#bcbd22",
    "#7f7f7f",
)
_FIXED_STYLES = {
    "min-distance": {"color": "#d62728", "linestyle": "--"},
    "load-weighted": {"color": "#8c564b", "linestyle": "--"},
    ORACLE_POLICY: {"color": "black", "linestyle": ":"},
}


def line_styles(names: Sequence[str]) -> dict[str, dict[str, Any]]:
    """A colour and line style per name, the same in every figure of a report: the baselines
    dashed in fixed colours, the oracle dotted black, the others solid from a palette in the
    order given."""
    styles: dict[str, dict[str, Any]] = {}
    others = [n for n in dict.fromkeys(names) if n not in _FIXED_STYLES]
    for i, name in enumerate(others):
        styles[name] = {"color": _PALETTE[i % len(_PALETTE)], "linestyle": "-"}
    for name in names:
        if name in _FIXED_STYLES:
            styles[name] = dict(_FIXED_STYLES[name])
    return styles


def _new_figure(width: float, height: float) -> Any:
    """An empty figure on an Agg canvas, sized in inches."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _png(figure: Any) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=_DPI)
    return buffer.getvalue()


def _cdf_axes(
    ax: Any,
    results: Sequence[PolicyResult],
    styles: Mapping[str, Mapping[str, Any]],
    values: Callable[[PolicyResult], np.ndarray],
    xlabel: str,
    title: str,
    log_x: bool = False,
) -> None:
    for r in results:
        ax.ecdf(values(r), label=r.policy, linewidth=1.6, **styles[r.policy])
    ax.axhline(0.25, color="0.55", linewidth=0.8, zorder=0)
    ax.annotate(
        "25th percentile", (0.01, 0.25), xycoords=("axes fraction", "data"),
        xytext=(0, 2), textcoords="offset points", fontsize=7, color="0.4",
    )  # fmt: skip
    if log_x:
        ax.set_xscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("CDF (fraction of test scenarios)")
    ax.set_ylim(0, 1.02)
    ax.set_title(title)
    ax.grid(True, which="major", alpha=0.35)


def _wide_range(values: np.ndarray) -> bool:
    """Positive values spanning more than two decades: shown on a log axis."""
    return bool(np.all(values > 0) and values.max() > 100 * values.min())


_METRICS: tuple[tuple[str, str, Callable[[PolicyResult], np.ndarray], str, bool], ...] = (
    # file, x label, values, title, log axis when they span > 2 decades (the delay: ~0.4 ms
    # to seconds). Not the PLR: its "zeros" are 1e-90-like numbers, linear as in the paper.
    (
        "throughput_cdf.png",
        "aggregate throughput (Mbit/s)",
        lambda r: r.throughput_bps / 1e6,
        "Aggregate throughput",
        False,
    ),
    ("delay_cdf.png", "mean delay (s)", lambda r: r.delay_s, "Delay", True),
    ("plr_cdf.png", "packet loss ratio (0-1)", lambda r: r.plr, "Packet loss ratio", False),
)


def _metric_axes(ax: Any, results: Sequence[PolicyResult], styles: Any, metric: tuple) -> None:
    _, xlabel, values, title, log_allowed = metric
    log_x = log_allowed and _wide_range(np.concatenate([values(r) for r in results]))
    if log_x:
        xlabel = xlabel.replace(")", ", log scale)")
    n = len(results[0].ids)
    _cdf_axes(ax, results, styles, values, xlabel, f"{title} CDF ({n} scenarios)", log_x)


def _cdf_figures(results: Sequence[PolicyResult], styles: Any) -> dict[str, bytes]:
    n = len(results[0].ids)
    figures: dict[str, bytes] = {}
    figure = _new_figure(6.4, 4.4)
    ax = figure.subplots()
    _cdf_axes(
        ax, results, styles, lambda r: r.utility,
        "mean network utility per scenario (episode mean)",
        f"Network utility CDF ({n} test scenarios)",
    )  # fmt: skip
    ax.legend(loc="upper left", fontsize=8, framealpha=0.9)
    figures["utility_cdf.png"] = _png(figure)
    for metric in _METRICS:
        figure = _new_figure(6.4, 4.4)
        ax = figure.subplots()
        _metric_axes(ax, results, styles, metric)
        ax.legend(loc="best", fontsize=8, framealpha=0.9)
        figures[metric[0]] = _png(figure)
    figure = _new_figure(16, 4.6)
    axes = figure.subplots(1, 3)
    for ax, metric in zip(axes, _METRICS, strict=True):
        _metric_axes(ax, results, styles, metric)
    handles, labels = axes[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 6))
    figures["metrics_cdf.png"] = _png(figure)
    return figures


def _heterogeneity_figure(results: Sequence[PolicyResult], styles: Any) -> bytes:
    """Mean utility per bin (lines, top) over the number of scenarios per bin (bars, below)."""
    bins = heterogeneity_bins(results)
    w = HETEROGENEITY_BIN_WIDTH
    centres = (bins.index + 0.5) * w
    figure = _new_figure(7.2, 5.4)
    ax, counts = figure.subplots(2, 1, sharex=True, height_ratios=[3, 1])
    for p, r in enumerate(results):
        ax.plot(centres, bins.mean[p], marker="o", markersize=4, label=r.policy, **styles[r.policy])
    ax.set_ylabel("mean network utility in the bin")
    ax.set_title(f"Mean utility per heterogeneity bin ({len(results[0].ids)} scenarios)")
    ax.grid(True, alpha=0.35)
    ax.legend(loc="best", fontsize=8, framealpha=0.9)
    bars = counts.bar(centres, bins.count, width=0.9 * w, color="0.75")
    counts.bar_label(bars, fontsize=7, color="0.3", padding=1)
    counts.set_ylim(0, bins.count.max() * 1.3)
    counts.set_ylabel("scenarios")
    counts.set_xlabel(f"heterogeneity index H (bins of width {w})")
    counts.set_xlim(max(0.0, bins.index.min() * w - w), min(1.0, (bins.index.max() + 2) * w))
    counts.grid(True, axis="x", alpha=0.35)
    return _png(figure)


def _learning_figure(learning: LearningCurves, styles: Any) -> bytes:
    """Median utility vs training episodes (log axis), the baselines as horizontal lines."""
    figure = _new_figure(6.4, 4.4)
    ax = figure.subplots()
    episodes = [p.episodes for c in learning.curves for p in c.points]
    for curve in learning.curves:
        ax.plot(
            [p.episodes for p in curve.points],
            [p.median_utility for p in curve.points],
            marker="o",
            markersize=4,
            label=curve.label,
            color=styles[curve.label]["color"],
            linestyle="-",
        )
    for name, value in learning.reference.items():
        style = styles.get(name, {"color": "0.4", "linestyle": "-."})
        ax.axhline(value, linewidth=1.4, label=f"{name} (reference, {value:.3f})", **style)
    ax.set_xscale("log")
    ax.set_xlim(min(100, min(episodes)) / 1.2, max(10_000, max(episodes)) * 1.2)
    ax.set_xlabel("training episodes (log scale)")
    ax.set_ylabel("median network utility on the test set")
    ax.set_title("Learning rate: median utility vs training episodes")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right", fontsize=8, framealpha=0.9)
    return _png(figure)


def render_figures(
    results: Sequence[PolicyResult], learning: LearningCurves | None
) -> dict[str, bytes]:
    """Every PNG of the report, by file name, rendered in memory."""
    names = [r.policy for r in results]
    if learning is not None:
        names += [c.label for c in learning.curves] + list(learning.reference)
    styles = line_styles(names)
    figures = _cdf_figures(results, styles)
    figures["utility_by_heterogeneity.png"] = _heterogeneity_figure(results, styles)
    if learning is not None:
        figures["learning_curve.png"] = _learning_figure(learning, styles)
    return figures
