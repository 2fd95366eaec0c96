"""The learning-curve file, ``learning_curve.json`` (format ``tupa-learning-curve/1``): its
reader for ``tupa report`` and its writer for the trainer.

::

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

The trainer imports :func:`write_learning_curve`; nothing here draws (no matplotlib).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from policies.report.checks import fail, finite_number, non_empty_text, read_json
from sim.atomic import atomic_write_json

LEARNING_CURVE_FORMAT = "tupa-learning-curve/1"
LEARNING_CURVE_FILE = "learning_curve.json"


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


def _parse_point(raw: Any, label: str, where: str) -> CurvePoint:
    if not isinstance(raw, dict):
        raise fail(label, where, "must be an object")
    for key in ("episodes", "median_utility"):
        if key not in raw:
            raise fail(label, f"{where}.{key}", "missing")
    episodes = raw["episodes"]
    if not isinstance(episodes, int) or isinstance(episodes, bool) or episodes < 1:
        raise fail(label, f"{where}.episodes", f"must be an integer >= 1, got {episodes!r}")
    median = finite_number(raw["median_utility"], label, f"{where}.median_utility")
    mean = raw.get("mean_utility")
    if mean is not None:
        mean = finite_number(mean, label, f"{where}.mean_utility")
    return CurvePoint(episodes=episodes, median_utility=median, mean_utility=mean)


def _parse_curve(raw: Any, label: str, where: str) -> LearningCurve:
    if not isinstance(raw, dict):
        raise fail(label, where, "must be an object")
    if "label" not in raw:
        raise fail(label, f"{where}.label", "missing")
    name = non_empty_text(raw["label"], label, f"{where}.label")
    points = raw.get("points")
    if not isinstance(points, list) or not points:
        raise fail(label, f"{where} ({name})", "points: must be a non-empty list")
    parsed = [
        _parse_point(p, label, f"{where} ({name}): points[{i}]") for i, p in enumerate(points)
    ]
    episodes = [p.episodes for p in parsed]
    if len(set(episodes)) != len(episodes):
        repeated = sorted({e for e in episodes if episodes.count(e) > 1})
        raise fail(label, f"{where} ({name})", f"points: episodes repeated: {repeated}")
    return LearningCurve(label=name, points=tuple(sorted(parsed, key=lambda p: p.episodes)))


def parse_learning_curve(document: Any, label: str = LEARNING_CURVE_FILE) -> LearningCurves:
    """Check a learning-curve document (see the module doc) and return it parsed, points
    sorted by episodes. Raises :class:`InputError` naming ``label``, the curve and the field."""
    if not isinstance(document, dict):
        raise fail(label, "top level", "must be an object")
    if document.get("format") != LEARNING_CURVE_FORMAT:
        got = json.dumps(document.get("format"))[:40]
        raise fail(label, "format", f'expected "{LEARNING_CURVE_FORMAT}", got {got}')
    curves = document.get("curves")
    if not isinstance(curves, list) or not curves:
        raise fail(label, "curves", "must be a non-empty list")
    parsed = [_parse_curve(c, label, f"curves[{i}]") for i, c in enumerate(curves)]
    labels = [c.label for c in parsed]
    if len(set(labels)) != len(labels):
        repeated = sorted({x for x in labels if labels.count(x) > 1})
        raise fail(label, "curves", f"labels repeated: {', '.join(repeated)}")
    reference = document.get("reference", {})
    if not isinstance(reference, dict):
        raise fail(label, "reference", "must be an object {policy: median utility}")
    values = {str(k): finite_number(v, label, f"reference.{k}") for k, v in reference.items()}
    return LearningCurves(curves=tuple(parsed), reference=values)


def load_learning_curve(path: Path) -> LearningCurves:
    """Read and check a ``learning_curve.json`` (see :func:`parse_learning_curve`)."""
    return parse_learning_curve(read_json(Path(path)), str(path))


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
