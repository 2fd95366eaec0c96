"""The report's altitude figure: utility against altitude, and where each policy flew.

``tupa eval --altitude-profiles N`` writes, beside its results, the first N scenarios' curves
(:mod:`policies.placements.altitude`: at each altitude, the best episode utility over the zone
centres). :func:`load_altitude_profiles` reads them from every eval file of a results directory (the
first file that has a scenario's curve gives it); :func:`altitude_figure` draws one panel per
scenario, at most :data:`COLUMNS` to a row, with each policy's end of episode in that scenario as a
marker at (its altitude, its episode utility); :func:`altitude_lines` is the report's paragraph and
table. Every profile is drawn up to :data:`MAX_PANELS`; the ones beyond are named in the figure, in
a warning and in the paragraph (the table lists every profile).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from policies.report.checks import fail, finite_number, non_empty_text, read_json
from policies.report.curves import LEARNING_CURVE_FILE
from policies.report.inputs import PolicyResult, Warn

MAX_PANELS = 12
"""Panels in the figure at most (3 rows of :data:`COLUMNS`): more would be unreadable."""
COLUMNS = 4
FIGURE_FILE = "altitude.png"


@dataclass(frozen=True)
class ProfileCurve:
    """One scenario's utility against altitude, as read from an eval file."""

    scenario_id: str
    environment: str
    altitudes_m: np.ndarray
    best_utility: np.ndarray


def _parse_profile(raw: Any, label: str, where: str) -> ProfileCurve:
    if not isinstance(raw, dict):
        raise fail(label, where, "must be an object")
    for key in ("id", "altitudes_m", "best_utility"):
        if key not in raw:
            raise fail(label, where, f"{key}: missing")
    curves = {}
    for key in ("altitudes_m", "best_utility"):
        values = raw[key]
        if not isinstance(values, list) or len(values) < 2:
            raise fail(label, where, f"{key}: must be a list of at least 2 numbers")
        curves[key] = np.array(
            [finite_number(v, label, f"{where}.{key}[{i}]") for i, v in enumerate(values)]
        )
    if len(curves["altitudes_m"]) != len(curves["best_utility"]):
        raise fail(label, where, "best_utility: must have one value per altitude")
    return ProfileCurve(
        scenario_id=non_empty_text(raw["id"], label, f"{where}.id"),
        environment=str(raw.get("environment", "open")),
        **curves,
    )


def load_altitude_profiles(results_dir: Path) -> list[ProfileCurve]:
    """The altitude profiles of the eval files in ``results_dir``, in file then list order,
    one per scenario id (the first seen). Files :func:`policies.report.inputs.load_eval_results`
    skips are skipped here too; a bad profile field is an :class:`InputError` naming it."""
    profiles: dict[str, ProfileCurve] = {}
    for path in sorted(Path(results_dir).glob("*.json")):
        if path.name == LEARNING_CURVE_FILE or path.name.startswith(".") or not path.is_file():
            continue
        document = read_json(path)
        if not isinstance(document, dict) or "altitude_profiles" not in document:
            continue
        raw = document["altitude_profiles"]
        if not isinstance(raw, list):
            raise fail(str(path), "altitude_profiles", "must be a list")
        for i, item in enumerate(raw):
            curve = _parse_profile(item, str(path), f"altitude_profiles[{i}]")
            profiles.setdefault(curve.scenario_id, curve)
    return list(profiles.values())


def _ends(results: Sequence[PolicyResult], scenario_id: str) -> list[tuple[str, float, float]]:
    """(policy, altitude, utility) where each policy with recorded altitudes ended the
    scenario's episode."""
    ends = []
    for r in results:
        if r.altitude_m is not None and scenario_id in r.ids:
            i = r.ids.index(scenario_id)
            ends.append((r.policy, float(r.altitude_m[i]), float(r.utility[i])))
    return ends


def left_out_note(profiles: Sequence[ProfileCurve]) -> str | None:
    """What the figure leaves out of ``profiles`` and why, in one line (None: nothing)."""
    left_out = [p.scenario_id for p in profiles[MAX_PANELS:]]
    if not left_out:
        return None
    return (
        f"{FIGURE_FILE}: {len(left_out)} of {len(profiles)} altitude profiles not drawn "
        f"({', '.join(left_out)}): at most {MAX_PANELS} panels; results.md's table has them all"
    )


