"""The report's inputs, read and checked: every eval file in a results directory, and the
learning curve beside them.

* **eval files**: every ``*.json`` written by ``tupa eval`` (one policy: an object with
  ``policy`` and ``scenarios``; several: ``{"results": [object, ...]}``). Each policy may appear
  in one file only. JSON files of any other shape (a scenario file, a checkpoint's metadata, a
  benchmark) are skipped with a warning; a file that is not valid JSON, or an eval file with a
  bad field, is an error.
* **learning curve** (optional): ``learning_curve.json``, see :mod:`policies.report.curves`.

Same scenarios for every policy: the eval files must cover exactly the same scenario ids, and
the same id must carry the same heterogeneity index H in every file (ids like ``s0000`` repeat
across generated sets, H tells the sets apart). Anything else is an error naming the policies:
a policy scored on a different subset would shift every CDF and every per-bin gain, and a
silent intersection would hide that. Differing evaluation settings (seed, queueing, episode
length, mode) are only warned about and shown in the report's settings table.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from policies.learned.checkpoints import RUN_FILE, training_run
from policies.report.checks import (
    check_scenario_ids,
    fail,
    finite_number,
    non_empty_text,
    read_json,
)
from policies.report.curves import LEARNING_CURVE_FILE, LearningCurves, load_learning_curve
from sim.errors import InputError

ORACLE_POLICY = "oracle"
BASELINE_POLICIES = ("min-distance", "load-weighted")  # drawn dashed; the oracle dotted
SETTINGS = ("seed", "queueing", "episode_steps", "mode", "environment")  # an evaluation's

_NOT_EVAL_FILES = (LEARNING_CURVE_FILE, RUN_FILE)
_SCENARIO_NUMBERS = ("utility", "heterogeneity", "throughput_bps", "delay_s", "plr")
_H_TOLERANCE = 1e-9

Warn = Callable[[str], None]


def stderr_warning(message: str) -> None:
    """The default ``warn``: one line on standard error."""
    print(f"tupa report: warning: {message}", file=sys.stderr)


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
    altitude_m: np.ndarray | None = None
    """Where the UAV ended each episode, its altitude (``uav_xyz_m[2]``); None when the file
    does not say (written before ``tupa eval`` recorded it)."""

    def reordered(self, ids: Sequence[str]) -> PolicyResult:
        """The same results in the order of ``ids`` (a permutation of ``self.ids``)."""
        position = {scenario_id: i for i, scenario_id in enumerate(self.ids)}
        order = np.array([position[scenario_id] for scenario_id in ids], dtype=int)
        return PolicyResult(
            policy=self.policy,
            source=self.source,
            ids=tuple(ids),
            settings=self.settings,
            altitude_m=None if self.altitude_m is None else self.altitude_m[order],
            **{name: getattr(self, name)[order] for name in _SCENARIO_NUMBERS},
        )


# --------------------------------------------------------------------------------------------
# One eval file


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
        raise fail(label, where, "must be an object")
    for key in ("policy", "scenarios"):
        if key not in raw:
            raise fail(label, where, f"{key}: missing")
    name = non_empty_text(raw["policy"], label, f"{where}.policy")
    where = f"{where} ({name})" if where else name
    rows = raw["scenarios"]
    if not isinstance(rows, list) or not rows:
        raise fail(label, where, "scenarios: must be a non-empty list")
    ids: list[str] = []
    numbers: dict[str, list[float]] = {key: [] for key in _SCENARIO_NUMBERS}
    altitudes: list[float] = []
    for i, row in enumerate(rows):
        at = f"scenarios[{i}]"
        if not isinstance(row, dict):
            raise fail(label, where, at, "must be an object")
        for key in ("id", *_SCENARIO_NUMBERS):
            if key not in row:
                raise fail(label, where, f"{at}.{key}", "missing")
        ids.append(non_empty_text(row["id"], label, f"{where}: {at}.id"))
        for key in _SCENARIO_NUMBERS:
            numbers[key].append(finite_number(row[key], label, f"{where}: {at}.{key}"))
        if "uav_xyz_m" in row:
            xyz = row["uav_xyz_m"]
            if not isinstance(xyz, list) or len(xyz) != 3:
                raise fail(label, where, f"{at}.uav_xyz_m", "must be [x, y, z]")
            altitudes.append(finite_number(xyz[2], label, f"{where}: {at}.uav_xyz_m[2]"))
    check_scenario_ids(ids, raw, label, where)
    return PolicyResult(
        policy=name,
        source=path,
        ids=tuple(ids),
        settings={key: raw[key] for key in SETTINGS if key in raw},
        altitude_m=np.array(altitudes) if len(altitudes) == len(rows) else None,
        **{key: np.array(values) for key, values in numbers.items()},
    )


def _parse_eval_document(document: dict[str, Any], path: Path) -> list[PolicyResult]:
    if "results" not in document:
        return [_parse_policy(document, path, "")]
    results = document["results"]
    if not isinstance(results, list) or not results:
        raise fail(str(path), "results", "must be a non-empty list")
    return [_parse_policy(raw, path, f"results[{i}]") for i, raw in enumerate(results)]


# --------------------------------------------------------------------------------------------
# Across files


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
    for key in SETTINGS:
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


def load_eval_results(results_dir: Path, warn: Warn = stderr_warning) -> list[PolicyResult]:
    """Every policy's results from the eval files in ``results_dir``, checked (see the module
    doc), over the same scenarios in the same order, in display order (others, then the
    baselines, then the oracle). Files are read in name order; ``learning_curve.json``,
    ``run.json`` (a training run's state, in a ``tupa train`` directory) and hidden files are
    not eval files; other non-eval JSON is skipped with ``warn``. A directory without eval
    files is an ``InputError``; for a training run's, naming the ``tupa eval`` that makes one."""
    results_dir = Path(results_dir)
    if not results_dir.is_dir():
        raise InputError(f"--results: {results_dir}: not a directory")
    results: list[PolicyResult] = []
    for path in sorted(results_dir.glob("*.json")):
        if path.name in _NOT_EVAL_FILES or path.name.startswith(".") or not path.is_file():
            continue
        document = read_json(path)
        if not _is_eval_document(document):
            warn(f"{path}: not a tupa eval result (no policy/scenarios or results), skipped")
            continue
        results.extend(_parse_eval_document(document, path))
    if not results:
        raise InputError(_nothing_to_report(results_dir))
    _check_unique_policies(results)
    results = _check_same_scenarios(results)
    _warn_on_settings(results, warn)
    return _display_order(results)


# --------------------------------------------------------------------------------------------
# Everything in a results directory


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


def _nothing_to_report(results_dir: Path) -> str:
    """The error for a results directory without eval files: for a training run's directory,
    the ``tupa eval`` command that makes one (its latest checkpoint when it was interrupted)."""
    run = training_run(results_dir)
    if run is None:
        return f"--results: {results_dir}: no tupa eval results (*.json) found"
    if run.finished:
        policy, state = results_dir, "a training run"
    elif run.latest is not None:
        policy, state = run.latest, f"a training run, interrupted after {run.progress()}"
    else:
        return (
            f"--results: {results_dir} is a training run with no checkpoint yet: nothing to report"
        )
    test = run.test_scenarios or "TEST.json"
    return (
        f"--results: {results_dir} is {state}, not tupa eval results: evaluate it first, e.g. "
        f"tupa eval --policy {policy} --scenarios {test} --json {results_dir / 'eval.json'} "
        f"(then tupa report --results {results_dir} draws it with its learning curve)"
    )


def load_inputs(
    results_dir: Path, warn: Warn = stderr_warning
) -> tuple[list[PolicyResult], LearningCurves | None]:
    """The eval results in ``results_dir`` (:func:`load_eval_results`) and its
    ``learning_curve.json`` if there is one (None otherwise). A reference in the curve that
    differs from the same policy's median utility in the eval files is warned about."""
    results_dir = Path(results_dir)
    results = load_eval_results(results_dir, warn)
    curve_path = results_dir / LEARNING_CURVE_FILE
    learning = load_learning_curve(curve_path) if curve_path.exists() else None
    if learning is not None:
        _warn_on_reference(results, learning, warn)
    return results, learning
