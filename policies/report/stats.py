"""The numbers behind the report's tables and figures, recomputed from the per-scenario rows:
utility per heterogeneity bin, the 25th percentile, and the paper's two headline gains."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from policies.evaluation.evaluation import (
    HETEROGENEITY_BIN_WIDTH,
    REFERENCE_POLICY,
    heterogeneity_bin,
)
from policies.report.inputs import PolicyResult

MIN_BIN_SCENARIOS = 10  # the "bins that hold at least 10 scenarios"


@dataclass(frozen=True)
class HeterogeneityBins:
    """Mean utility per non-empty H bin: ``index`` (bin i is [i·w, (i+1)·w)), ``count`` of
    scenarios, ``mean[p, b]`` for policy p (in the results' order) and bin b."""

    index: np.ndarray
    count: np.ndarray
    mean: np.ndarray

    def label(self, b: int) -> str:
        w = HETEROGENEITY_BIN_WIDTH
        return f"[{self.index[b] * w:.2f}, {(self.index[b] + 1) * w:.2f})"


def heterogeneity_bins(results: Sequence[PolicyResult]) -> HeterogeneityBins:
    """Bin the scenarios by H (width 0.05, as ``tupa eval``'s table) and average each policy's
    utility per bin; empty bins are left out."""
    bins = np.array([heterogeneity_bin(h) for h in results[0].heterogeneity])
    index = np.unique(bins)
    count = np.array([int(np.sum(bins == b)) for b in index])
    mean = np.array([[r.utility[bins == b].mean() for b in index] for r in results])
    return HeterogeneityBins(index=index, count=count, mean=mean)


def p25(values: np.ndarray) -> float:
    """The 25th percentile with linear interpolation (as ``tupa eval``)."""
    return float(np.percentile(values, 25))


def ratio(value: float, reference: float) -> str:
    """``value / reference`` as ``"1.23x"``, ``"n/a"`` when the reference is not positive."""
    return f"{value / reference:.2f}x" if reference > 0 else "n/a"


def headlines(results: Sequence[PolicyResult], bins: HeterogeneityBins) -> list[str]:
    """The paper's two headline numbers (p25 gain, gain in the most heterogeneous bin) as we
    measure them, one line per policy against min-distance (none without min-distance)."""
    names = [r.policy for r in results]
    if REFERENCE_POLICY not in names:
        return []
    ref = names.index(REFERENCE_POLICY)
    ref_p25 = p25(results[ref].utility)
    top = len(bins.index) - 1
    populated = np.flatnonzero(bins.count >= MIN_BIN_SCENARIOS)
    lines = []
    for p, result in enumerate(results):
        if p == ref:
            continue
        own_p25 = p25(result.utility)
        line = (
            f"{result.policy} vs {REFERENCE_POLICY}: p25 utility {own_p25:.3f} vs "
            f"{ref_p25:.3f} = {ratio(own_p25, ref_p25)} (paper: ~1.75x); most heterogeneous "
            f"bin H {bins.label(top)} (n={bins.count[top]}): {bins.mean[p, top]:.3f} vs "
            f"{bins.mean[ref, top]:.3f} = {ratio(bins.mean[p, top], bins.mean[ref, top])} "
            "(paper: ~4x)"
        )
        if populated.size and populated[-1] != top:
            b = int(populated[-1])
            line += (
                f"; highest bin with >= {MIN_BIN_SCENARIOS} scenarios, H {bins.label(b)} "
                f"(n={bins.count[b]}): {ratio(bins.mean[p, b], bins.mean[ref, b])}"
            )
        lines.append(line)
    return lines
