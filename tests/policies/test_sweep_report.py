"""``tupa report`` on a sweep: the learning-curve table and the versions table agree.

Synthetic trials (no training): each trial's final evaluation and learning-curve file written
by hand, with a mean utility over the test scenarios that differs from the median, as it does
on a small test set (issue 42: 0.882 in the curve table, 0.824 in the versions table, for the
same trials).
"""

from __future__ import annotations

import re
from pathlib import Path

from policies.report.curves import LEARNING_CURVE_FILE, write_learning_curve
from policies.report.sweep import Finished, _markdown, _reference, _versions


def _evaluation(mean: float, median: float) -> dict:
    return {
        "policy": {"mean_utility": mean, "median_utility": median, "p25_utility": median},
        "min-distance": {"mean_utility": 0.70, "median_utility": 0.75, "p25_utility": 0.6},
        "oracle": {"mean_utility": 0.90, "median_utility": 0.95, "p25_utility": 0.8},
        "ratio_to_oracle": mean / 0.90,
    }


def _trial(tmp_path: Path, seed: int, episodes: int, mean: float, median: float) -> Finished:
    trial_dir = tmp_path / f"ddqn-spec-e{episodes}-s{seed}"
    trial_dir.mkdir()
    write_learning_curve(
        trial_dir / LEARNING_CURVE_FILE,
        [
            {
                "label": "ddqn-spec",
                "points": [{"episodes": episodes, "median_utility": median, "mean_utility": mean}],
            }
        ],
        {"min-distance": 0.75, "oracle": 0.95},
    )
    params = {"algorithm": "ddqn", "strategy": "spec", "episodes": episodes, "seed": seed,
              "test_set": "t"}  # fmt: skip
    return Finished(trial_dir.name, params, trial_dir, _evaluation(mean, median))


def _section(text: str, title: str) -> str:
    return text.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]


def test_the_curve_table_and_the_versions_table_show_the_same_number_for_the_same_trials(
    tmp_path: Path,
) -> None:
    finished = [
        _trial(tmp_path, seed=1, episodes=8, mean=0.824, median=0.882),
        _trial(tmp_path, seed=2, episodes=8, mean=0.810, median=0.870),
        _trial(tmp_path, seed=3, episodes=8, mean=0.830, median=0.890),
    ]
    versions = _versions(finished)
    text = _markdown({"name": "s", "trials": {t.id: {} for t in finished}}, versions,
                     _reference(finished), [], [])  # fmt: skip

    paper = _section(text, "The paper's 4 versions")
    row = next(line for line in paper.splitlines() if line.startswith("| `ddqn-spec`"))
    versions_value = row.split("|")[4].strip().split()[0]
    curves = _section(text, "Learning curves")
    row = next(line for line in curves.splitlines() if line.startswith("| 8 "))
    curve_value = row.split("|")[2].strip().split()[0]
    assert versions_value == curve_value == "0.824", (versions_value, curve_value)
    # Both say what they show: the mean over the test scenarios, the median over seeds.
    assert "mean utility over the test scenarios" in paper
    assert "mean utility over the test scenarios" in curves
    # The reference lines are the same statistic (min-distance's mean, not its median).
    assert re.search(r"min-distance 0\.700\b", curves), curves


def test_curves_without_a_mean_fall_back_to_the_median_and_say_so(tmp_path: Path) -> None:
    trial = _trial(tmp_path, seed=1, episodes=8, mean=0.824, median=0.882)
    write_learning_curve(  # an older curve file: medians only
        trial.dir / LEARNING_CURVE_FILE,
        [{"label": "ddqn-spec", "points": [{"episodes": 4, "median_utility": 0.5}]}],
    )
    versions = _versions([trial])
    text = _markdown({"name": "s", "trials": {trial.id: {}}}, versions, {}, [],
                     [])  # fmt: skip
    curves = _section(text, "Learning curves")
    assert "median utility over the test scenarios" in curves
    assert "| 8 | 0.882" in curves
