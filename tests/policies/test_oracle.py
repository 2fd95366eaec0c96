"""The oracle: in the volume, never beaten by the baselines, consistent with the environment."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from policies.evaluation.evaluation import evaluate_policy
from policies.placements.oracle import OracleConfig, OraclePlacement, episode_utility
from policies.registry import make_placement
from sim.config import AreaConfig, NetworkConfig
from sim.scenarios import Scenario, generate_scenarios
from sim.world import PAPER

AREA = AreaConfig()
STEPS = 30  # a shorter episode than the paper's keeps these tests fast; the logic is the same


def in_volume(position: np.ndarray, area: AreaConfig) -> bool:
    return bool(
        position.shape == (3,)
        and 0.0 <= position[0] <= area.size_x_m
        and 0.0 <= position[1] <= area.size_y_m
        and area.z_min_m <= position[2] <= area.z_max_m
    )


@settings(max_examples=8, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_users=st.integers(1, 5),
    queueing=st.sampled_from(["fq-codel", "mac-only"]),
)
def test_oracle_is_never_beaten_by_the_baselines_on_the_expected_model(
    seed, n_users, queueing
) -> None:
    scenarios = generate_scenarios(2, n_users, seed=seed, area=AREA)
    world = replace(
        PAPER,
        episode_steps=STEPS,
        stochastic=False,
        network=NetworkConfig().with_queueing(queueing),
    )
    results = {
        name: evaluate_policy(make_placement(name, world), scenarios, world, progress=False)
        for name in ("min-distance", "load-weighted", "oracle")
    }
    oracle = [s["utility"] for s in results["oracle"]["scenarios"]]
    for name in ("min-distance", "load-weighted"):
        for o, b in zip(oracle, (s["utility"] for s in results[name]["scenarios"]), strict=True):
            assert o >= b - 1e-9


def test_oracle_score_is_the_environment_episode() -> None:
    """The oracle's own score of its position equals the expected-mode environment's episode."""
    scenarios = generate_scenarios(3, 3, seed=11, area=AREA)
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS))
    searched = [oracle.search(s).utility for s in scenarios]
    world = replace(PAPER, episode_steps=STEPS, stochastic=False)
    result = evaluate_policy(oracle, scenarios, world, progress=False)
    assert np.allclose(searched, [s["utility"] for s in result["scenarios"]], atol=1e-12)


def test_oracle_matches_or_beats_the_exhaustive_grid() -> None:
    """Regression check of the screen: on these scenarios the short-horizon screen keeps the
    grid's best full-episode position, and refinement only adds to it."""
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS))
    grid = AREA.grid_positions_m()
    for scenario in generate_scenarios(3, 3, seed=5, area=AREA):
        exhaustive = episode_utility(oracle.model, grid, scenario, STEPS).max()
        result = oracle.search(scenario)
        assert result.utility >= exhaustive - 1e-12
        assert result.utility >= result.grid_utility


@pytest.mark.parametrize(
    "area",
    [AREA, AreaConfig(size_x_m=100.0, size_y_m=50.0, zone_m=25.0, z_min_m=25.0, z_max_m=25.0)],
)
def test_oracle_position_lies_in_the_volume(area: AreaConfig) -> None:
    corner_users = Scenario(
        "corners",
        [[0.0, 0.0], [area.size_x_m, area.size_y_m], [area.size_x_m, 0.0]],
        [30e6, 5e6, 5e6],
    )
    scenarios = [corner_users, *generate_scenarios(3, 4, seed=2, area=area)]
    oracle = OraclePlacement(area, config=OracleConfig(episode_steps=10, initial_step_m=40.0))
    for scenario in scenarios:
        assert in_volume(oracle.place(scenario), area)


def test_oracle_without_refinement_returns_a_candidate() -> None:
    scenario = generate_scenarios(1, 3, seed=3, area=AREA)[0]
    config = OracleConfig(episode_steps=10, refine_starts=0, include_baselines=False)
    result = OraclePlacement(AREA, config=config).search(scenario)
    assert any(np.array_equal(result.position_m, p) for p in AREA.grid_positions_m())
    assert result.utility == result.grid_utility


def test_oracle_config_is_validated() -> None:
    with pytest.raises(ValueError, match="top_k"):
        OracleConfig(top_k=0)
    with pytest.raises(ValueError, match="min_step_m"):
        OracleConfig(min_step_m=0.0)
