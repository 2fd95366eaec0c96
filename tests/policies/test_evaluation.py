"""evaluate_policy: result shape, determinism, the acting-policy seam, and the tables."""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pytest

from policies.evaluation.evaluation import (
    evaluate_policy,
    format_results,
    heterogeneity_bin,
)
from policies.interface import Policy
from policies.registry import make_placement
from sim.config import AreaConfig
from sim.errors import InputError
from sim.observation import UserReports
from sim.scenarios import Scenario, generate_scenarios
from sim.utility import heterogeneity_index
from sim.world import PAPER, World

AREA = AreaConfig()
STEPS = 20
CENTRE_M = np.array([262.5, 262.5, 25.0])  # the environments' default start


@pytest.fixture(scope="module")
def scenarios() -> list[Scenario]:
    return generate_scenarios(6, 3, seed=4, area=AREA)


WORLD = replace(PAPER, episode_steps=STEPS)


def run(policy: Any, scenarios: list[Scenario], **kwargs: Any) -> dict[str, Any]:
    kwargs = {"progress": False, **kwargs}
    return evaluate_policy(policy, scenarios, kwargs.pop("world", WORLD), **kwargs)


def test_result_shape(scenarios: list[Scenario]) -> None:
    result = run(make_placement("min-distance"), scenarios)
    assert list(result) == [
        "policy",
        "world",
        "environment",
        "n_scenarios",
        "mean_utility",
        "median_utility",
        "p25_utility",
        "mean_time_to_final_s",
        "seed",
        "queueing",
        "episode_steps",
        "mode",
        "scenarios",
    ]
    assert result["policy"] == "min-distance"
    assert result["n_scenarios"] == len(scenarios)
    rows = result["scenarios"]
    assert [r["id"] for r in rows] == [s.id for s in scenarios]
    for row, scenario in zip(rows, scenarios, strict=True):
        assert list(row) == [
            "id",
            "utility",
            "heterogeneity",
            "throughput_bps",
            "delay_s",
            "plr",
            "time_to_final_s",
            "uav_xyz_m",
            "trace",
        ]
        assert all(type(row[k]) is float for k in list(row)[1:-2])
        assert len(row["trace"]) == STEPS
        assert 0 < row["time_to_final_s"] <= STEPS * WORLD.step_s
        np.testing.assert_allclose(row["uav_xyz_m"], make_placement("min-distance").place(scenario))
        assert 0.0 <= row["utility"] <= 1.0
        assert 0.0 <= row["plr"] <= 1.0
        assert row["delay_s"] >= 0.0
        assert 0.0 <= row["throughput_bps"] <= scenario.load_bps.sum() * 1.5
        assert row["heterogeneity"] == heterogeneity_index(
            scenario.users_xy_m, scenario.load_bps, AREA
        )
    values = np.array([r["utility"] for r in rows])
    assert result["mean_utility"] == pytest.approx(values.mean())
    assert result["median_utility"] == pytest.approx(np.median(values))
    assert result["p25_utility"] == pytest.approx(np.percentile(values, 25))
    json.dumps(result, allow_nan=False)  # plain JSON


def test_same_seed_same_json_other_seed_differs(scenarios: list[Scenario]) -> None:
    policy = make_placement("load-weighted")
    first = json.dumps(run(policy, scenarios, seed=3))
    assert json.dumps(run(policy, scenarios, seed=3)) == first
    assert json.dumps(run(policy, scenarios, seed=4)) != first


@dataclass
class FixedPlacement:
    name: str
    position_m: np.ndarray

    def place(self, scenario: Any) -> np.ndarray:
        return self.position_m


@dataclass
class HoverAtStart:
    """A policy deciding targets itself (the seam a checkpoint plugs into): default start,
    then hold where it is."""

    name: str = "hover"
    spec: str = "hover"
    kind: str = "coordinates"

    def begin_episode(self, users: Any, world: World) -> None:
        return None

    def decide(self, reports: UserReports, vehicle_xyz_m: np.ndarray) -> np.ndarray:
        assert len(reports.x_m) == 3
        return vehicle_xyz_m.copy()

    def describe(self) -> dict[str, Any]:
        return {"name": self.name}


def test_a_deciding_policy_runs_in_the_same_loop(scenarios: list[Scenario]) -> None:
    agent = HoverAtStart()
    assert isinstance(agent, Policy)
    acted = run(agent, scenarios, seed=9)
    static = run(FixedPlacement("hover", CENTRE_M), scenarios, seed=9)
    assert acted == static


def test_every_policy_sees_the_same_random_numbers(scenarios: list[Scenario]) -> None:
    # Two policies that pick the same position get the same episode, whatever their names.
    a = run(FixedPlacement("a", np.array([100.0, 200.0, 50.0])), scenarios, seed=1)
    b = run(FixedPlacement("b", np.array([100.0, 200.0, 50.0])), scenarios, seed=1)
    assert a["scenarios"] == b["scenarios"]


def test_bad_arguments(scenarios: list[Scenario]) -> None:
    policy = make_placement("min-distance")
    with pytest.raises(ValueError, match="empty"):
        evaluate_policy(policy, [], WORLD, progress=False)
    with pytest.raises(ValueError, match="seed"):
        evaluate_policy(policy, scenarios, WORLD, seed=-1, progress=False)
    with pytest.raises(InputError, match="episode_steps"):
        replace(WORLD, episode_steps=0)


def test_heterogeneity_bins() -> None:
    assert heterogeneity_bin(0.0) == 0
    assert heterogeneity_bin(0.1) == 2
    assert heterogeneity_bin(0.149999) == 2
    assert heterogeneity_bin(1.0) == 19


def test_tables_name_policies_bins_and_gains(scenarios: list[Scenario]) -> None:
    results = [run(make_placement(n), scenarios) for n in ("min-distance", "load-weighted")]
    text = format_results(results)
    assert "min-distance" in text and "load-weighted" in text
    assert "load-weighted/min-distance" in text
    bins = {heterogeneity_bin(r["heterogeneity"]) for r in results[0]["scenarios"]}
    for b in bins:
        assert f"[{b * 0.05:.2f}, {(b + 1) * 0.05:.2f})" in text
    # Without the reference there is no gain column.
    assert "/min-distance" not in format_results(results[1:])
