"""``tupa report --results SWEEP_DIR``: a finished (or partly finished) ``tupa sweep`` merged.

Reads the sweep's state file (:mod:`policies.sweep.state`), every finished trial's final
evaluation and ``learning_curve.json``, and writes to ``--out``:

* ``sweep_learning_curve.png``: per trained version (algorithm-strategy, plus any other grid
  axis that varies, such as the world), the mean utility over the test scenarios against
  training episodes (log axis), a line through the median across seeds and a band from its
  25th to its 75th percentile; min-distance and the oracle as horizontal lines. The mean, as
  every table of ``results.md`` gives it, so that a trial shows one number everywhere (the
  median over the scenarios only when a curve file holds no means, and then said).
* ``results.md``: the trials (failed ones listed with their last error, never dropped), the
  paper's 4 versions (DDQN and DDPG, each with Spec and Gen10k) at their largest budget, every
  other version, Gen500 vs Gen10k per algorithm and budget, the learning-curve table
  (median [p25, p75] across seeds) and the exported checkpoints.
* ``best/<version>-e<episodes>.zip`` (+ ``.json``): per cell of the grid (a version at an
  episode budget), the seed with the highest final mean utility, exported with
  :func:`policies.learned.checkpoints.export_checkpoint` (the metadata says which trial it came
  from).

A seed's learning curve joins its trials of one version: the points every trial's curve file
holds (at 100, 200, 500, ... episodes, on the first ``curve_scenarios`` test scenarios; a
longer trial's point wins over a shorter one's), and each trial's final evaluation on the
whole test set at its own budget. Everything is computed and rendered before the first file is
written; a sweep without a finished trial is an error.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from policies.report.curves import LEARNING_CURVE_FILE, load_learning_curve
from policies.report.inputs import Warn, stderr_warning
from policies.report.output import REPORT_FILE, ReportFiles
from sim.errors import InputError

FIGURE_FILE = "sweep_learning_curve.png"
BEST_DIR = "best"
PAPER_VERSIONS: tuple[str, ...] = ("ddqn-spec", "ddqn-gen10k", "ddpg-spec", "ddpg-gen10k")
_GROUPING_EXCLUDED = ("algorithm", "strategy", "episodes", "seed")


@dataclass
class Finished:
    """One finished trial: its id, parameters, directory and final evaluation."""

    id: str
    params: dict[str, Any]
    dir: Path
    evaluation: dict[str, Any] | None


@dataclass
class Version:
    """A trained version (``label``): its trials, and per seed ``{episodes: (mean, median)}``
    (the mean and the median utility over the test scenarios; the mean is ``None`` in curve
    files that hold only medians). ``statistic`` is the one :meth:`band` spreads across seeds
    (:func:`_versions` sets it, the same for every version of a report)."""

    label: str
    algorithm: str
    strategy: str
    others: str
    trials: list[Finished] = field(default_factory=list)
    curves: dict[int, dict[int, tuple[float | None, float]]] = field(default_factory=dict)
    statistic: str = "mean"

    def band(self) -> list[tuple[int, float, float, float, int]]:
        """``(episodes, median, p25, p75, seeds)`` of :attr:`statistic` across seeds, by
        episodes."""
        by_episodes: dict[int, list[float]] = defaultdict(list)
        for points in self.curves.values():
            for episodes, (mean, median) in points.items():
                value = median if self.statistic == "median" or mean is None else mean
                by_episodes[episodes].append(value)
        rows = []
        for episodes in sorted(by_episodes):
            values = np.array(by_episodes[episodes])
            q25, q50, q75 = np.percentile(values, [25, 50, 75])
            rows.append((episodes, float(q50), float(q25), float(q75), len(values)))
        return rows

    def at_budget(self, episodes: int) -> list[Finished]:
        return [t for t in self.trials if t.params["episodes"] == episodes]

    @property
    def budgets(self) -> list[int]:
        return sorted({t.params["episodes"] for t in self.trials})


def build_sweep_report(sweep_dir: Path, out_dir: Path, warn: Warn = stderr_warning) -> Any:
    """Merge the sweep in ``sweep_dir`` into ``out_dir`` (see the module doc); returns the
    :class:`policies.report.output.ReportFiles` written."""
    from policies.sweep.state import read_state
    from sim.atomic import atomic_write_bytes, atomic_write_text

    sweep_dir, out_dir = Path(sweep_dir), Path(out_dir)
    state = read_state(sweep_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out: {out_dir}: exists and is not a directory")
    finished, unfinished = _read_trials(state, sweep_dir, warn)
    versions = _versions(finished)
    reference = _reference(finished, _statistic(versions))
    figure = _figure(versions, reference)
    cells = _best_per_cell(versions)
    markdown = _markdown(state, versions, reference, unfinished, cells)
    written = []
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(out_dir / FIGURE_FILE, figure)
        written.append(out_dir / FIGURE_FILE)
        written.extend(_export(cells, state, sweep_dir, out_dir / BEST_DIR))
        atomic_write_text(out_dir / REPORT_FILE, markdown)
        written.append(out_dir / REPORT_FILE)
    except OSError as exc:
        raise InputError(f"--out: {out_dir}: cannot write: {exc.strerror or exc}") from None
    lines = []
    for version in versions.values():
        budget = version.budgets[-1]
        utilities = [_mean_utility(t) for t in version.at_budget(budget)]
        known = [u for u in utilities if u is not None]
        if known:
            lines.append(
                f"{version.label} after {budget} episodes: mean utility {np.median(known):.3f} "
                f"(median of {len(known)} seed{'s' if len(known) > 1 else ''})"
            )
    return ReportFiles(written=tuple(written), headlines=tuple(lines))


# --------------------------------------------------------------------------------------------
# Reading


def _read_trials(
    state: dict[str, Any], sweep_dir: Path, warn: Warn
) -> tuple[list[Finished], list[tuple[str, dict[str, Any]]]]:
    finished, unfinished = [], []
    for trial_id, entry in state["trials"].items():
        if entry.get("status") != "done":
            unfinished.append((trial_id, entry))
            continue
        trial_dir = sweep_dir / entry["dir"]
        if not (trial_dir / "model.zip").is_file():
            warn(
                f"{trial_dir}: trial {trial_id} is done in the state but has no model.zip, left out"
            )
            unfinished.append((trial_id, {**entry, "status": "missing"}))
            continue
        evaluation = (entry.get("result") or {}).get("evaluation")
        finished.append(Finished(trial_id, entry["params"], trial_dir, evaluation))
    if not finished:
        raise InputError(f"--results: {sweep_dir}: the sweep has no finished trial yet")
    return finished, unfinished


def _versions(finished: Sequence[Finished]) -> dict[str, Version]:
    keys = sorted({k for t in finished for k in t.params} - set(_GROUPING_EXCLUDED))
    varying = [
        k for k in keys if len({json.dumps(t.params.get(k), sort_keys=True) for t in finished}) > 1
    ]
    versions: dict[str, Version] = {}
    for trial in sorted(finished, key=lambda t: t.params["episodes"]):
        p = trial.params
        others = " ".join(f"{k}={_shown(p.get(k))}" for k in varying)
        label = f"{p['algorithm']}-{p['strategy']}" + (f" {others}" if others else "")
        version = versions.setdefault(label, Version(label, p["algorithm"], p["strategy"], others))
        version.trials.append(trial)
        points = version.curves.setdefault(p["seed"], {})
        curve_file = trial.dir / LEARNING_CURVE_FILE
        if curve_file.exists():
            for curve in load_learning_curve(curve_file).curves:
                points.update(
                    {pt.episodes: (pt.mean_utility, pt.median_utility) for pt in curve.points}
                )
        if trial.evaluation:
            final = trial.evaluation["policy"]
            points[p["episodes"]] = (float(final["mean_utility"]), float(final["median_utility"]))
    # The tables of trials give the mean utility over the test scenarios: the curves too, so
    # that one trial shows one number, unless a curve file holds only medians (then every
    # curve, and the reference lines, show the median, and say so).
    statistic = "mean"
    for version in versions.values():
        if any(m is None for points in version.curves.values() for m, _ in points.values()):
            statistic = "median"
    for version in versions.values():
        version.statistic = statistic
    order = {v: i for i, v in enumerate(PAPER_VERSIONS)}
    return dict(
        sorted(
            versions.items(),
            key=lambda kv: (
                kv[1].others,
                order.get(f"{kv[1].algorithm}-{kv[1].strategy}", 99),
                kv[0],
            ),
        )
    )


def _shown(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value)


def _mean_utility(trial: Finished) -> float | None:
    return float(trial.evaluation["policy"]["mean_utility"]) if trial.evaluation else None


def _statistic(versions: dict[str, Version]) -> str:
    """What the curves show over the test scenarios: ``"mean"`` or ``"median"``."""
    return next(iter(versions.values())).statistic if versions else "mean"


def _reference(finished: Sequence[Finished], statistic: str = "mean") -> dict[str, float]:
    """min-distance's and the oracle's ``statistic`` (mean or median) utility over the test
    scenarios, as the curves show it (the median over trials; they differ only between test
    sets and worlds)."""
    values: dict[str, list[float]] = defaultdict(list)
    for trial in finished:
        for name in ("min-distance", "oracle"):
            if trial.evaluation and name in trial.evaluation:
                values[name].append(float(trial.evaluation[name][f"{statistic}_utility"]))
    return {name: float(np.median(v)) for name, v in values.items()}


# --------------------------------------------------------------------------------------------
# Figure


def _figure(versions: dict[str, Version], reference: dict[str, float]) -> bytes:
    from policies.report.figures import _new_figure, _png, line_styles

    styles = line_styles([*versions, *reference])
    figure = _new_figure(8.4, 4.6)
    ax = figure.subplots()
    all_episodes = []
    for label, version in versions.items():
        band = version.band()
        if not band:
            continue
        x = np.array([b[0] for b in band], dtype=float)
        med, q25, q75 = (np.array([b[i] for b in band]) for i in (1, 2, 3))
        seeds = max(b[4] for b in band)
        color = styles[label]["color"]
        ax.errorbar(
            x,
            med,
            yerr=[med - q25, q75 - med],
            marker="o",
            markersize=4,
            capsize=3,
            color=color,
            label=f"{label} ({seeds} seed{'s' if seeds > 1 else ''})",
        )
        if len(x) > 1:
            ax.fill_between(x, q25, q75, color=color, alpha=0.18, linewidth=0)
        all_episodes.extend(x)
    for name, value in reference.items():
        ax.axhline(value, linewidth=1.3, label=f"{name} ({value:.3f})", **styles[name])
    ax.set_xscale("log")
    ax.set_xlim(min(all_episodes) / 1.3, max(all_episodes) * 1.3)
    ticks = sorted(set(all_episodes))
    ax.set_xticks(ticks, [f"{t:g}" for t in ticks], minor=False)
    ax.set_xticks([], minor=True)
    ax.set_xlabel("training episodes (log scale)")
    ax.set_ylabel(f"{_statistic(versions)} utility over the test set (median over seeds)")
    ax.set_title("Learning rate across seeds: median and inter-quartile range")
    ax.grid(True, which="both", alpha=0.3)
    # Outside the axes: a collapsed run lies anywhere from the bottom to the top.
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, framealpha=0.9)
    return _png(figure)


# --------------------------------------------------------------------------------------------
# Best checkpoint per cell


def _best_per_cell(versions: dict[str, Version]) -> list[tuple[str, int, Finished, int]]:
    """``(version, episodes, best trial, seeds in the cell)`` for every cell with a final
    evaluation."""
    cells = []
    for label, version in versions.items():
        for budget in version.budgets:
            scored = [
                (u, t) for t in version.at_budget(budget) if (u := _mean_utility(t)) is not None
            ]
            if scored:
                best = max(scored, key=lambda ut: (ut[0], -ut[1].params["seed"]))[1]
                cells.append((label, budget, best, len(scored)))
    return cells


def _file_name(label: str, episodes: int) -> str:
    safe = "".join(c if c.isalnum() or c in "-." else "_" for c in label.replace("=", "-"))
    return f"{safe}-e{episodes}.zip"


def _export(
    cells: Sequence[tuple[str, int, Finished, int]],
    state: dict[str, Any],
    sweep_dir: Path,
    best_dir: Path,
) -> list[Path]:
    from policies.learned.checkpoints import export_checkpoint
    from sim.files import load_scenarios

    areas: dict[str, Any] = {}
    written = []
    for label, episodes, trial, _ in cells:
        test_set = trial.params["test_set"]
        if test_set not in areas:
            path = Path(state["test_sets"][test_set])
            areas[test_set] = load_scenarios(path if path.is_absolute() else sweep_dir / path)[0]
        dest = best_dir / _file_name(label, episodes)
        export_checkpoint(
            trial.dir / "model.zip",
            dest,
            areas[test_set],
            sweep={"name": state.get("name"), "trial": trial.id, "cell": label},
        )
        written.append(dest)
    return written


# --------------------------------------------------------------------------------------------
# results.md


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    from policies.report.markdown import _md_table

    return _md_table(header, rows)


def _spread(values: Sequence[float]) -> str:
    if not values:
        return "-"
    q25, q50, q75 = np.percentile(values, [25, 50, 75])
    return f"{q50:.3f} [{q25:.3f}, {q75:.3f}]" if len(values) > 1 else f"{q50:.3f}"


def _version_row(version: Version) -> list[str]:
    budget = version.budgets[-1]
    trials = [t for t in version.at_budget(budget) if t.evaluation]
    utilities = [_mean_utility(t) or 0.0 for t in trials]
    ratios = [float(t.evaluation["ratio_to_oracle"]) for t in trials if t.evaluation]
    baseline = [float(t.evaluation["min-distance"]["mean_utility"]) for t in trials if t.evaluation]
    oracle = [float(t.evaluation["oracle"]["mean_utility"]) for t in trials if t.evaluation]
    best = max(trials, key=_mean_utility).id if trials else "-"
    return [
        f"`{version.label}`",
        str(budget),
        str(len(trials)),
        _spread(utilities),
        _spread(ratios),
        f"{np.median(baseline):.3f}" if baseline else "-",
        f"{np.median(oracle):.3f}" if oracle else "-",
        f"`{best}`",
    ]


_VERSION_HEADER = (
    "version",
    "episodes",
    "seeds",
    "mean utility over the test scenarios, median [p25, p75] over seeds",
    "x oracle",
    "min-distance",
    "oracle",
    "best trial",
)


def _markdown(
    state: dict[str, Any],
    versions: dict[str, Version],
    reference: dict[str, float],
    unfinished: Sequence[tuple[str, dict[str, Any]]],
    cells: Sequence[tuple[str, int, Finished, int]],
) -> str:
    total = len(state["trials"])
    done = total - len(unfinished)
    lines = [
        f"# Sweep `{state.get('name')}`",
        "",
        f"{done} of {total} trials finished (sweep file `{state.get('spec_file')}`). Each trial "
        "is one `tupa train` run; utilities are each trial's final evaluation on its whole test "
        "set (mean over scenarios of the episode-mean utility), spread across seeds as median "
        "[25th, 75th percentile].",
        "",
    ]
    if unfinished:
        rows = []
        for trial_id, entry in unfinished:
            errors = entry.get("errors") or []
            rows.append(
                [
                    f"`{trial_id}`",
                    entry.get("status", "?"),
                    str(entry.get("attempts", 0)),
                    errors[-1] if errors else "-",
                ]
            )
        lines += [
            "## Trials not finished",
            "",
            _table(["trial", "status", "attempts", "last error"], rows),
            "",
        ]

    paper = [v for v in versions.values() if f"{v.algorithm}-{v.strategy}" in PAPER_VERSIONS]
    missing = sorted(set(PAPER_VERSIONS) - {f"{v.algorithm}-{v.strategy}" for v in paper})
    lines += [
        "## The paper's 4 versions",
        "",
        "DDQN (sequential moves) and DDPG (absolute coordinates), each trained with Spec "
        "(the test set itself) and Gen10k (unique generated scenarios), at their largest "
        "budget in the sweep.",
        "",
    ]
    if paper:
        lines += [_table(_VERSION_HEADER, [_version_row(v) for v in paper]), ""]
    if missing:
        lines += [f"Not in this sweep: {', '.join(f'`{m}`' for m in missing)}.", ""]
    others = [v for v in versions.values() if v not in paper]
    if others:
        lines += [
            "## Other versions",
            "",
            _table(_VERSION_HEADER, [_version_row(v) for v in others]),
            "",
        ]

    lines += ["## Gen500 vs Gen10k", ""]
    rows = []
    for version in versions.values():
        if version.strategy != "gen10k":
            continue
        twin_label = version.label.replace(
            f"{version.algorithm}-gen10k", f"{version.algorithm}-gen500", 1
        )
        twin = versions.get(twin_label)
        if twin is None:
            continue
        for budget in sorted(set(version.budgets) & set(twin.budgets)):
            a = [u for t in version.at_budget(budget) if (u := _mean_utility(t)) is not None]
            b = [u for t in twin.at_budget(budget) if (u := _mean_utility(t)) is not None]
            if a and b:
                rows.append(
                    [
                        f"`{version.label}` / `{twin.label}`",
                        str(budget),
                        _spread(a),
                        _spread(b),
                        f"{np.median(a) - np.median(b):+.3f}",
                    ]
                )
    if rows:
        lines += [
            "Same algorithm and budget: 10,000 unique scenarios seen once (as many as the "
            "episodes) against 500 unique scenarios cycled (the paper: Gen500 never "
            "passes the baseline).",
            "",
            _table(["versions", "episodes", "gen10k", "gen500", "gen10k - gen500"], rows),
            "",
        ]
    else:
        lines += ["No algorithm has both gen10k and gen500 trials at the same budget.", ""]

    statistic = _statistic(versions)
    same = (
        "the statistic of the tables above, so a trial's final point is the number they give"
        if statistic == "mean"
        else "not the tables' mean: a learning-curve file without means was read"
    )
    lines += [
        "## Learning curves",
        "",
        f"![learning curves]({FIGURE_FILE})",
        "",
        f"The {statistic} utility over the test scenarios after each number of training "
        f"episodes ({same}), median [p25, p75] over seeds (n: seeds with that point). A "
        "budget's point is its trials' final evaluation on the whole test set, unless a longer "
        "trial's curve has a point there (on its first curve scenarios).",
        "",
    ]
    episodes = sorted({b[0] for v in versions.values() for b in v.band()})
    header = ["episodes", *[f"`{label}`" for label in versions]]
    rows = []
    for e in episodes:
        row = [str(e)]
        for version in versions.values():
            point = next((b for b in version.band() if b[0] == e), None)
            row.append(
                "-"
                if point is None
                else f"{point[1]:.3f} [{point[2]:.3f}, {point[3]:.3f}] n={point[4]}"
            )
        rows.append(row)
    lines += [_table(header, rows), ""]
    if reference:
        shown = ", ".join(f"{k} {v:.3f}" for k, v in reference.items())
        lines += [f"Reference, {statistic} utility over the test scenarios: {shown}.", ""]

    lines += [
        "## Best checkpoint per cell",
        "",
        f"Exported with `export_checkpoint` into `{BEST_DIR}/`: the seed with the highest "
        "final mean utility in each cell.",
        "",
    ]
    rows = [
        [
            f"`{label}`",
            str(e),
            str(n),
            f"`{trial.id}`",
            f"{_mean_utility(trial):.3f}",
            f"`{BEST_DIR}/{_file_name(label, e)}`",
        ]
        for label, e, trial, n in cells
    ]
    lines += [
        _table(["version", "episodes", "seeds", "best trial", "mean utility", "file"], rows),
        "",
    ]
    return "\n".join(lines)
