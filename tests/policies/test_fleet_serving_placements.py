"""The service's fleet placements (policies.fleet_policy.FleetPlacementPolicy): the k-means
baselines place from the report alone; the search oracle searches from where the vehicles are."""

from __future__ import annotations

import numpy as np

from policies.fleet_policy import FleetPlacementPolicy
from policies.interface import ReportedUsers
from policies.placements.fleet_baselines import KMeansPlacement
from policies.placements.fleet_oracle import FleetOracle, FleetOracleConfig
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
    np.testing.assert_array_equal(served, oracle.place_from(users, VEHICLES, None, WORLD.flight))
    assert min_pairwise_distance_m(served) >= 10.0
    # One vehicle over each hot spot.
    nearest = {
        int(np.argmin(np.hypot(*(served[:, :2] - spot).T))) for spot in ([65, 85], [425, 400])
    }
    assert nearest == {0, 1}
