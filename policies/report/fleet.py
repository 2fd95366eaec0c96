"""``tupa report`` over fleet evaluations (``tupa eval --uavs K``, format ``tupa-fleet-eval/1``).

A results directory holds either single-UAV eval files or fleet ones (:func:`holds_fleet_results`
tells, and refuses a mix: the two measure different things). From the fleet files,
:func:`build_fleet_report` writes, each atomically and only once everything is read, checked and
rendered:

* ``fleet_metrics.png``: one panel per metric (network utility, served-user fraction, Jain
  fairness, minimum user throughput, handovers per episode), one box per policy over the
  scenarios (quartiles, whiskers to 1.5 IQR, the mean as a white diamond) with every scenario's
  value drawn over it: the spread and the small-sample points stay visible (each y axis zoomed
  to its data, so that differences of a few hundredths show);
* ``fleet_utility_by_heterogeneity.png``: mean utility per heterogeneity bin of width 0.05, the
  number of scenarios per bin below (as the single-UAV report's figure);
* ``results.md``: the means per policy (and the ratio to ``fleet-oracle`` when it was
  evaluated), utility per H bin with counts and ratios, the evaluation settings.

Checks, each an :class:`~sim.errors.InputError` of one line naming the file and field: every
row's fields are finite numbers, a policy appears once, every policy was evaluated with the same
K and on the same scenarios (ids and heterogeneity). Differing world, episode, seed or
re-planning settings are warned about and shown in the settings table. Summaries are recomputed
from the rows, not copied from the files.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from policies.evaluation.evaluation import HETEROGENEITY_BIN_WIDTH, heterogeneity_bin
from policies.evaluation.fleet_evaluation import FLEET_EVAL_FORMAT, FLEET_METRICS, FLEET_ORACLE
from policies.report.checks import (
    check_scenario_ids,
    fail,
    finite_number,
    non_empty_text,
    read_json,
)
from policies.report.curves import LEARNING_CURVE_FILE
from policies.report.inputs import Warn, _is_eval_document
from policies.report.output import REPORT_FILE, ReportFiles, write_report_files
from sim.errors import InputError
from sim.fleet import MAX_UAVS

__all__ = [
    "FLEET_FIGURES",
    "FleetResult",
    "build_fleet_report",
    "holds_fleet_results",
    "load_fleet_results",
]

METRICS_FIGURE = "fleet_metrics.png"
HETEROGENEITY_FIGURE = "fleet_utility_by_heterogeneity.png"
FLEET_FIGURES = (METRICS_FIGURE, HETEROGENEITY_FIGURE)
SETTINGS = ("world", "environment", "episode_steps", "replan_every", "seed", "channel_mode")
BASELINES = ("kmeans-min-distance", "kmeans-load-weighted")
_H_TOLERANCE = 1e-9

# metric, panel title, the scale of the values shown
_PANELS: tuple[tuple[str, str, float], ...] = (
    ("utility", "Network utility", 1.0),
    ("served_fraction", "Served-user fraction", 1.0),
    ("jain_fairness", "Jain fairness of throughput", 1.0),
    ("min_throughput_bps", "Minimum user throughput (Mbit/s)", 1e-6),
    ("handovers", "Handovers per episode", 1.0),
)
_FIXED_COLOURS = {
    "kmeans-min-distance": "#d62728",
    "kmeans-load-weighted": "#8c564b",
    "kmeans-scored": "#7f7f7f",
    FLEET_ORACLE: "black",
}
_PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#e377c2", "#17becf", "#bcbd22")


@dataclass(frozen=True)
class FleetResult:
    """One policy's rows from a fleet eval file, as arrays in scenario order: ``values[m]``
    for each metric of :data:`policies.evaluation.fleet_evaluation.FLEET_METRICS`."""

    policy: str
    source: Path
    uavs: int
    ids: tuple[str, ...]
    heterogeneity: np.ndarray
    values: dict[str, np.ndarray]
    settings: dict[str, Any]

    def reordered(self, ids: Sequence[str]) -> FleetResult:
        position = {scenario_id: i for i, scenario_id in enumerate(self.ids)}
        order = np.array([position[i] for i in ids], dtype=int)
        return FleetResult(
            self.policy,
            self.source,
            self.uavs,
            tuple(ids),
            self.heterogeneity[order],
            {key: value[order] for key, value in self.values.items()},
            self.settings,
        )


# --------------------------------------------------------------------------------------------
# Reading


def _is_fleet_document(document: Any) -> bool:
    return isinstance(document, dict) and document.get("format") == FLEET_EVAL_FORMAT


def _eval_files(results_dir: Path) -> list[tuple[Path, Any]]:
    if not results_dir.is_dir():
        raise InputError(f"--results: {results_dir}: not a directory")
    files = []
    for path in sorted(results_dir.glob("*.json")):
        if path.name == LEARNING_CURVE_FILE or path.name.startswith(".") or not path.is_file():
            continue
        files.append((path, read_json(path)))
    return files


def holds_fleet_results(results_dir: Path) -> bool:
    """Whether ``results_dir`` holds fleet eval files (``tupa-fleet-eval/1``); an error when it
    holds both fleet and single-UAV eval files."""
    fleet, single = [], []
    for path, document in _eval_files(Path(results_dir)):
        if _is_fleet_document(document):
            fleet.append(path)
        elif _is_eval_document(document):
            single.append(path)
    if fleet and single:
        raise InputError(
            f"--results: {results_dir}: holds fleet eval files ({fleet[0].name}) and single-UAV "
            f"ones ({single[0].name}); report them from separate directories"
        )
    return bool(fleet)


def _parse(raw: Any, path: Path, where: str) -> FleetResult:
    label = str(path)
    if not isinstance(raw, dict):
        raise fail(label, where, "must be an object")
    if raw.get("format") != FLEET_EVAL_FORMAT:
        raise fail(label, where, f"format: must be {FLEET_EVAL_FORMAT!r}")
    for key in ("policy", "uavs", "scenarios"):
        if key not in raw:
            raise fail(label, where, f"{key}: missing")
    name = non_empty_text(raw["policy"], label, f"{where}.policy".lstrip("."))
    where = f"{where} ({name})" if where else name
    uavs = raw["uavs"]
    if isinstance(uavs, bool) or not isinstance(uavs, int) or not 1 <= uavs <= MAX_UAVS:
        raise fail(label, where, f"uavs: must be an integer in 1..{MAX_UAVS}, got {uavs!r}")
    rows = raw["scenarios"]
    if not isinstance(rows, list) or not rows:
        raise fail(label, where, "scenarios: must be a non-empty list")
    ids: list[str] = []
    heterogeneity: list[float] = []
    values: dict[str, list[float]] = {key: [] for key in FLEET_METRICS}
    for i, row in enumerate(rows):
        at = f"scenarios[{i}]"
        if not isinstance(row, dict):
            raise fail(label, where, at, "must be an object")
        for key in ("id", "heterogeneity", *FLEET_METRICS):
            if key not in row:
                raise fail(label, where, f"{at}.{key}", "missing")
        ids.append(non_empty_text(row["id"], label, f"{where}: {at}.id"))
        heterogeneity.append(
            finite_number(row["heterogeneity"], label, f"{where}: {at}.heterogeneity")
        )
        for key in FLEET_METRICS:
            value = finite_number(row[key], label, f"{where}: {at}.{key}")
            if value < 0:
                raise fail(label, where, f"{at}.{key}", f"must be >= 0, got {value}")
            values[key].append(value)
    check_scenario_ids(ids, raw, label, where)
    return FleetResult(
        policy=name,
        source=path,
        uavs=uavs,
        ids=tuple(ids),
        heterogeneity=np.array(heterogeneity),
        values={key: np.array(v) for key, v in values.items()},
        settings={key: raw[key] for key in SETTINGS if key in raw},
    )


def _parse_document(document: dict[str, Any], path: Path) -> list[FleetResult]:
    if "results" not in document:
        return [_parse(document, path, "")]
    items = document["results"]
    if not isinstance(items, list) or not items:
        raise fail(str(path), "results", "must be a non-empty list")
    return [_parse(item, path, f"results[{i}]") for i, item in enumerate(items)]


def _aligned(results: Sequence[FleetResult]) -> list[FleetResult]:
    """Every result over the first one's scenarios in its order; errors naming the policies
    for a repeated policy, another K, or other scenarios."""
    first = results[0]
    seen: dict[str, FleetResult] = {}
    aligned = []
    for r in results:
        other = seen.setdefault(r.policy, r)
        if other is not r:
            where = (
                f"twice in {r.source}"
                if other.source == r.source
                else (f"in both {other.source} and {r.source}")
            )
            raise InputError(f"policy {r.policy!r} appears {where}; keep one of them")
        if r.uavs != first.uavs:
            raise InputError(
                f"uavs: {first.policy!r} ({first.source}) flies {first.uavs} UAVs, {r.policy!r} "
                f"({r.source}) {r.uavs}; report one fleet size at a time"
            )
        if set(r.ids) != set(first.ids):
            raise InputError(
                f"policies {first.policy!r} ({first.source}) and {r.policy!r} ({r.source}) were "
                "evaluated on different scenario sets; evaluate every policy on the same "
                "scenario file"
            )
        r = r.reordered(first.ids)
        differ = np.flatnonzero(np.abs(r.heterogeneity - first.heterogeneity) > _H_TOLERANCE)
        if differ.size:
            i = int(differ[0])
            raise InputError(
                f"policies {first.policy!r} ({first.source}) and {r.policy!r} ({r.source}) share "
                f"scenario ids but not scenarios: {first.ids[i]} has H = "
                f"{first.heterogeneity[i]:.4f} in one and {r.heterogeneity[i]:.4f} in the other"
            )
        aligned.append(r)
    fixed = [*BASELINES, FLEET_ORACLE]
    return sorted(
        aligned,
        key=lambda r: (1, fixed.index(r.policy)) if r.policy in fixed else (0, aligned.index(r)),
    )


def load_fleet_results(results_dir: Path, warn: Warn) -> list[FleetResult]:
    """Every policy's rows from the fleet eval files in ``results_dir``, checked (module doc),
    over the same scenarios in the same order: other policies first, then the k-means
    baselines, the oracle last. Other JSON files are skipped with ``warn``."""
    results: list[FleetResult] = []
    for path, document in _eval_files(Path(results_dir)):
        if not _is_fleet_document(document):
            warn(f"{path}: not a tupa fleet eval result (format {FLEET_EVAL_FORMAT}), skipped")
            continue
        results.extend(_parse_document(document, path))
    if not results:
        raise InputError(f"--results: {results_dir}: no fleet eval results (*.json) found")
    results = _aligned(results)
    for key in SETTINGS:
        if len({json.dumps(r.settings.get(key)) for r in results}) > 1:
            listed = ", ".join(f"{r.policy}={r.settings.get(key, '?')}" for r in results)
            warn(f"policies evaluated with different {key}: {listed}")
    return results


# --------------------------------------------------------------------------------------------
# Numbers


@dataclass(frozen=True)
class _Bins:
    index: np.ndarray
    count: np.ndarray
    mean: np.ndarray  # (P, B) mean utility

    def label(self, b: int) -> str:
        w = HETEROGENEITY_BIN_WIDTH
        return f"[{self.index[b] * w:.2f}, {(self.index[b] + 1) * w:.2f})"


def _bins(results: Sequence[FleetResult]) -> _Bins:
    bins = np.array([heterogeneity_bin(h) for h in results[0].heterogeneity])
    index = np.unique(bins)
    count = np.array([int(np.sum(bins == b)) for b in index])
    mean = np.array([[r.values["utility"][bins == b].mean() for b in index] for r in results])
    return _Bins(index, count, mean)


def _oracle(results: Sequence[FleetResult]) -> FleetResult | None:
    return next((r for r in results if r.policy == FLEET_ORACLE), None)


def _ratio(value: float, reference: float) -> str:
    return f"{value / reference:.3f}" if reference > 0 else "n/a"


def _headlines(results: Sequence[FleetResult]) -> list[str]:
    oracle = _oracle(results)
    lines = []
    for r in results:
        v = r.values
        line = (
            f"{r.policy} (K={r.uavs}): utility {v['utility'].mean():.3f}, served "
            f"{v['served_fraction'].mean():.3f}, Jain {v['jain_fairness'].mean():.3f}, min "
            f"{v['min_throughput_bps'].mean() / 1e6:.2f} Mbit/s, handovers "
            f"{v['handovers'].mean():.1f} per episode"
        )
        if oracle is not None and r is not oracle:
            reference = oracle.values["utility"].mean()
            line += f"; {_ratio(v['utility'].mean(), reference)} of {FLEET_ORACLE}'s utility"
        lines.append(line)
    return lines


# --------------------------------------------------------------------------------------------
# Figures


def _colours(results: Sequence[FleetResult]) -> dict[str, str]:
    others = [r.policy for r in results if r.policy not in _FIXED_COLOURS]
    colours = {name: _PALETTE[i % len(_PALETTE)] for i, name in enumerate(others)}
    colours.update(
        {r.policy: _FIXED_COLOURS[r.policy] for r in results if r.policy in _FIXED_COLOURS}
    )
    return colours


def _metrics_figure(results: Sequence[FleetResult], colours: dict[str, str]) -> bytes:
    from policies.report.figures import _new_figure, _png

    n = len(results[0].ids)
    figure = _new_figure(3.3 * len(_PANELS), 4.6)
    axes = figure.subplots(1, len(_PANELS))
    positions = np.arange(1, len(results) + 1)
    jitter = np.random.default_rng(0)  # the same offsets in every report of the same results
    for ax, (metric, title, scale) in zip(axes, _PANELS, strict=True):
        data = [r.values[metric] * scale for r in results]
        boxes = ax.boxplot(
            data, positions=positions, widths=0.6, showmeans=True, patch_artist=True,
            showfliers=False,
            meanprops={"marker": "D", "markerfacecolor": "white", "markeredgecolor": "black"},
            medianprops={"color": "black"},
        )  # fmt: skip
        for patch, r in zip(boxes["boxes"], results, strict=True):
            patch.set_facecolor(colours[r.policy])
            patch.set_alpha(0.35)
        for x, values, r in zip(positions, data, results, strict=True):
            offsets = jitter.uniform(-0.15, 0.15, len(values))
            ax.scatter(x + offsets, values, s=9, color=colours[r.policy], zorder=3)
        ax.set_xticks(positions, [r.policy for r in results], rotation=30, ha="right", fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.grid(True, axis="y", alpha=0.35)
    figure.suptitle(
        f"Fleet of {results[0].uavs} UAVs: per-scenario episode means over {n} scenarios "
        "(box: quartiles; diamond: mean; dots: scenarios; y axes zoomed to the data)",
        fontsize=10,
    )
    return _png(figure)


def _heterogeneity_figure(results: Sequence[FleetResult], colours: dict[str, str]) -> bytes:
    from policies.report.figures import _new_figure, _png

    bins = _bins(results)
    w = HETEROGENEITY_BIN_WIDTH
    centres = (bins.index + 0.5) * w
    figure = _new_figure(7.2, 5.4)
    ax, counts = figure.subplots(2, 1, sharex=True, height_ratios=[3, 1])
    for p, r in enumerate(results):
        style = ":" if r.policy == FLEET_ORACLE else "--" if r.policy in BASELINES else "-"
        ax.plot(centres, bins.mean[p], marker="o", markersize=4, label=r.policy,
                color=colours[r.policy], linestyle=style)  # fmt: skip
    ax.set_ylabel("mean network utility in the bin")
    ax.set_title(
        f"Fleet of {results[0].uavs} UAVs: mean utility per heterogeneity bin "
        f"({len(results[0].ids)} scenarios)"
    )
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


# --------------------------------------------------------------------------------------------
# results.md


def _md_table(header: Sequence[str], rows: Sequence[Sequence[str]], numeric: bool = True) -> str:
    align = ["---"] + ["---:" if numeric else "---"] * (len(header) - 1)
    return "\n".join("| " + " | ".join(row) + " |" for row in [header, align, *rows])


def _means_table(results: Sequence[FleetResult]) -> str:
    oracle = _oracle(results)
    header = ["policy", "n", "mean utility", "median utility", "p25 utility", "served fraction",
              "Jain fairness", "min throughput (Mbit/s)", "handovers / episode"]  # fmt: skip
    if oracle is not None:
        header += [f"utility / `{FLEET_ORACLE}`", "median scenario ratio"]
    rows = []
    for r in results:
        u = r.values["utility"]
        row = [
            f"`{r.policy}`",
            str(len(r.ids)),
            f"{u.mean():.3f}",
            f"{np.median(u):.3f}",
            f"{np.percentile(u, 25):.3f}",
            f"{r.values['served_fraction'].mean():.3f}",
            f"{r.values['jain_fairness'].mean():.3f}",
            f"{r.values['min_throughput_bps'].mean() / 1e6:.2f}",
            f"{r.values['handovers'].mean():.2f}",
        ]
        if oracle is not None:
            best = oracle.values["utility"]
            per_scenario = u[best > 0] / best[best > 0]
            median = f"{np.median(per_scenario):.3f}" if per_scenario.size else "n/a"
            row += [_ratio(u.mean(), best.mean()), median]
        rows.append(row)
    return _md_table(header, rows)


def _bins_table(results: Sequence[FleetResult], bins: _Bins) -> str:
    names = [r.policy for r in results]
    oracle = names.index(FLEET_ORACLE) if FLEET_ORACLE in names else None
    others = [] if oracle is None else [p for p in range(len(results)) if p != oracle]
    header = ["H bin", "n", *[f"`{n}`" for n in names]]
    header += [f"`{names[p]}` / `{FLEET_ORACLE}`" for p in others]
    rows = []
    for b in range(len(bins.index)):
        row = [bins.label(b), str(bins.count[b])]
        row += [f"{bins.mean[p, b]:.3f}" for p in range(len(results))]
        if oracle is not None:
            row += [_ratio(bins.mean[p, b], bins.mean[oracle, b]) for p in others]
        rows.append(row)
    return _md_table(header, rows)


def _settings_table(results: Sequence[FleetResult]) -> str:
    rows = [
        [f"`{r.policy}`", str(r.uavs), *[str(r.settings.get(k, "?")) for k in SETTINGS],
         f"`{r.source.name}`"]
        for r in results
    ]  # fmt: skip
    header = ["policy", "UAVs", "world", "environment", "episode steps", "re-placed every",
              "seed", "channels", "file"]  # fmt: skip
    return _md_table(header, rows, numeric=False)


def _markdown(results: Sequence[FleetResult], results_dir: Path) -> str:
    bins = _bins(results)
    files = sorted({r.source.name for r in results})
    n, k = len(results[0].ids), results[0].uavs
    oracle = _oracle(results)
    lines = [
        "# TUPA fleet evaluation report",
        "",
        f"Written by `tupa report` from {len(files)} fleet eval file(s) in `{results_dir}`: "
        f"{len(results)} policies flying {k} UAVs, each evaluated on the same {n} scenarios "
        "(`tupa eval --uavs K`, one episode of the fleet environment per scenario). Per "
        "scenario, utility, served-user fraction, Jain fairness and minimum user throughput are "
        "means over the episode's steps, handovers a count over the episode; the summaries "
        "below are recomputed from those rows.",
        "",
        "## Summary",
        "",
        "Means over the scenarios (the utility also its median and 25th percentile)"
        + (
            f"; the ratio of each mean utility to `{FLEET_ORACLE}`'s and the median of the "
            "per-scenario ratios."
            if oracle is not None
            else f"; `{FLEET_ORACLE}` was not evaluated, so no ratios to it."
        ),
        "",
        _means_table(results),
        "",
        f"![fleet metrics per policy]({METRICS_FIGURE})",
        "",
        "## Utility by heterogeneity index",
        "",
        f"Mean utility per bin of width {HETEROGENEITY_BIN_WIDTH} of the scenarios' "
        "heterogeneity index H (empty bins left out), with the number of scenarios per bin"
        + (f" and each policy's ratio to `{FLEET_ORACLE}`." if oracle is not None else "."),
        "",
        _bins_table(results, bins),
        "",
        f"![utility by heterogeneity]({HETEROGENEITY_FIGURE})",
        "",
        "## Evaluation settings",
        "",
        _settings_table(results),
        "",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# The report


def build_fleet_report(results_dir: Path, out_dir: Path, warn: Warn) -> Any:
    """Read the fleet eval files in ``results_dir`` and write the figures and ``results.md``
    to ``out_dir`` (created if missing); nothing is written on bad input. Returns
    :class:`policies.report.output.ReportFiles` (one headline per policy)."""

    results_dir, out_dir = Path(results_dir), Path(out_dir)
    results = load_fleet_results(results_dir, warn)
    if (results_dir / LEARNING_CURVE_FILE).exists():
        warn(f"{results_dir / LEARNING_CURVE_FILE}: a fleet report draws no learning curve")
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out: {out_dir}: exists and is not a directory")
    colours = _colours(results)
    files = {
        METRICS_FIGURE: _metrics_figure(results, colours),
        HETEROGENEITY_FIGURE: _heterogeneity_figure(results, colours),
    }
    markdown = _markdown(results, results_dir)
    written = write_report_files(out_dir, {**files, REPORT_FILE: markdown})
    return ReportFiles(written=tuple(written), headlines=tuple(_headlines(results)))
