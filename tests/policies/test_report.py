"""``tupa report``: figures and results.md from real (small) eval outputs; bad input writes
nothing; the learning-curve format round-trips."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from policies.evaluation.evaluation import evaluate_policy
from policies.registry import make_placement
from policies.report import ReportFiles, build_report
from policies.report.curves import (
    LEARNING_CURVE_FORMAT,
    CurvePoint,
    LearningCurve,
    load_learning_curve,
    write_learning_curve,
)
from policies.report.inputs import load_eval_results
from service.cli import main
from sim.atomic import atomic_write_json
from sim.config import AreaConfig, NetworkConfig
from sim.errors import InputError
from sim.scenarios import generate_scenarios
from sim.world import PAPER

AREA = AreaConfig()
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
CDF_FIGURES = (
    "utility_cdf.png",
    "throughput_cdf.png",
    "delay_cdf.png",
    "plr_cdf.png",
    "metrics_cdf.png",
    "utility_by_heterogeneity.png",
)
CURVE = {
    "format": LEARNING_CURVE_FORMAT,
    "curves": [
        {
            "label": "ddqn-test",
            "points": [
                {"episodes": 1000, "median_utility": 0.93, "mean_utility": 0.9},
                {"episodes": 100, "median_utility": 0.81, "mean_utility": 0.8},
            ],
        },
        {"label": "ddpg-test", "points": [{"episodes": 100, "median_utility": 0.7}]},
    ],
    "reference": {"min-distance": 0.85, "oracle": 0.99},
}


def _evaluate(name: str, scenarios: list) -> dict:
    world = replace(PAPER, area=AREA, network=NetworkConfig(), episode_steps=5)
    return evaluate_policy(make_placement(name, world), scenarios, world, seed=1, progress=False)


@pytest.fixture(scope="module")
def evaluations() -> dict[str, dict]:
    """Real eval results of the three baselines on 10 scenarios, episodes of 5 steps, plus a
    stand-in for a trained policy (the load-weighted results renamed, utilities changed)."""
    scenarios = generate_scenarios(10, 3, seed=5, area=AREA)
    results = {name: _evaluate(name, scenarios) for name in ("min-distance", "load-weighted")}
    results["oracle"] = _evaluate("oracle", scenarios)
    trained = json.loads(json.dumps(results["load-weighted"]))
    trained["policy"] = "ddqn-test"
    for i, row in enumerate(trained["scenarios"]):
        row["utility"] = 0.5 + 0.04 * i
    results["ddqn-test"] = trained
    return results


def _write_results_dir(directory: Path, evaluations: dict[str, dict]) -> Path:
    """A results directory as the pipeline leaves it: baselines in one file (the several-policy
    shape), the oracle and the trained policy alone, a learning curve, an unrelated JSON."""
    atomic_write_json(
        directory / "baselines.json",
        {"results": [evaluations["min-distance"], evaluations["load-weighted"]]},
    )
    atomic_write_json(directory / "oracle.json", evaluations["oracle"])
    atomic_write_json(directory / "ddqn-test.json", evaluations["ddqn-test"])
    atomic_write_json(directory / "learning_curve.json", CURVE)
    atomic_write_json(directory / "ddqn-test.meta.json", {"algorithm": "ddqn"})
    return directory


@pytest.fixture
def results_dir(tmp_path: Path, evaluations: dict[str, dict]) -> Path:
    """A fresh results directory, for tests that break it."""
    return _write_results_dir(tmp_path / "results", evaluations)


@pytest.fixture(scope="module")
def built(tmp_path_factory, evaluations: dict[str, dict]) -> tuple[Path, ReportFiles, list[str]]:
    """The report of the intact results directory, built once: (out dir, report, warnings)."""
    base = tmp_path_factory.mktemp("built")
    results = _write_results_dir(base / "results", evaluations)
    out = base / "deep" / "report"
    warnings: list[str] = []
    return out, build_report(results, out, warn=warnings.append), warnings


def _utility(evaluation: dict) -> np.ndarray:
    return np.array([row["utility"] for row in evaluation["scenarios"]])


def _assert_png(path: Path) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, path
    assert len(data) > 10_000, (path, len(data))


# --------------------------------------------------------------------------------------------
# The whole report


def test_report_writes_every_figure_and_the_tables(built, evaluations: dict[str, dict]) -> None:
    out, report, warnings = built

    for name in (*CDF_FIGURES, "learning_curve.png"):
        _assert_png(out / name)
    assert {p.name for p in report.written} == {*CDF_FIGURES, "learning_curve.png", "results.md"}
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left
    assert any("ddqn-test.meta.json: not a tupa eval result" in w for w in warnings)
    # the synthetic curve's references are not these baselines' medians: said, not fatal
    assert any("reference min-distance 0.850 differs" in w for w in warnings)

    markdown = (out / "results.md").read_text()
    reference = _utility(evaluations["min-distance"])
    for name, evaluation in evaluations.items():
        utility = _utility(evaluation)
        row = (
            f"| `{name}` | 10 | {utility.mean():.3f} | {np.median(utility):.3f} | "
            f"{np.percentile(utility, 25):.3f} |"
        )
        assert row in markdown, row
        throughput = np.mean([s["throughput_bps"] for s in evaluation["scenarios"]]) / 1e6
        delay = np.mean([s["delay_s"] for s in evaluation["scenarios"]]) * 1e3
        assert f"| {throughput:.2f} | {delay:.1f} |" in markdown
    gain = np.percentile(_utility(evaluations["ddqn-test"]), 25) / np.percentile(reference, 25)
    headline = next(line for line in report.headlines if line.startswith("ddqn-test vs"))
    assert f"= {gain:.2f}x (paper: ~1.75x)" in headline
    assert headline in markdown
    for figure in (*CDF_FIGURES, "learning_curve.png"):
        assert f"({figure})" in markdown


def test_bins_table_matches_an_independent_binning(built, evaluations: dict[str, dict]) -> None:
    markdown = (built[0] / "results.md").read_text()
    rows = evaluations["min-distance"]["scenarios"]
    bins = np.array([math.floor(round(row["heterogeneity"] * 20, 9)) for row in rows])
    top = bins.max()
    mask = bins == top
    trained = _utility(evaluations["ddqn-test"])[mask].mean()
    baseline = _utility(evaluations["min-distance"])[mask].mean()
    label = f"[{top * 0.05:.2f}, {(top + 1) * 0.05:.2f})"
    assert f"| {label} | {int(mask.sum())} | {trained:.3f} | {baseline:.3f} |" in markdown
    assert f"(n={int(mask.sum())}): {trained:.3f} vs {baseline:.3f}" in markdown


def test_learning_curve_table(built) -> None:
    markdown = (built[0] / "results.md").read_text()
    assert "| episodes | `ddqn-test` | `ddpg-test` |" in markdown
    assert "| 100 | 0.810 | 0.700 |" in markdown  # points sorted by episodes
    assert "| 1000 | 0.930 | – |" in markdown
    assert "`ddqn-test` first beats `min-distance` (0.850) after 1000 episodes" in markdown
    assert "`ddpg-test` never beats `min-distance` (0.850) up to 100 episodes" in markdown


def test_without_learning_curve_or_min_distance(
    tmp_path: Path, evaluations: dict[str, dict]
) -> None:
    results = tmp_path / "results"
    atomic_write_json(results / "oracle.json", evaluations["oracle"])
    out = tmp_path / "out"
    report = build_report(results, out)
    assert not (out / "learning_curve.png").exists()
    assert report.headlines == ()
    markdown = (out / "results.md").read_text()
    assert "Learning curve" not in markdown
    assert "`min-distance` is not among the results" in markdown


def test_scenario_order_does_not_matter(tmp_path: Path, evaluations: dict[str, dict]) -> None:
    results = tmp_path / "results"
    shuffled = json.loads(json.dumps(evaluations["oracle"]))
    shuffled["scenarios"].reverse()
    atomic_write_json(results / "a.json", evaluations["min-distance"])
    atomic_write_json(results / "b.json", shuffled)
    loaded = load_eval_results(results)
    assert [r.policy for r in loaded] == ["min-distance", "oracle"]
    assert loaded[1].ids == loaded[0].ids
    by_id = {row["id"]: row["utility"] for row in evaluations["oracle"]["scenarios"]}
    assert loaded[1].utility.tolist() == [by_id[i] for i in loaded[1].ids]


# --------------------------------------------------------------------------------------------
# Bad input: InputError, nothing written


def _break_mismatched(directory: Path) -> None:
    document = json.loads((directory / "oracle.json").read_text())
    document["scenarios"] = document["scenarios"][:-1]
    document["n_scenarios"] -= 1
    atomic_write_json(directory / "oracle.json", document)


def _break_other_scenarios(directory: Path) -> None:
    document = json.loads((directory / "oracle.json").read_text())
    document["scenarios"][3]["heterogeneity"] += 0.1
    atomic_write_json(directory / "oracle.json", document)


def _break_duplicate(directory: Path) -> None:
    shutil.copy(directory / "oracle.json", directory / "oracle-again.json")


def _break_field(directory: Path) -> None:
    document = json.loads((directory / "oracle.json").read_text())
    document["scenarios"][2]["utility"] = None
    atomic_write_json(directory / "oracle.json", document)


def _break_curve(directory: Path) -> None:
    curve = json.loads(json.dumps(CURVE))
    curve["curves"][0]["points"][1]["episodes"] = 1000
    atomic_write_json(directory / "learning_curve.json", curve)


@pytest.mark.parametrize(
    ("breaker", "message"),
    [
        (lambda d: (d / "oracle.json").write_text("{not json"), "oracle.json: not valid JSON"),
        (_break_mismatched, "different scenario sets"),
        (_break_other_scenarios, "share scenario ids but not scenarios"),
        (_break_duplicate, "'oracle' appears in both"),
        (_break_field, "oracle.json: oracle: scenarios[2].utility: must be a finite number"),
        (_break_curve, "learning_curve.json: curves[0] (ddqn-test): points: episodes repeated"),
    ],
)
def test_bad_input_is_an_input_error_and_writes_nothing(
    results_dir: Path, tmp_path: Path, breaker, message: str
) -> None:
    breaker(results_dir)
    out = tmp_path / "out"
    with pytest.raises(InputError) as error:
        build_report(results_dir, out, warn=lambda _: None)
    assert message in str(error.value)
    assert "\n" not in str(error.value)
    assert not out.exists()


def test_mismatched_sets_name_both_policies(results_dir: Path, tmp_path: Path) -> None:
    _break_mismatched(results_dir)
    with pytest.raises(InputError) as error:
        build_report(results_dir, tmp_path / "out", warn=lambda _: None)
    text = str(error.value)
    assert "'min-distance'" in text and "'oracle'" in text and "different scenario sets" in text


def test_empty_directory(tmp_path: Path) -> None:
    (tmp_path / "results").mkdir()
    with pytest.raises(InputError, match="no tupa eval results"):
        build_report(tmp_path / "results", tmp_path / "out")
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# The CLI


def test_cli_report(results_dir: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "cli-out"
    assert main(["report", "--results", str(results_dir), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "wrote 8 files" in captured.out and "ddqn-test vs min-distance" in captured.out
    assert "warning" in captured.err and "ddqn-test.meta.json" in captured.err
    assert (out / "results.md").exists()


@pytest.mark.parametrize("content", [None, "[1, 2"])
def test_cli_bad_input_exits_2(tmp_path: Path, capsys, content: str | None) -> None:
    results = tmp_path / "results"
    results.mkdir()
    if content is not None:
        (results / "eval.json").write_text(content)
    out = tmp_path / "out"
    assert main(["report", "--results", str(results), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tupa report: error:") and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_cli_out_is_a_file(results_dir: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "file"
    out.write_text("x")
    assert main(["report", "--results", str(results_dir), "--out", str(out)]) == 2
    assert "not a directory" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# The learning-curve format


def test_learning_curve_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "lc" / "learning_curve.json"
    write_learning_curve(
        path,
        [LearningCurve("ddqn", (CurvePoint(500, 0.9, 0.88), CurvePoint(100, 0.7)))],
        {"min-distance": 0.8},
    )
    document = json.loads(path.read_text())
    assert document["format"] == LEARNING_CURVE_FORMAT
    assert document["curves"][0]["points"][1] == {"episodes": 100, "median_utility": 0.7}
    loaded = load_learning_curve(path)
    assert [p.episodes for p in loaded.curves[0].points] == [100, 500]
    assert loaded.curves[0].points[1].mean_utility == 0.88
    assert loaded.reference == {"min-distance": 0.8}


@pytest.mark.parametrize(
    ("curves", "message"),
    [
        ([], "curves: must be a non-empty list"),
        ([{"label": "a", "points": []}], "points: must be a non-empty list"),
        ([{"label": "a", "points": [{"episodes": 0, "median_utility": 1}]}], "integer >= 1"),
        ([{"label": "a", "points": [{"episodes": 5}]}], "median_utility: missing"),
        (
            [{"label": "a", "points": [{"episodes": 5, "median_utility": float("nan")}]}],
            "finite number",
        ),
        (
            [
                {"label": "a", "points": [{"episodes": 5, "median_utility": 1}]},
                {"label": "a", "points": [{"episodes": 6, "median_utility": 1}]},
            ],
            "labels repeated: a",
        ),
    ],
)
def test_write_learning_curve_rejects_bad_curves(
    tmp_path: Path, curves: list, message: str
) -> None:
    path = tmp_path / "learning_curve.json"
    with pytest.raises(InputError, match=message):
        write_learning_curve(path, curves)
    assert not path.exists()


@pytest.mark.process
def test_importing_the_module_does_not_load_matplotlib() -> None:
    code = "import sys, policies.report; assert 'matplotlib' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_the_report_shows_where_each_policy_flies_and_in_which_environment(
    tmp_path: Path,
) -> None:
    town = AreaConfig(environment="urban")
    world = replace(PAPER, area=town, episode_steps=5)
    scenarios = generate_scenarios(6, 3, seed=8, area=town)
    directory = tmp_path / "results"
    for name in ("min-distance", "min-distance-env"):
        result = evaluate_policy(make_placement(name, world), scenarios, world, progress=False)
        assert result["environment"] == "urban"
        atomic_write_json(directory / f"{name}.json", result)
    build_report(directory, tmp_path / "report", warn=lambda _: None)
    text = (tmp_path / "report" / "results.md").read_text()
    section = text.split("## Altitude", 1)[1].split("\n## ", 1)[0]
    assert "`urban` environment" in section
    rows = {line.split("|")[1].strip(): line for line in section.splitlines() if "`min" in line}
    assert rows["`min-distance`"].split("|")[2].strip() == "25.0"  # flies lowest
    assert float(rows["`min-distance-env`"].split("|")[2]) > 25.0  # climbs for line of sight
    assert "| urban |" in text.split("## Evaluation settings", 1)[1]


def test_an_eval_file_without_positions_has_no_altitude_table_and_a_bad_one_is_named(
    results_dir: Path, tmp_path: Path
) -> None:
    for path in results_dir.glob("*.json"):
        document = json.loads(path.read_text())
        for result in document.get("results", [document]):
            for row in result.get("scenarios", []):
                row.pop("uav_xyz_m", None)
        atomic_write_json(path, document)
    build_report(results_dir, tmp_path / "plain", warn=lambda _: None)
    assert "## Altitude" not in (tmp_path / "plain" / "results.md").read_text()
    oracle = json.loads((results_dir / "oracle.json").read_text())
    oracle["scenarios"][0]["uav_xyz_m"] = [1.0, 2.0]
    atomic_write_json(results_dir / "oracle.json", oracle)
    with pytest.raises(InputError, match=r"scenarios\[0\]\.uav_xyz_m: must be \[x, y, z\]"):
        build_report(results_dir, tmp_path / "bad", warn=lambda _: None)
