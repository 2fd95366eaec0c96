"""Fleet evaluation (policies/evaluation/fleet_evaluation.py), ``tupa eval --uavs K`` and ``tupa
report``'s fleet figures (policies/report/fleet.py): a tiny trained checkpoint and the three fleet
baselines end to end on a small scenario file, the document's rows against
:func:`evaluate_fleet` called directly, and the refusals (exit 2, one line, nothing written)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from policies.evaluation.fleet_evaluation import (
    FLEET_EVAL_FORMAT,
    FLEET_METRICS,
    add_ratio_to_oracle,
    build_fleet_candidate,
    evaluate_fleet,
)
from policies.fleet_policy import FleetCheckpointServing
from policies.interface import ReportedUsers
from policies.learned.fleet_checkpoint import FleetCheckpointPolicy
from policies.placements.fleet_baselines import KMeansPlacement
from policies.report import build_report
from policies.training.fleet_training import FleetTrainConfig, train_fleet
from service.cli import main
from sim.atomic import atomic_write_json
from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import load_scenarios, save_scenarios
from sim.fleet import FleetConfig
from sim.fleet_env import FleetParallelEnv
from sim.geometry import assign_targets
from sim.scenarios import generate_scenarios
from sim.world import get_world
from tests.helpers import tiny_preset
from tests.tiers import needs

AREA = AreaConfig()
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
STEPS = 4
WORLD = replace(get_world("closed-loop"), episode_steps=STEPS)
NAMES = ("kmeans-min-distance", "kmeans-load-weighted", "fleet-oracle")
SINGLE_UAV_CHECKPOINT = Path(__file__).parents[2] / "policies" / "checkpoints" / "ddqn-dr.zip"


@pytest.fixture(scope="module")
@needs("training")
def checkpoint(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fleet-eval") / "run"
    config = FleetTrainConfig(
        n_uavs=2, episodes=3, out_dir=out, preset=tiny_preset(), seed=2, users=(8, 10),
        command="test", progress=False,
    )  # fmt: skip
    train_fleet(config)
    return out


@pytest.fixture(scope="module")
def scenario_file(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("fleet-scenarios") / "scenarios.json"
    scenarios = [
        *generate_scenarios(2, 10, seed=3, family="hotspots", total_load_bps=80e6),
        *generate_scenarios(1, 10, seed=4, family="uniform", total_load_bps=80e6),
    ]
    save_scenarios(path, AREA, scenarios)
    return path


@pytest.fixture(scope="module")
def evaluated(checkpoint, scenario_file, tmp_path_factory) -> tuple[Path, dict]:
    """``tupa eval --uavs 2`` with the checkpoint and the three baselines, once."""
    out = tmp_path_factory.mktemp("fleet-results") / "fleet.json"
    argv = ["eval", "--uavs", "2", "--scenarios", str(scenario_file), "--json", str(out)]
    for name in (str(checkpoint), *NAMES):
        argv += ["--policy", name]
    assert main([*argv, "--episode-steps", str(STEPS), "--seed", "3", "--no-progress"]) == 0
    return out, json.loads(out.read_text())


def test_the_cli_writes_one_document_per_policy(evaluated, checkpoint, scenario_file):
    _, document = evaluated
    assert document["format"] == FLEET_EVAL_FORMAT
    results = document["results"]
    assert [r["policy"] for r in results] == ["ddpg-fleet-shared", *NAMES]
    _, scenarios = load_scenarios(scenario_file)
    for result in results:
        assert result["format"] == FLEET_EVAL_FORMAT
        assert result["uavs"] == 2 and result["seed"] == 3
        assert result["world"] == "closed-loop" and result["episode_steps"] == STEPS
        assert [row["id"] for row in result["scenarios"]] == [s.id for s in scenarios]
        for row in result["scenarios"]:
            assert 0.0 <= row["utility"] <= 1.0
            assert 0.0 <= row["served_fraction"] <= 1.0
            assert 0.0 < row["jain_fairness"] <= 1.0
            assert 0.0 <= row["min_throughput_bps"] < 1e9
            assert isinstance(row["handovers"], int) and row["handovers"] >= 0
            assert 0.0 <= row["heterogeneity"] <= 1.0
        for metric in FLEET_METRICS:
            values = [row[metric] for row in result["scenarios"]]
            assert result[f"mean_{metric}"] == pytest.approx(np.mean(values))
    oracle = results[-1]
    assert all(row["ratio_to_oracle"] == 1.0 for row in oracle["scenarios"])
    for result in results:
        for row, best in zip(result["scenarios"], oracle["scenarios"], strict=True):
            assert row["ratio_to_oracle"] == pytest.approx(row["utility"] / best["utility"])


def test_the_rows_are_what_evaluate_fleet_gives(evaluated, checkpoint, scenario_file):
    """The CLI adds nothing of its own: each document is evaluate_fleet's, called directly
    with the policy built from the same name (and deterministic: a second call agrees)."""
    _, document = evaluated
    _, scenarios = load_scenarios(scenario_file)
    fleet = FleetConfig(n_uavs=2)
    for spec, written in zip((str(checkpoint), *NAMES), document["results"], strict=True):
        name, candidate = build_fleet_candidate(spec, 2, WORLD, fleet, seed=3)
        direct = evaluate_fleet(
            candidate, scenarios, 2, WORLD, fleet, STEPS, seed=3, name=name, progress=False
        )
        rows = [
            {k: v for k, v in row.items() if k != "ratio_to_oracle"} for row in written["scenarios"]
        ]
        assert rows == direct["scenarios"]
        assert {k: written[k] for k in direct if k != "scenarios"} == {
            k: v for k, v in direct.items() if k != "scenarios"
        }


def test_the_report_draws_the_fleet_figures(evaluated, tmp_path, capsys):
    out, document = evaluated
    report_dir = tmp_path / "report"
    assert main(["report", "--results", str(out.parent), "--out", str(report_dir)]) == 0
    for name in ("fleet_metrics.png", "fleet_utility_by_heterogeneity.png"):
        data = (report_dir / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000
    markdown = (report_dir / "results.md").read_text()
    for result in document["results"]:
        assert f"`{result['policy']}`" in markdown
        # The mean utility, recomputed from the rows, is in the summary table.
        assert f"| {result['mean_utility']:.3f} |" in markdown
    for header in ("mean utility", "served fraction", "Jain fairness", "min throughput",
                   "handovers / episode", "utility / `fleet-oracle`"):  # fmt: skip
        assert header in markdown
    # The per-bin table counts every scenario once.
    bin_rows = [line for line in markdown.splitlines() if line.startswith("| [")]
    assert sum(int(line.split("|")[2]) for line in bin_rows) == 3
    printed = capsys.readouterr().out
    assert "of fleet-oracle's utility" in printed


def test_without_the_oracle_there_is_no_ratio(scenario_file, tmp_path):
    out = tmp_path / "one.json"
    argv = ["eval", "--uavs", "3", "--policy", "kmeans-load-weighted", "--scenarios",
            str(scenario_file), "--json", str(out), "--episode-steps", "3"]  # fmt: skip
    assert main(argv) == 0
    document = json.loads(out.read_text())
    assert document["policy"] == "kmeans-load-weighted" and document["uavs"] == 3
    assert "ratio_to_oracle" not in document
    assert all("ratio_to_oracle" not in row for row in document["scenarios"])
    assert not add_ratio_to_oracle([document])
    report = build_report(tmp_path, tmp_path / "report", warn=lambda message: None)
    assert (tmp_path / "report" / "results.md") in report.written
    assert "was not evaluated" in (tmp_path / "report" / "results.md").read_text()


def test_handovers_count_the_episodes_handovers():
    """A placement re-placed every step hands users over; the row's count is the episode's
    total, the last step's running count, and does not leak into the next scenario."""
    scenarios = generate_scenarios(2, 12, seed=11, family="mixture", total_load_bps=80e6)
    world = replace(get_world("closed-loop-moving"), episode_steps=6)
    placement = KMeansPlacement(3, AREA, True)
    result = evaluate_fleet(placement, scenarios, 3, world, progress=False)
    env = FleetParallelEnv(action_kind="continuous", world=world, fleet=FleetConfig(3))
    for i, (scenario, row) in enumerate(zip(scenarios, result["scenarios"], strict=True)):
        env.reset(seed=i, options={"scenario": scenario})
        counts = []
        while env.agents:
            # Assigned to the vehicles by least travel, as the evaluation (and the service) do.
            placed = placement.place(ReportedUsers.of(env.reports))
            *_, infos = env.step_to(assign_targets(env.uav_xyz_m, placed))
            counts.append(infos["uav_0"]["handovers"])
        assert row["handovers"] == counts[-1]
        assert counts == sorted(counts)  # a running count


