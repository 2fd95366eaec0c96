"""The paper's figures and tables from ``tupa eval`` results: ``tupa report``.

Inputs, all in one results directory:

* **eval files**: every ``*.json`` written by ``tupa eval`` (one policy: an object with
  ``policy`` and ``scenarios``; several: ``{"results": [object, ...]}``). Each policy may appear
  in one file only. JSON files of any other shape (a scenario file, a checkpoint's metadata, a
  benchmark) are skipped with a warning; a file that is not valid JSON, or an eval file with a
  bad field, is an error.
* **learning curve** (optional): ``learning_curve.json`` in the format ``tupa-learning-curve/1``,
  written by the trainer with :func:`write_learning_curve`::

      {"format": "tupa-learning-curve/1",
       "curves": [{"label": "ddqn-gen10k",
                   "points": [{"episodes": 100, "median_utility": 0.81, "mean_utility": 0.80},
                              ...]}],
       "reference": {"min-distance": 0.95, "oracle": 0.99}}

  ``label`` names the trained version (the policy name its checkpoint evaluates under, so that
  the figures give it the same colour); each point is one training session of ``episodes``
  episodes, evaluated on the test set: ``median_utility`` (required) and ``mean_utility``
  (optional) of the per-scenario mean utility. Extra keys in a point are ignored (free for wall
  time, a checkpoint path...). ``reference`` (optional) holds the median utility of baselines on
  the same test set, drawn as horizontal lines.

Same scenarios for every policy: the eval files must cover exactly the same scenario ids, and
the same id must carry the same heterogeneity index H in every file (ids like ``s0000`` repeat
across generated sets, H tells the sets apart). Anything else is an error naming the policies:
a policy scored on a different subset would shift every CDF and every per-bin gain, and a
silent intersection would hide that. Differing evaluation settings (seed, queueing, episode
length, mode) are only warned about and shown in the report's settings table.

Outputs (:func:`build_report`), written only once every input has been read and checked, each
file atomically: ``utility_cdf.png``, ``throughput_cdf.png``, ``delay_cdf.png``, ``plr_cdf.png``,
``metrics_cdf.png`` (the three metric CDFs side by side, as the paper's figure),
``utility_by_heterogeneity.png``, ``learning_curve.png`` (only with a learning curve) and
``results.md`` (the tables behind the figures and the paper's two headline numbers as we
measure them). Summaries are recomputed from the per-scenario rows, not copied from the files.

matplotlib is imported only when drawing, so the trainer can import :func:`write_learning_curve`
without it.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import sys
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from policies.evaluation import HETEROGENEITY_BIN_WIDTH, REFERENCE_POLICY, heterogeneity_bin
from sim.errors import InputError
from sim.files import atomic_write_json, atomic_write_text, replacement_mode

LEARNING_CURVE_FORMAT = "tupa-learning-curve/1"
LEARNING_CURVE_FILE = "learning_curve.json"
REPORT_FILE = "results.md"
ORACLE_POLICY = "oracle"
BASELINE_POLICIES = ("min-distance", "load-weighted")  # drawn dashed; the oracle dotted
MIN_BIN_SCENARIOS = 10  # the "bins that hold at least 10 scenarios"

_SCENARIO_NUMBERS = ("utility", "heterogeneity", "throughput_bps", "delay_s", "plr")
_SETTINGS = ("seed", "queueing", "episode_steps", "mode")
_H_TOLERANCE = 1e-9
_DPI = 150

Warn = Callable[[str], None]


def _stderr_warning(message: str) -> None:
    print(f"tupa report: warning: {message}", file=sys.stderr)


# --------------------------------------------------------------------------------------------
# Data


@dataclass(frozen=True)
class PolicyResult:
    """One policy's per-scenario results from an eval file (arrays in scenario order).

    ``utility`` is each scenario's episode-mean network utility, ``throughput_bps`` the mean
    aggregate throughput, ``delay_s`` and ``plr`` the users' mean delay and packet loss ratio,
    ``heterogeneity`` the scenario's index H. ``settings`` holds the evaluation's ``seed``,
    ``queueing``, ``episode_steps`` and ``mode`` where the file has them.
    """

    policy: str
    source: Path
    ids: tuple[str, ...]
    utility: np.ndarray
    heterogeneity: np.ndarray
    throughput_bps: np.ndarray
    delay_s: np.ndarray
    plr: np.ndarray
    settings: dict[str, Any] = field(default_factory=dict)

    def reordered(self, ids: Sequence[str]) -> PolicyResult:
        """The same results in the order of ``ids`` (a permutation of ``self.ids``)."""
        position = {scenario_id: i for i, scenario_id in enumerate(self.ids)}
        order = np.array([position[scenario_id] for scenario_id in ids], dtype=int)
        return PolicyResult(
            policy=self.policy,
            source=self.source,
            ids=tuple(ids),
            settings=self.settings,
            **{name: getattr(self, name)[order] for name in _SCENARIO_NUMBERS},
        )


@dataclass(frozen=True)
class CurvePoint:
    """One training session: ``episodes`` trained, then evaluated on the test set."""

    episodes: int
    median_utility: float
    mean_utility: float | None = None


@dataclass(frozen=True)
class LearningCurve:
    """The points of one trained version (``label``, e.g. ``"ddqn-gen10k"``), by episodes."""

    label: str
    points: tuple[CurvePoint, ...]


@dataclass(frozen=True)
class LearningCurves:
    """A parsed ``learning_curve.json``: the curves and the baselines' median utilities."""

    curves: tuple[LearningCurve, ...]
    reference: dict[str, float]


