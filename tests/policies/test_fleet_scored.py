"""``kmeans-scored``: candidate partitions scored on the fleet model, the best one flown."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from policies.evaluation.fleet_evaluation import FLEET_EVAL_POLICIES, build_fleet_candidate
from policies.fleet_policy import (
    FLEET_POLICIES,
    FleetPlacementPolicy,
    ReportedAssociation,
    resolve_fleet_policy,
)
from policies.placements.fleet_baselines import KMeansPlacement
from policies.placements.fleet_oracle import FleetStart, fleet_episode_utility
from policies.placements.fleet_scored import KMEANS_SCORED, ScoredKMeansPlacement
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet import FleetConfig, FleetModel
from sim.flight import Flight
from sim.geometry import assign_targets, volume_bounds
from sim.observation import UserReports
from sim.scenarios import Scenario, generate_scenarios
from sim.world import get_world


def _one_loaded_spot() -> Scenario:
    """90 Mbit/s in one hot spot (more than one cell carries) and 3 Mbit/s in two far corners."""
    rng = np.random.default_rng(3)
    xy = np.concatenate(
        [
            rng.normal([250.0, 250.0], 12.0, (10, 2)),
            rng.normal([60.0, 60.0], 10.0, (3, 2)),
            rng.normal([440.0, 60.0], 10.0, (3, 2)),
        ]
    )
    load = np.concatenate([np.full(10, 9e6), np.full(6, 0.5e6)])
    return Scenario("spot", np.clip(xy, 1.0, 499.0), load)


def _score(
    fleet: FleetConfig, placement: np.ndarray, users: Scenario, start: FleetStart | None = None
) -> float:
    """The placement's score as :class:`ScoredKMeansPlacement` scores it (its defaults)."""
    steps = ScoredKMeansPlacement.score_steps
    return float(fleet_episode_utility(FleetModel(fleet), placement[None], users, steps, 1,
                                       1.0, start)[0])  # fmt: skip


@pytest.mark.parametrize("k", [2, 3, 4])
def test_the_pick_is_the_best_candidate_and_both_kmeans_are_candidates(k: int) -> None:
    fleet = FleetConfig(n_uavs=k)
    placement = ScoredKMeansPlacement(fleet)
    users = generate_scenarios(1, 30, 11 + k, family="hotspots", total_load_bps=40e6 * k)[0]
    fleets_m, scores, names = placement.scores(users)
    assert fleets_m.shape == (len(names), k, 3) and scores.shape == (len(names),)
    np.testing.assert_array_equal(placement.place(users), fleets_m[int(np.argmax(scores))])
    # Both k-means baselines are among the candidates, bit for bit, so the pick scores at least
    # as well as either on the model.
    for load_weighted, name in ((False, "kmeans-min-distance"), (True, "load^1")):
        baseline = KMeansPlacement(k, AreaConfig(), load_weighted, fleet.separation_m)
        np.testing.assert_array_equal(fleets_m[names.index(name)], baseline.place(users))
        assert scores.max() >= _score(fleet, baseline.place(users), users) - 1e-12


def test_a_loaded_hot_spot_gets_both_uavs_where_kmeans_splits_them() -> None:
    users, fleet = _one_loaded_spot(), FleetConfig(n_uavs=2)
    placed = ScoredKMeansPlacement(fleet).place(users)
    kmeans_lw = KMeansPlacement(2, AreaConfig(), True).place(users)
    # k-means gives one UAV to the light corners; the scored pick keeps both over the spot.
    assert np.all(np.hypot(placed[:, 0] - 250.0, placed[:, 1] - 250.0) < 60.0)
    assert _score(fleet, placed, users) > _score(fleet, kmeans_lw, users) + 0.3


@pytest.mark.parametrize("k", [1, 2, 5])
def test_placements_are_deterministic_separated_and_inside(k: int) -> None:
    fleet = FleetConfig(n_uavs=k, separation_m=25.0)
    users = _one_loaded_spot()
    placed = ScoredKMeansPlacement(fleet).place(users)
    np.testing.assert_array_equal(placed, ScoredKMeansPlacement(fleet).place(users))
    lower, upper = volume_bounds(AreaConfig())
    assert placed.shape == (k, 3)
    assert np.all(placed >= lower) and np.all(placed <= upper)
    gap = placed[:, None] - placed[None]
    assert (np.sqrt((gap**2).sum(-1)) + np.diag(np.full(k, np.inf))).min() >= 25.0


