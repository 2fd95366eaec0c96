"""The fleet's placements: k-means baselines and the search oracle are deterministic, separated,
inside the volume, and the oracle is never below the k-means placements on its own objective."""

from __future__ import annotations

import numpy as np
import pytest

from policies.interface import UsersLike
from policies.placements.fleet_baselines import KMeansPlacement, kmeans
from policies.placements.fleet_oracle import (
    FleetOracle,
    FleetOracleConfig,
    FleetStart,
    fleet_episode_utility,
)
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import FleetConfig, FleetModel
from sim.flight import Flight, fly_many
from sim.geometry import assign_targets, volume_bounds
from sim.scenarios import Scenario, generate_scenarios


def _hot_spots() -> Scenario:
    """Three hot spots of unequal demand: 120 Mbit/s, more than one cell carries."""
    rng = np.random.default_rng(4)
    centres = np.array([[80.0, 90.0], [400.0, 120.0], [260.0, 420.0]])
    counts, loads = (6, 4, 2), (4e6, 12e6, 18e6)
    xy = np.concatenate(
        [c + rng.normal(0.0, 15.0, (n, 2)) for c, n in zip(centres, counts, strict=True)]
    )
    load = np.concatenate([np.full(n, v) for n, v in zip(counts, loads, strict=True)])
    return Scenario("hot", np.clip(xy, 1.0, 499.0), load * 120e6 / load.sum())


def _check_placement(positions: np.ndarray, k: int, separation_m: float = 10.0) -> None:
    lower, upper = volume_bounds(AreaConfig())
    assert positions.shape == (k, 3)
    assert np.all(positions >= lower) and np.all(positions <= upper)
    gap = positions[:, None] - positions[None]
    distance = np.sqrt((gap**2).sum(-1)) + np.diag(np.full(k, np.inf))
    assert distance.min() >= separation_m


def test_kmeans_finds_separate_clusters_deterministically() -> None:
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.normal(c, 5.0, (20, 2)) for c in ([0, 0], [100, 0], [0, 100])])
    centres, labels = kmeans(points, 3, seed=1)
    assert sorted(np.bincount(labels)) == [20, 20, 20]
    again, labels_again = kmeans(points, 3, seed=1)
    np.testing.assert_array_equal(centres, again)
    np.testing.assert_array_equal(labels, labels_again)
    # Weights pull a centre toward the heavy point.
    two = np.array([[0.0, 0.0], [10.0, 0.0]])
    centre, _ = kmeans(two, 1, weights=np.array([1.0, 3.0]))
    assert centre[0, 0] == pytest.approx(7.5)


@pytest.mark.parametrize("load_weighted", [False, True])
def test_kmeans_placements_are_deterministic_separated_and_inside(load_weighted: bool) -> None:
    scenario = _hot_spots()
    placement = KMeansPlacement(3, load_weighted=load_weighted)
    first = placement.place(scenario)
    np.testing.assert_array_equal(
        first, KMeansPlacement(3, load_weighted=load_weighted).place(scenario)
    )
    _check_placement(first, 3)
    assert np.all(first[:, 2] == 25.0)  # min-distance flies at the lowest level
    # One UAV over each hot spot.
    centres = np.array([[80.0, 90.0], [400.0, 120.0], [260.0, 420.0]])
    nearest = np.argmin(np.linalg.norm(first[:, None, :2] - centres[None], axis=-1), axis=1)
    assert sorted(nearest) == [0, 1, 2]
    assert placement.name == ("kmeans-load-weighted" if load_weighted else "kmeans-min-distance")


def test_more_uavs_than_users_still_gives_separated_positions() -> None:
    scenario = generate_scenarios(1, 2, seed=0, family="uniform")[0]
    _check_placement(KMeansPlacement(5).place(scenario), 5)


class _Recording:
    """A single-UAV placement that records the users it is asked to place over."""

    name = "recording"

    def __init__(self) -> None:
        self.groups: list[np.ndarray] = []

    def place(self, users: UsersLike) -> np.ndarray:
        xy = np.asarray(users.users_xy_m, dtype=float)
        self.groups.append(xy)
        return np.array([*xy.mean(axis=0), 60.0])


def test_per_cluster_placement_keeps_the_partition_and_places_each_group() -> None:
    from policies.placements.baselines import MinDistancePlacement

    scenario = _hot_spots()
    # The default per-cluster placement, named explicitly, gives the baseline to the bit.
    explicit = KMeansPlacement(3, load_weighted=True, per_cluster=MinDistancePlacement(
        AreaConfig(), load_weighted=True))  # fmt: skip
    np.testing.assert_array_equal(
        explicit.place(scenario), KMeansPlacement(3, load_weighted=True).place(scenario)
    )
    # Another placement is asked once per k-means group: the groups partition the users.
    recording = _Recording()
    placement = KMeansPlacement(3, load_weighted=True, per_cluster=recording)
    positions = placement.place(scenario)
    assert placement.name == "kmeans-load-weighted+recording"
    assert len(recording.groups) == 3
    _, labels = kmeans(scenario.users_xy_m, 3, scenario.load_bps, 0, 4)
    expected = sorted(tuple(map(tuple, scenario.users_xy_m[labels == c])) for c in range(3))
    assert sorted(tuple(map(tuple, g)) for g in recording.groups) == expected
    _check_placement(positions, 3)
    assert np.all(positions[:, 2] == 60.0)  # the per-cluster placement's own altitude


def test_bad_fleet_sizes_are_one_line_errors() -> None:
    with pytest.raises(InputError, match=r"^n_uavs:"):
        KMeansPlacement(9)
    with pytest.raises(InputError, match=r"^separation_m:"):
        KMeansPlacement(2, separation_m=0.0)