@dataclass(frozen=True)
class Report:
    """What :func:`build_report` wrote: the files, and one headline line per compared policy."""

    written: tuple[Path, ...]
    headlines: tuple[str, ...]


# --------------------------------------------------------------------------------------------
# Small validation helpers: messages are "<file>: <item>: <field>: <problem>"


def _fail(label: str, *parts: str) -> InputError:
    return InputError(": ".join([label, *[p for p in parts if p]]))


def _number(value: Any, label: str, where: str) -> float:
    if isinstance(value, int | float) and not isinstance(value, bool):
        with contextlib.suppress(OverflowError):
            number = float(value)
            if math.isfinite(number):
                return number
    raise _fail(label, where, f"must be a finite number, got {json.dumps(value)[:40]}")


def _text(value: Any, label: str, where: str) -> str:
    if isinstance(value, str) and value.strip():
        return value
    raise _fail(label, where, f"must be a non-empty string, got {json.dumps(value)[:40]}")


def _read_json(path: Path) -> Any:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or getattr(exc, "reason", None) or exc
        raise _fail(str(path), f"cannot read: {reason}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise _fail(
            str(path), f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    except RecursionError:
        raise _fail(str(path), "not valid JSON: nested too deeply") from None


# --------------------------------------------------------------------------------------------
# The learning-curve file


def _parse_point(raw: Any, label: str, where: str) -> CurvePoint:
    if not isinstance(raw, dict):
        raise _fail(label, where, "must be an object")
    for key in ("episodes", "median_utility"):
        if key not in raw:
            raise _fail(label, f"{where}.{key}", "missing")
    episodes = raw["episodes"]
    if not isinstance(episodes, int) or isinstance(episodes, bool) or episodes < 1:
        raise _fail(label, f"{where}.episodes", f"must be an integer >= 1, got {episodes!r}")
    median = _number(raw["median_utility"], label, f"{where}.median_utility")
    mean = raw.get("mean_utility")
    if mean is not None:
        mean = _number(mean, label, f"{where}.mean_utility")
    return CurvePoint(episodes=episodes, median_utility=median, mean_utility=mean)


def _parse_curve(raw: Any, label: str, where: str) -> LearningCurve:
    if not isinstance(raw, dict):
        raise _fail(label, where, "must be an object")
    if "label" not in raw:
        raise _fail(label, f"{where}.label", "missing")
    name = _text(raw["label"], label, f"{where}.label")
    points = raw.get("points")
    if not isinstance(points, list) or not points:
        raise _fail(label, f"{where} ({name})", "points: must be a non-empty list")
    parsed = [
        _parse_point(p, label, f"{where} ({name}): points[{i}]") for i, p in enumerate(points)
    ]
    episodes = [p.episodes for p in parsed]
    if len(set(episodes)) != len(episodes):
        repeated = sorted({e for e in episodes if episodes.count(e) > 1})
        raise _fail(label, f"{where} ({name})", f"points: episodes repeated: {repeated}")
    return LearningCurve(label=name, points=tuple(sorted(parsed, key=lambda p: p.episodes)))


def parse_learning_curve(document: Any, label: str = LEARNING_CURVE_FILE) -> LearningCurves:
    """Check a learning-curve document (see the module doc) and return it parsed, points
    sorted by episodes. Raises :class:`InputError` naming ``label``, the curve and the field."""
    if not isinstance(document, dict):
        raise _fail(label, "top level", "must be an object")
    if document.get("format") != LEARNING_CURVE_FORMAT:
        got = json.dumps(document.get("format"))[:40]
        raise _fail(label, "format", f'expected "{LEARNING_CURVE_FORMAT}", got {got}')
    curves = document.get("curves")
    if not isinstance(curves, list) or not curves:
        raise _fail(label, "curves", "must be a non-empty list")
    parsed = [_parse_curve(c, label, f"curves[{i}]") for i, c in enumerate(curves)]
    labels = [c.label for c in parsed]
    if len(set(labels)) != len(labels):
        repeated = sorted({x for x in labels if labels.count(x) > 1})
        raise _fail(label, "curves", f"labels repeated: {', '.join(repeated)}")
    reference = document.get("reference", {})
    if not isinstance(reference, dict):
        raise _fail(label, "reference", "must be an object {policy: median utility}")
    values = {str(k): _number(v, label, f"reference.{k}") for k, v in reference.items()}
    return LearningCurves(curves=tuple(parsed), reference=values)


def load_learning_curve(path: Path) -> LearningCurves:
    """Read and check a ``learning_curve.json`` (see :func:`parse_learning_curve`)."""
    return parse_learning_curve(_read_json(Path(path)), str(path))


def learning_curve_document(
    curves: Sequence[LearningCurve | Mapping[str, Any]],
    reference: Mapping[str, float] | None = None,
) -> dict[str, Any]:
    """The JSON document for ``curves`` (:class:`LearningCurve` objects, or dicts already in
    the file's shape) and ``reference`` ({baseline: median utility}), checked as the reader
    checks it, so every document written can be read back."""

    def as_dict(curve: LearningCurve | Mapping[str, Any]) -> dict[str, Any]:
        if isinstance(curve, LearningCurve):
            points = []
            for p in curve.points:
                point: dict[str, Any] = {"episodes": p.episodes, "median_utility": p.median_utility}
                if p.mean_utility is not None:
                    point["mean_utility"] = p.mean_utility
                points.append(point)
            return {"label": curve.label, "points": points}
        return {"label": curve.get("label"), "points": list(curve.get("points", []))}

    document = {
        "format": LEARNING_CURVE_FORMAT,
        "curves": [as_dict(c) for c in curves],
        "reference": {str(k): float(v) for k, v in (reference or {}).items()},
    }
    parse_learning_curve(document, "learning curve")
    return document


def write_learning_curve(
    path: Path,
    curves: Sequence[LearningCurve | Mapping[str, Any]],
    reference: Mapping[str, float] | None = None,
) -> None:
    """Write ``learning_curve.json`` atomically (see :func:`learning_curve_document`).

    Example, after training sessions of 100 and 1000 episodes::

        write_learning_curve(out / "learning_curve.json",
            [{"label": "ddqn-gen10k", "points": [
                {"episodes": 100, "median_utility": 0.81, "mean_utility": 0.80},
                {"episodes": 1000, "median_utility": 0.97, "mean_utility": 0.93}]}],
            {"min-distance": 0.95, "oracle": 0.99})

    Raises :class:`InputError` (a ``ValueError``) on a bad curve, before touching the file.
    """
    atomic_write_json(Path(path), learning_curve_document(curves, reference))


# --------------------------------------------------------------------------------------------
# Eval files


def _is_eval_document(document: Any) -> bool:
    """The shapes ``tupa eval`` writes: a policy object (``policy`` and ``scenarios``), or
    ``{"results": [...]}`` whose items are objects with a ``policy`` (so that a benchmark's
    ``{"results": {...}}`` is not mistaken for one). A file of either shape is then checked
    field by field: a bad field is an error, not a skip."""
    if not isinstance(document, dict):
        return False
    if "policy" in document and "scenarios" in document:
        return True
    results = document.get("results")
    return (
        isinstance(results, list)
        and bool(results)
        and all(isinstance(item, dict) and "policy" in item for item in results)
    )


def _parse_policy(raw: Any, path: Path, where: str) -> PolicyResult:
    label = str(path)
    if not isinstance(raw, dict):
        raise _fail(label, where, "must be an object")
    for key in ("policy", "scenarios"):
        if key not in raw:
            raise _fail(label, where, f"{key}: missing")
    name = _text(raw["policy"], label, f"{where}.policy")
    where = f"{where} ({name})" if where else name
    rows = raw["scenarios"]
    if not isinstance(rows, list) or not rows:
        raise _fail(label, where, "scenarios: must be a non-empty list")
    ids: list[str] = []
    numbers: dict[str, list[float]] = {key: [] for key in _SCENARIO_NUMBERS}
    for i, row in enumerate(rows):
        at = f"scenarios[{i}]"
        if not isinstance(row, dict):
            raise _fail(label, where, at, "must be an object")
        for key in ("id", *_SCENARIO_NUMBERS):
            if key not in row:
                raise _fail(label, where, f"{at}.{key}", "missing")
        ids.append(_text(row["id"], label, f"{where}: {at}.id"))
        for key in _SCENARIO_NUMBERS:
            numbers[key].append(_number(row[key], label, f"{where}: {at}.{key}"))
    if len(set(ids)) != len(ids):
        repeated = sorted({x for x in ids if ids.count(x) > 1})
        raise _fail(label, where, "scenarios", f"ids repeated: {', '.join(repeated[:5])}")
    if "n_scenarios" in raw and raw["n_scenarios"] != len(rows):
        raise _fail(
            label, where, "n_scenarios", f"says {raw['n_scenarios']!r}, the list has {len(rows)}"
        )
    return PolicyResult(
        policy=name,
        source=path,
        ids=tuple(ids),
        settings={key: raw[key] for key in _SETTINGS if key in raw},
        **{key: np.array(values) for key, values in numbers.items()},
    )


def _parse_eval_document(document: dict[str, Any], path: Path) -> list[PolicyResult]:
    if "results" not in document:
        return [_parse_policy(document, path, "")]
    results = document["results"]
    if not isinstance(results, list) or not results:
        raise _fail(str(path), "results", "must be a non-empty list")
    return [_parse_policy(raw, path, f"results[{i}]") for i, raw in enumerate(results)]


def _check_unique_policies(results: Sequence[PolicyResult]) -> None:
    seen: dict[str, PolicyResult] = {}
    for result in results:
        first = seen.setdefault(result.policy, result)
        if first is not result:
            where = (
                f"twice in {result.source}"
                if first.source == result.source
                else f"in both {first.source} and {result.source}"
            )
            raise InputError(f"policy {result.policy!r} appears {where}; keep one of them")


def _check_same_scenarios(results: Sequence[PolicyResult]) -> list[PolicyResult]:
    """All results over the first one's scenarios in its order; an error naming the policies
    if any covers other ids, or the same ids with another heterogeneity (another scenario)."""
    first = results[0]
    aligned = [first]
    for other in results[1:]:
        if set(other.ids) != set(first.ids):
            only_first = sorted(set(first.ids) - set(other.ids))
            only_other = sorted(set(other.ids) - set(first.ids))
            raise InputError(
                f"policies {first.policy!r} ({first.source}, {len(first.ids)} scenarios) and "
                f"{other.policy!r} ({other.source}, {len(other.ids)} scenarios) were evaluated "
                f"on different scenario sets: {_some(only_first)} only in {first.policy!r}, "
                f"{_some(only_other)} only in {other.policy!r}; evaluate every policy on the "
                "same scenario file"
            )
        other = other.reordered(first.ids)
        differ = np.flatnonzero(np.abs(other.heterogeneity - first.heterogeneity) > _H_TOLERANCE)
        if differ.size:
            i = int(differ[0])
            raise InputError(
                f"policies {first.policy!r} ({first.source}) and {other.policy!r} "
                f"({other.source}) share scenario ids but not scenarios: {first.ids[i]} has "
                f"H = {first.heterogeneity[i]:.4f} in one and {other.heterogeneity[i]:.4f} in "
                f"the other ({differ.size} such ids); evaluate every policy on the same "
                "scenario file"
            )
        aligned.append(other)
    return aligned


def _some(ids: Sequence[str]) -> str:
    if not ids:
        return "no ids"
    shown = ", ".join(ids[:3]) + (", ..." if len(ids) > 3 else "")
    return f"{len(ids)} ids ({shown})"


def _warn_on_settings(results: Sequence[PolicyResult], warn: Warn) -> None:
    for key in _SETTINGS:
        values = {json.dumps(r.settings.get(key)) for r in results}
        if len(values) > 1:
            listed = ", ".join(f"{r.policy}={r.settings.get(key, '?')}" for r in results)
            warn(f"policies evaluated with different {key}: {listed}")


def _display_order(results: Sequence[PolicyResult]) -> list[PolicyResult]:
    """Trained and other policies first (as read), then the baselines, the oracle last."""
    fixed = [*BASELINE_POLICIES, ORACLE_POLICY]

    def rank(item: tuple[int, PolicyResult]) -> tuple[int, int]:
        index, result = item
        if result.policy in fixed:
            return (1, fixed.index(result.policy))
        return (0, index)

    return [r for _, r in sorted(enumerate(results), key=rank)]


def load_eval_results(results_dir: Path, warn: Warn = _stderr_warning) -> list[PolicyResult]:
    """Every policy's results from the eval files in ``results_dir``, checked (see the module
    doc), over the same scenarios in the same order, in display order (others, then the
    baselines, then the oracle). Files are read in name order; ``learning_curve.json`` and
    hidden files are not eval files; other non-eval JSON is skipped with ``warn``."""
    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        raise InputError(f"--results: {results_dir}: not a directory")
    results: list[PolicyResult] = []
    for path in sorted(results_dir.glob("*.json")):
        if path.name == LEARNING_CURVE_FILE or path.name.startswith(".") or not path.is_file():
            continue
        document = _read_json(path)
        if not _is_eval_document(document):
            warn(f"{path}: not a tupa eval result (no policy/scenarios or results), skipped")
            continue
        results.extend(_parse_eval_document(document, path))
    if not results:
        raise InputError(f"--results: {results_dir}: no tupa eval results (*.json) found")
    _check_unique_policies(results)
    results = _check_same_scenarios(results)
    _warn_on_settings(results, warn)
    return _display_order(results)


# --------------------------------------------------------------------------------------------
# Numbers behind the figures


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


def _ratio(value: float, reference: float) -> str:
    return f"{value / reference:.2f}x" if reference > 0 else "n/a"


def _headlines(results: Sequence[PolicyResult], bins: HeterogeneityBins) -> list[str]:
    """The paper's two headline numbers (p25 gain, gain in the most heterogeneous bin) as we
    measure them, one line per policy against min-distance."""
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
            f"{ref_p25:.3f} = {_ratio(own_p25, ref_p25)} (paper: ~1.75x); most heterogeneous "
            f"bin H {bins.label(top)} (n={bins.count[top]}): {bins.mean[p, top]:.3f} vs "
            f"{bins.mean[ref, top]:.3f} = {_ratio(bins.mean[p, top], bins.mean[ref, top])} "
            "(paper: ~4x)"
        )
        if populated.size and populated[-1] != top:
            b = int(populated[-1])
            line += (
                f"; highest bin with >= {MIN_BIN_SCENARIOS} scenarios, H {bins.label(b)} "
                f"(n={bins.count[b]}): {_ratio(bins.mean[p, b], bins.mean[ref, b])}"
            )
        lines.append(line)
    return lines