def altitude_figure(
    profiles: Sequence[ProfileCurve],
    results: Sequence[PolicyResult],
    styles: dict[str, dict[str, Any]],
    warn: Warn | None = None,
) -> bytes:
    """:func:`altitude_drawing` as PNG bytes."""
    from policies.report.figures import _png

    return _png(altitude_drawing(profiles, results, styles, warn))


def altitude_drawing(
    profiles: Sequence[ProfileCurve],
    results: Sequence[PolicyResult],
    styles: dict[str, dict[str, Any]],
    warn: Warn | None = None,
) -> Any:
    """The figure: one panel per profile, at most :data:`COLUMNS` to a row, up to :data:`MAX_PANELS`
    (the profiles beyond are named below the panels and, once, to ``warn``): the best utility
    at each altitude (line), and each policy's end of episode (marker, in the policy's report
    colour)."""
    from policies.report.figures import _new_figure

    shown = list(profiles[:MAX_PANELS])
    rows = -(-len(shown) // COLUMNS)
    columns = -(-len(shown) // rows)  # balanced: 5 panels are 3 + 2, not 4 + 1
    figure = _new_figure(3.4 * columns + 0.6, 3.4 * rows + 0.3)
    grid = figure.subplots(rows, columns, squeeze=False, sharey=True)
    axes = [ax for row in grid for ax in row]
    for ax in axes[len(shown) :]:
        ax.set_axis_off()  # the last row's empty places
    axes = axes[: len(shown)]
    markers = "osD^v<>p*h"
    for ax, curve in zip(axes, shown, strict=True):
        ax.plot(curve.altitudes_m, curve.best_utility, color="0.3", linewidth=1.6)
        best = int(np.argmax(curve.best_utility))
        ax.axvline(curve.altitudes_m[best], color="0.6", linewidth=0.8, linestyle=":")
        for k, (policy, z_m, utility) in enumerate(_ends(results, curve.scenario_id)):
            ax.plot(
                [z_m],
                [utility],
                linestyle="none",
                marker=markers[k % len(markers)],
                markersize=6,
                markerfacecolor="none",
                markeredgewidth=1.4,
                color=styles.get(policy, {}).get("color", "black"),
                label=policy,
            )
        ax.set_title(f"{curve.scenario_id} ({curve.environment})", fontsize=9)
        ax.set_xlabel("altitude (m)")
        ax.grid(True, alpha=0.3)
    for row in grid:
        row[0].set_ylabel("episode utility (best (x, y) at each altitude)")
    handles, labels = axes[0].get_legend_handles_labels()
    if handles:
        axes[-1].legend(handles, labels, loc="lower right", fontsize=7, framealpha=0.9)
    note = left_out_note(profiles)
    if note:
        figure.supxlabel(note.removeprefix(f"{FIGURE_FILE}: "), fontsize=8, color="0.25")
        if warn is not None:
            warn(note)
    return figure


def altitude_lines(profiles: Sequence[ProfileCurve]) -> list[str]:
    """The report's paragraph on the profiles: the figure and, per scenario, the best
    altitude against the floor and the ceiling."""
    if not profiles:
        return []
    rows = []
    for c in profiles:
        best = int(np.argmax(c.best_utility))
        rows.append(
            f"| {c.scenario_id} | {c.environment} | {c.altitudes_m[best]:.0f} | "
            f"{c.best_utility[best]:.3f} | {c.best_utility[0]:.3f} | {c.best_utility[-1]:.3f} |"
        )
    note = left_out_note(profiles)
    return [
        "Utility against altitude for the first scenarios: at each altitude, the mean episode "
        "utility at the best zone centre (the model's expected mode); markers are where each "
        "policy ended its episode in that scenario, at its episode's utility (that episode's "
        "own fading and line-of-sight draws, so a marker may sit above the curve).",
        "",
        *([f"{note}.", ""] if note else []),
        f"![utility against altitude]({FIGURE_FILE})",
        "",
        "| scenario | environment | best altitude (m) | utility there | at the floor | "
        "at the ceiling |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
        *rows,
        "",
    ]