def test_evaluate_fleet_refuses_bad_input():
    scenarios = generate_scenarios(1, 5, seed=1)
    placement = KMeansPlacement(2, AREA)
    with pytest.raises(InputError, match="seed"):
        evaluate_fleet(placement, scenarios, 2, WORLD, seed=-1, progress=False)
    with pytest.raises(InputError, match="n_uavs"):
        evaluate_fleet(placement, scenarios, 2, WORLD, FleetConfig(n_uavs=3), progress=False)
    with pytest.raises(InputError, match="policy"):
        build_fleet_candidate("min-distance", 2, WORLD)
    with pytest.raises(InputError, match="policy"):
        build_fleet_candidate("no/such/checkpoint", 2, WORLD)


@pytest.mark.parametrize(
    ("extra", "option"),
    [
        (["--uavs", "2", "--policy", "oracle"], "--policy"),
        (["--uavs", "2", "--policy", "no/such/dir"], "--policy"),
        (["--uavs", "2", "--policy", str(SINGLE_UAV_CHECKPOINT)], "--policy"),
        (["--uavs", "1", "--policy", "kmeans-min-distance"], "--uavs"),
        (["--uavs", "9", "--policy", "kmeans-min-distance"], "--uavs"),
        (["--uavs", "2", "--policy", "fleet-oracle", "--backend", "local"], "--backend"),
        (["--uavs", "2", "--policy", "fleet-oracle", "--altitude-profiles", "1"],
         "--altitude-profiles"),
        (["--uavs", "2", "--policy", "fleet-oracle", "--replan-every", "0"], "--replan-every"),
        (["--policy", "min-distance", "--replan-every", "2"], "--replan-every"),
        (["--uavs", "2", "--policy", "fleet-oracle", "--world", "moon"], "world"),
    ],
)  # fmt: skip
def test_the_cli_refuses_bad_fleet_input(scenario_file, tmp_path, capsys, extra, option):
    out = tmp_path / "out.json"
    argv = ["eval", "--scenarios", str(scenario_file), "--json", str(out), "--no-progress"]
    assert main([*argv, *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert option in err and "\n" not in err
    assert not out.exists()


def _fleet_document(policy: str, uavs: int = 2, utility: object = 0.5, h: float = 0.3) -> dict:
    row = {"id": "s0", "heterogeneity": h, "utility": utility, "served_fraction": 1.0,
           "jain_fairness": 0.9, "min_throughput_bps": 1e6, "handovers": 0}  # fmt: skip
    return {"format": FLEET_EVAL_FORMAT, "policy": policy, "uavs": uavs, "scenarios": [row]}


@pytest.mark.parametrize(
    ("files", "message"),
    [
        (
            {"a.json": _fleet_document("kmeans-min-distance"),
             "b.json": {"policy": "min-distance", "scenarios": []}},
            "single-UAV",
        ),
        (
            {"a.json": _fleet_document("kmeans-min-distance"),
             "b.json": _fleet_document("fleet-oracle", uavs=3)},
            "uavs",
        ),
        ({"a.json": _fleet_document("kmeans-min-distance", utility="x")}, "scenarios[0].utility"),
        (
            {"a.json": _fleet_document("kmeans-min-distance"),
             "b.json": _fleet_document("fleet-oracle", h=0.7)},
            "not scenarios",
        ),
        (
            {"a.json": _fleet_document("fleet-oracle"), "b.json": _fleet_document("fleet-oracle")},
            "appears in both",
        ),
    ],
)  # fmt: skip
def test_the_report_refuses_bad_fleet_input_and_writes_nothing(tmp_path, capsys, files, message):
    results = tmp_path / "results"
    results.mkdir()
    for name, document in files.items():
        atomic_write_json(results / name, document)
    out = tmp_path / "report"
    assert main(["report", "--results", str(results), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not out.exists()


def test_a_checkpoint_flies_another_fleet_size(checkpoint, scenario_file):
    """A checkpoint trained with 2 UAVs is evaluated with 3 (parameters shared)."""
    name, policy = build_fleet_candidate(str(checkpoint / "model.zip"), 3, WORLD)
    assert isinstance(policy, FleetCheckpointServing) and name == "ddpg-fleet-shared"
    assert isinstance(policy.policy, FleetCheckpointPolicy)
    _, scenarios = load_scenarios(scenario_file)
    result = evaluate_fleet(policy, scenarios[:1], 3, WORLD, progress=False)
    assert result["uavs"] == 3 and result["n_scenarios"] == 1