def test_more_uavs_than_user_positions() -> None:
    users = Scenario("two", np.array([[100.0, 100.0], [300.0, 300.0]]), np.array([5e6, 1e6]))
    placed = ScoredKMeansPlacement(FleetConfig(n_uavs=4)).place(users)
    assert placed.shape == (4, 3) and np.all(np.isfinite(placed))


@pytest.mark.parametrize("steps", [0, -1, 2.5, True])
def test_bad_score_steps_is_an_input_error(steps: object) -> None:
    with pytest.raises(InputError, match="score_steps"):
        ScoredKMeansPlacement(score_steps=steps)  # type: ignore[arg-type]


@pytest.mark.parametrize("step_s", [0.0, -1.0, float("nan"), float("inf")])
def test_a_bad_step_is_an_input_error(step_s: float) -> None:
    with pytest.raises(InputError, match="step_s"):
        ScoredKMeansPlacement(step_s=step_s)


def test_evaluated_and_served_by_name() -> None:
    world = get_world("closed-loop")
    assert KMEANS_SCORED in FLEET_EVAL_POLICIES and KMEANS_SCORED in FLEET_POLICIES
    name, candidate = build_fleet_candidate(KMEANS_SCORED, 3, world)
    users = generate_scenarios(1, 30, 3, family="hotspots", total_load_bps=120e6)[0]
    zeros = np.zeros(len(users.load_bps))
    reports = UserReports.from_metrics(users.users_xy_m, users.load_bps, zeros, zeros, zeros)
    # What is evaluated is what is served: the same decision from the same report.
    three = np.column_stack([15.0 * np.arange(3), np.zeros(3), np.full(3, 25.0)])
    np.testing.assert_array_equal(
        candidate.decide_fleet(reports, three),
        resolve_fleet_policy(KMEANS_SCORED, world, 10.0).decide_fleet(reports, three),
    )
    assert name == KMEANS_SCORED and isinstance(candidate, FleetPlacementPolicy)
    # Served with the service's decision period as the model's step (5 s here), as the oracle is:
    # from these vehicles, scoring with 1-s steps picks another placement.
    world = replace(world, step_s=5.0)
    served = resolve_fleet_policy(KMEANS_SCORED, world, 10.0)
    for k in (3, 2):  # as many targets as vehicles fly now, scored flown from where they are
        vehicles = np.column_stack([15.0 * np.arange(k), np.zeros(k), np.full(k, 25.0)])
        targets = served.decide_fleet(reports, vehicles)
        fleet = FleetConfig(n_uavs=k)
        # From the users' APs as the one rule estimates them (a fresh start: K changed).
        on = ReportedAssociation(world).at(reports, vehicles)
        expected, one_second = (
            ScoredKMeansPlacement(
                fleet, world.area, world.network, world.utility, step_s=step_s
            ).place_from(users, vehicles, on, world.flight)
            for step_s in (world.step_s, 1.0)
        )
        np.testing.assert_array_equal(targets, expected)
        assert not np.array_equal(expected, one_second)


def test_from_where_the_fleet_is_the_pick_is_the_best_flown_candidate() -> None:
    users, fleet = _one_loaded_spot(), FleetConfig(n_uavs=3)
    placement = ScoredKMeansPlacement(fleet)
    homes = np.array([[20.0, 20.0, 25.0], [480.0, 20.0, 25.0], [250.0, 480.0, 25.0]])
    start = FleetStart(homes, None, Flight())
    fleets_m, scores, _ = placement.scores(users, start)
    placed = placement.place_from(users, homes)
    np.testing.assert_array_equal(placed, fleets_m[int(np.argmax(scores))])
    # Row i is vehicle i's target: the candidate given to the vehicles by least flight.
    np.testing.assert_array_equal(placed, assign_targets(homes, placed))
    kmeans_lw = assign_targets(homes, KMeansPlacement(3, AreaConfig(), True).place(users))
    assert _score(fleet, placed, users, start) >= _score(fleet, kmeans_lw, users, start) - 1e-12