def test_oracle_is_deterministic_and_at_least_the_kmeans_placements() -> None:
    scenario = _hot_spots()
    config = FleetOracleConfig(episode_steps=8, restarts=1, sweeps=2, screen_stride=4)
    oracle = FleetOracle(FleetConfig(n_uavs=3), config=config)
    result = oracle.search(scenario)
    again = FleetOracle(FleetConfig(n_uavs=3), config=config).search(scenario)
    np.testing.assert_array_equal(result.positions_m, again.positions_m)
    assert result.utility == again.utility
    _check_placement(result.positions_m, 3)
    for load_weighted in (False, True):
        baseline = KMeansPlacement(3, load_weighted=load_weighted).place(scenario)
        assert result.utility >= oracle.score(baseline[None], scenario)[0]
    # Its reported score is the score of what it returns.
    assert oracle.score(result.positions_m[None], scenario)[0] == pytest.approx(result.utility)
    assert result.utility > result.start_utility  # the search did improve on its starts


def test_without_sweeps_the_oracle_refines_the_kmeans_placements_only() -> None:
    """sweeps=0: no coordinate descent over the area, so the answer is a compass-refined k-means
    placement: no worse than either, and found with far fewer simulated episodes."""
    scenario = _hot_spots()
    local = FleetOracleConfig(episode_steps=8, restarts=0, sweeps=0, pair_stride=0)
    swept = FleetOracleConfig(episode_steps=8, restarts=0, sweeps=1, pair_stride=0)
    result = FleetOracle(FleetConfig(n_uavs=3), config=local).search(scenario)
    full = FleetOracle(FleetConfig(n_uavs=3), config=swept).search(scenario)
    _check_placement(result.positions_m, 3)
    assert result.utility >= result.start_utility
    assert result.episodes_simulated < full.episodes_simulated
    with pytest.raises(InputError, match=r"^sweeps: must be >= 0"):
        FleetOracleConfig(sweeps=-1)


def test_settled_episodes_are_scored_exactly() -> None:
    """Skipping a placement's settled steps changes nothing: the same as stepping them all."""
    scenario = _hot_spots()
    model = FleetModel(FleetConfig(n_uavs=2))
    fleets = np.array(
        [
            [[80.0, 90.0, 25.0], [400.0, 120.0, 25.0]],  # well placed: settles at once
            [[10.0, 490.0, 100.0], [20.0, 480.0, 100.0]],  # badly placed: never settles
        ]
    )
    fast = fleet_episode_utility(model, fleets, scenario, steps=12)
    for b in range(2):
        state, total = None, 0.0
        for t in range(13):
            result = model.step(fleets[b], scenario.users_xy_m, scenario.load_bps, state)
            state = result.state
            total += result.utility[0] if t >= 1 else 0.0
        assert fast[b] == pytest.approx(total / 12, rel=1e-12)


def test_a_flown_episode_is_the_environment_s_and_a_fleet_already_there_scores_as_held() -> None:
    """Scored from a start, the episode is the one the fleet environment flies (expected mode,
    the vehicles' flight, associations carried); a start at the placement itself is the held
    placement's score."""
    scenario = _hot_spots()
    model = FleetModel(FleetConfig(n_uavs=2))
    placement = np.array([[80.0, 90.0, 25.0], [400.0, 120.0, 25.0]])
    homes = np.array([[240.0, 250.0, 25.0], [260.0, 250.0, 25.0]])
    flight = Flight(10.0, 3.0)
    steps = 40
    at_once = FleetStart(placement, None, flight)
    assert fleet_episode_utility(model, placement[None], scenario, steps, start=at_once)[
        0
    ] == pytest.approx(fleet_episode_utility(model, placement[None], scenario, steps)[0], rel=1e-12)
    flown = fleet_episode_utility(
        model, placement[None], scenario, steps, start=FleetStart(homes, None, flight)
    )[0]
    here, state, total = homes.copy(), None, 0.0
    for t in range(steps + 1):
        if t > 0:
            here = fly_many(here, placement, flight, 1.0)
        result = model.step(here, scenario.users_xy_m, scenario.load_bps, state)
        state = result.state
        total += result.utility[0] if t >= 1 else 0.0
    assert flown == pytest.approx(total / steps, rel=1e-12)


def test_searched_from_where_the_fleet_is_the_oracle_is_at_least_kmeans_flown() -> None:
    scenario = _hot_spots()
    config = FleetOracleConfig(episode_steps=30, restarts=1, sweeps=2, screen_stride=4)
    oracle = FleetOracle(FleetConfig(n_uavs=3), config=config)
    homes = np.array([[237.5, 262.5, 25.0], [262.5, 262.5, 25.0], [287.5, 262.5, 25.0]])
    start = FleetStart(homes, None, Flight(10.0, 3.0))
    result = oracle.search(scenario, start)
    _check_placement(result.positions_m, 3)
    # In the order a controller gives the targets to the vehicles, the order it was scored in.
    np.testing.assert_array_equal(assign_targets(homes, result.positions_m), result.positions_m)
    assert oracle.score(result.positions_m[None], scenario, start=start)[0] == pytest.approx(
        result.utility
    )
    for load_weighted in (False, True):
        baseline = assign_targets(
            homes, KMeansPlacement(3, load_weighted=load_weighted).place(scenario)
        )
        assert result.utility >= oracle.score(baseline[None], scenario, start=start)[0]
    np.testing.assert_array_equal(
        oracle.place_from(scenario, homes, None, Flight(10.0, 3.0)), result.positions_m
    )
    with pytest.raises(InputError, match="association"):
        oracle.search(scenario, FleetStart(homes, np.zeros(3, dtype=int), Flight()))
