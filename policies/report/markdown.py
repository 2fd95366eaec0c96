"""``results.md``: the headline numbers, the tables behind the figures, links to the figures."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from policies.evaluation.evaluation import HETEROGENEITY_BIN_WIDTH, REFERENCE_POLICY
from policies.report.curves import LEARNING_CURVE_FILE, LearningCurve, LearningCurves
from policies.report.inputs import SETTINGS, PolicyResult
from policies.report.stats import HeterogeneityBins, headlines, heterogeneity_bins, p25, ratio


def _md_table(header: Sequence[str], rows: Sequence[Sequence[str]], numeric: bool = True) -> str:
    """A markdown table, the first column left-aligned, the others right-aligned if
    ``numeric``."""
    align = ["---"] + ["---:" if numeric else "---"] * (len(header) - 1)
    lines = [header, align, *rows]
    return "\n".join("| " + " | ".join(row) + " |" for row in lines)


def _summary_table(results: Sequence[PolicyResult]) -> str:
    names = [r.policy for r in results]
    ref = results[names.index(REFERENCE_POLICY)] if REFERENCE_POLICY in names else None
    header = ["policy", "n", "mean utility", "median utility", "p25 utility"]
    if ref is not None:
        header.append(f"p25 / {REFERENCE_POLICY}")
    header += ["throughput (Mbit/s)", "delay (ms)", "PLR"]
    rows = []
    for r in results:
        row = [
            f"`{r.policy}`",
            str(len(r.ids)),
            f"{r.utility.mean():.3f}",
            f"{np.median(r.utility):.3f}",
            f"{p25(r.utility):.3f}",
        ]
        if ref is not None:
            row.append(ratio(p25(r.utility), p25(ref.utility)))
        row += [
            f"{r.throughput_bps.mean() / 1e6:.2f}",
            f"{r.delay_s.mean() * 1e3:.1f}",
            f"{r.plr.mean():.4f}",
        ]
        rows.append(row)
    return _md_table(header, rows)


def _settings_table(results: Sequence[PolicyResult]) -> str:
    rows = [
        [f"`{r.policy}`", *[str(r.settings.get(k, "?")) for k in SETTINGS], f"`{r.source.name}`"]
        for r in results
    ]
    header = ["policy", "seed", "queueing", "episode steps", "mode", "environment", "file"]
    return _md_table(header, rows, numeric=False)


def _altitude_section(results: Sequence[PolicyResult], profiles: Sequence[str] = ()) -> list[str]:
    """Where each policy flies: the altitude the UAV ended each episode at; ``profiles``: the
    utility-against-altitude paragraph (:func:`policies.report.altitude.altitude_lines`)."""
    known = [r for r in results if r.altitude_m is not None]
    if not known:
        return ["## Altitude", "", *profiles] if profiles else []
    environments = sorted({str(r.settings.get("environment", "open")) for r in results})
    rows = []
    for r in known:
        z = r.altitude_m
        assert z is not None
        q25, q50, q75 = np.percentile(z, [25, 50, 75])
        rows.append([f"`{r.policy}`", f"{z.mean():.1f}", f"{q25:.1f}", f"{q50:.1f}", f"{q75:.1f}"])
    return [
        "## Altitude",
        "",
        f"Where each policy flies in the `{'`, `'.join(environments)}` environment: the "
        "altitude (m) the UAV ended each episode at, over the scenarios. Under free space "
        "(`open`) the lowest altitude is all but always best; over a town, climbing buys line "
        'of sight (docs/network-model.md, "Channel environments").',
        "",
        _md_table(["policy", "mean", "p25", "median", "p75"], rows),
        "",
        *profiles,
    ]


def _bins_table(results: Sequence[PolicyResult], bins: HeterogeneityBins) -> str:
    names = [r.policy for r in results]
    ref = names.index(REFERENCE_POLICY) if REFERENCE_POLICY in names else None
    gains = [] if ref is None else [p for p in range(len(results)) if p != ref]
    header = ["H bin", "n", *[f"`{n}`" for n in names]]
    header += [f"`{names[p]}` / `{REFERENCE_POLICY}`" for p in gains]
    rows = []
    for b in range(len(bins.index)):
        row = [bins.label(b), str(bins.count[b])]
        row += [f"{bins.mean[p, b]:.3f}" for p in range(len(results))]
        if ref is not None:
            row += [ratio(bins.mean[p, b], bins.mean[ref, b]) for p in gains]
        rows.append(row)
    return _md_table(header, rows)


def _first_beating(curve: LearningCurve, name: str, level: float) -> str:
    for point in curve.points:
        if point.median_utility > level:
            return f"first beats `{name}` ({level:.3f}) after {point.episodes} episodes"
    return f"never beats `{name}` ({level:.3f}) up to {curve.points[-1].episodes} episodes"


def _learning_section(learning: LearningCurves) -> list[str]:
    episodes = sorted({p.episodes for c in learning.curves for p in c.points})
    values = {c.label: {p.episodes: p.median_utility for p in c.points} for c in learning.curves}
    rows = [
        [
            str(e),
            *[
                f"{values[c.label][e]:.3f}" if e in values[c.label] else "–"
                for c in learning.curves
            ],
        ]
        for e in episodes
    ]
    lines = [
        "## Learning curve",
        "",
        "Median utility on the test set after training for the given number of episodes "
        f"(from `{LEARNING_CURVE_FILE}`).",
        "",
        _md_table(["episodes", *[f"`{c.label}`" for c in learning.curves]], rows),
        "",
    ]
    if learning.reference:
        listed = ", ".join(f"`{k}` {v:.3f}" for k, v in learning.reference.items())
        lines += [f"Reference (median utility on the same test set): {listed}.", ""]
    if REFERENCE_POLICY in learning.reference:
        level = learning.reference[REFERENCE_POLICY]
        for curve in learning.curves:
            beating = _first_beating(curve, REFERENCE_POLICY, level)
            lines.append(f"- `{curve.label}` {beating} (paper: after 500 episodes at most).")
        lines.append("")
    lines += ["![learning curve](learning_curve.png)", ""]
    return lines


def render_markdown(
    results: Sequence[PolicyResult],
    learning: LearningCurves | None,
    results_dir: Path,
    altitude_profiles: Sequence[str] = (),
) -> str:
    """``results.md``: the headline numbers, the tables behind the figures, the figures
    (``altitude_profiles``: the lines of the altitude figure's paragraph, if any)."""
    bins = heterogeneity_bins(results)
    headline_lines = headlines(results, bins)
    n = len(results[0].ids)
    files = sorted({r.source.name for r in results})
    lines = [
        "# TUPA evaluation report",
        "",
        f"Written by `tupa report` from {len(files)} eval file(s) in `{results_dir}`: "
        f"{len(results)} policies, each evaluated on the same {n} scenarios. Per scenario, "
        "utility, throughput, delay and PLR are the episode means written by `tupa eval`; the "
        "summaries below are recomputed from them.",
        "",
        "## Headline numbers against the paper",
        "",
        "The paper reports TUPA at ~1.75x the min-distance baseline's utility at the 25th "
        "percentile, and ~4x in the most heterogeneous bin (~0.8 vs ~0.2). Ours:",
        "",
    ]
    if headline_lines:
        lines += [f"- {line}" for line in headline_lines]
    else:
        lines.append(f"- `{REFERENCE_POLICY}` is not among the results: no gains computed.")
    lines += [
        "",
        "## Summary",
        "",
        "Utility: mean, median and 25th percentile over scenarios of each episode's mean "
        "network utility. Throughput: mean aggregate throughput; delay: the users' mean delay; "
        "PLR: the users' mean packet loss ratio (each averaged over scenarios).",
        "",
        _summary_table(results),
        "",
        "![utility CDF](utility_cdf.png)",
        "",
        "![throughput, delay and PLR CDFs](metrics_cdf.png)",
        "",
        "Single figures: [throughput](throughput_cdf.png), [delay](delay_cdf.png), "
        "[PLR](plr_cdf.png).",
        "",
        "## Utility by heterogeneity index",
        "",
        f"Mean utility per bin of width {HETEROGENEITY_BIN_WIDTH} of the scenarios' "
        "heterogeneity index H (empty bins left out)"
        + (f", and each policy's ratio to `{REFERENCE_POLICY}`." if headline_lines else "."),
        "",
        _bins_table(results, bins),
        "",
        "![utility by heterogeneity](utility_by_heterogeneity.png)",
        "",
    ]
    lines += _altitude_section(results, altitude_profiles)
    if learning is not None:
        lines += _learning_section(learning)
    lines += ["## Evaluation settings", "", _settings_table(results), ""]
    return "\n".join(lines)
