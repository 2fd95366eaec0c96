"""The service's fleet placements (policies.fleet_policy.FleetPlacementPolicy): the k-means
baselines place from the report alone; the scored placements search from where the vehicles
are, the users on the APs the fleet model's rule gives them (policies.fleet_policy
.ServedAssociation, as a served fleet checkpoint sees them), carried from one decision to the
next."""

from __future__ import annotations

import numpy as np

from policies.fleet_baselines import KMeansPlacement
from policies.fleet_oracle import FleetOracle, FleetOracleConfig
from policies.fleet_policy import FleetPlacementPolicy
from policies.fleet_scored import ScoredKMeansPlacement
from policies.interface import ReportedUsers
from sim.association import associate_at
from sim.fleet import FleetConfig
from sim.geometry import min_pairwise_distance_m
from sim.observation import UserReports
from sim.world import get_world

WORLD = get_world("closed-loop")
VEHICLES = np.array([[240.0, 250.0, 25.0], [260.0, 250.0, 25.0]])


def _reports() -> UserReports:
    xy = np.array([[60.0, 80.0], [70.0, 90.0], [420.0, 400.0], [430.0, 390.0], [425.0, 410.0]])
    offered = np.array([2e6, 2e6, 12e6, 12e6, 12e6])
    zeros = np.zeros(len(xy))
    return UserReports(xy[:, 0], xy[:, 1], offered, offered.copy(), zeros, zeros)


def _associated(vehicles: np.ndarray, current: np.ndarray | None = None) -> np.ndarray:
    """The fleet model's association (1, U) at ``vehicles``, computed here, from ``current``."""
    reports = _reports()
    xy = np.column_stack([reports.x_m, reports.y_m])
    radio, hysteresis_db = WORLD.network.radio, FleetConfig().hysteresis_db
    return associate_at(vehicles[None], xy, WORLD.area, radio, current, hysteresis_db)[0]


def test_kmeans_is_served_as_it_places() -> None:
    served = FleetPlacementPolicy("kmeans-load-weighted", WORLD).decide_fleet(_reports(), VEHICLES)
    users = ReportedUsers.of(_reports())
    np.testing.assert_array_equal(served, KMeansPlacement(2, WORLD.area, True).place(users))


def test_the_oracle_is_served_from_where_the_vehicles_are() -> None:
    served = FleetPlacementPolicy("fleet-oracle", WORLD).decide_fleet(_reports(), VEHICLES)
    oracle = FleetOracle(
        FleetConfig(n_uavs=2), WORLD.area, WORLD.network, WORLD.utility,
        FleetOracleConfig(step_s=WORLD.step_s),
    )  # fmt: skip
    users = ReportedUsers.of(_reports())
    expected = oracle.place_from(users, VEHICLES, _associated(VEHICLES)[0], WORLD.flight)
    np.testing.assert_array_equal(served, expected)
    assert min_pairwise_distance_m(served) >= 10.0
    # One vehicle over each hot spot.
    nearest = {
        int(np.argmin(np.hypot(*(served[:, :2] - spot).T))) for spot in ([65, 85], [425, 400])
    }
    assert nearest == {0, 1}


def test_kmeans_scored_is_served_from_the_users_aps_carried_between_decisions() -> None:
    policy = FleetPlacementPolicy("kmeans-scored", WORLD)
    scored = ScoredKMeansPlacement(
        FleetConfig(n_uavs=2), WORLD.area, WORLD.network, WORLD.utility, step_s=WORLD.step_s
    )
    users = ReportedUsers.of(_reports())
    start = np.array([[400.0, 380.0, 25.0], [100.0, 100.0, 25.0]])
    first = _associated(start)
    np.testing.assert_array_equal(
        policy.decide_fleet(_reports(), start),
        scored.place_from(users, start, first[0], WORLD.flight),
    )
    # The next decision, both vehicles near the big hot spot: the small one's users keep their
    # AP (the hysteresis), which a fresh association would not give them.
    moved = np.array([[362.0, 385.0, 25.0], [466.0, 382.0, 25.0]])
    carried, fresh = _associated(moved, first), _associated(moved)
    assert not np.array_equal(carried, fresh)
    served = policy.decide_fleet(_reports(), moved)
    np.testing.assert_array_equal(served, scored.place_from(users, moved, carried[0], WORLD.flight))
    # Which is not what it gave when served without the users' APs (as evaluated, it has them).
    assert not np.array_equal(served, scored.place_from(users, moved, None, WORLD.flight))