# --------------------------------------------------------------------------------------------
# Markdown


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
            row.append(_ratio(p25(r.utility), p25(ref.utility)))
        row += [
            f"{r.throughput_bps.mean() / 1e6:.2f}",
            f"{r.delay_s.mean() * 1e3:.1f}",
            f"{r.plr.mean():.4f}",
        ]
        rows.append(row)
    return _md_table(header, rows)


def _settings_table(results: Sequence[PolicyResult]) -> str:
    rows = [
        [f"`{r.policy}`", *[str(r.settings.get(k, "?")) for k in _SETTINGS], f"`{r.source.name}`"]
        for r in results
    ]
    header = ["policy", "seed", "queueing", "episode steps", "mode", "file"]
    return _md_table(header, rows, numeric=False)


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
            row += [_ratio(bins.mean[p, b], bins.mean[ref, b]) for p in gains]
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
) -> str:
    """``results.md``: the headline numbers, the tables behind the figures, the figures."""
    bins = heterogeneity_bins(results)
    headlines = _headlines(results, bins)
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
    if headlines:
        lines += [f"- {line}" for line in headlines]
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
        + (f", and each policy's ratio to `{REFERENCE_POLICY}`." if headlines else "."),
        "",
        _bins_table(results, bins),
        "",
        "![utility by heterogeneity](utility_by_heterogeneity.png)",
        "",
    ]
    if learning is not None:
        lines += _learning_section(learning)
    lines += ["## Evaluation settings", "", _settings_table(results), ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Figures (matplotlib's object API with the Agg canvas: no pyplot, no global state)

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


# --------------------------------------------------------------------------------------------
# Writing


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    """``sim.files.atomic_write_text`` for bytes: temporary file in the same directory,
    fsync, rename over ``path``; on an error the temporary file is removed."""
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp_name, replacement_mode(path))
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def _warn_on_reference(
    results: Sequence[PolicyResult], learning: LearningCurves, warn: Warn
) -> None:
    for r in results:
        if r.policy in learning.reference:
            median = float(np.median(r.utility))
            if abs(median - learning.reference[r.policy]) > 5e-4:
                warn(
                    f"{LEARNING_CURVE_FILE}: reference {r.policy} "
                    f"{learning.reference[r.policy]:.3f} differs from its median utility "
                    f"{median:.3f} in {r.source.name} (another test set or seed?)"
                )


def build_report(results_dir: Path, out_dir: Path, warn: Warn = _stderr_warning) -> Report:
    """Read the eval files (and ``learning_curve.json`` if present) in ``results_dir`` and
    write the figures and ``results.md`` to ``out_dir`` (created if missing).

    Everything is read, checked and rendered before the first file is written, so bad input
    (:class:`InputError`) leaves ``out_dir`` untouched. Warnings (skipped files, differing
    evaluation settings) go to ``warn``.
    """
    results_dir, out_dir = Path(results_dir), Path(out_dir)
    results = load_eval_results(results_dir, warn)
    curve_path = results_dir / LEARNING_CURVE_FILE
    learning = load_learning_curve(curve_path) if curve_path.exists() else None
    if learning is not None:
        _warn_on_reference(results, learning, warn)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out: {out_dir}: exists and is not a directory")
    figures = render_figures(results, learning)
    markdown = render_markdown(results, learning, results_dir)
    written = []
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        for name, data in figures.items():
            _atomic_write_bytes(out_dir / name, data)
            written.append(out_dir / name)
        atomic_write_text(out_dir / REPORT_FILE, markdown)
        written.append(out_dir / REPORT_FILE)
    except OSError as exc:
        raise InputError(f"--out: {out_dir}: cannot write: {exc.strerror or exc}") from None
    headlines = _headlines(results, heterogeneity_bins(results))
    return Report(written=tuple(written), headlines=tuple(headlines))
