"""Policies on a site (issue 38/40): ``min-distance-env`` chooses the position with the least
mean path loss the site gives (policies/placements/baselines.py), and the fleet policies'
association estimate hears each AP at its exact position on the site, an AP with no path never heard
(sim/association.py, as sim/fleet.py's association). Open field and towns are unchanged."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from policies.interface import ReportedUsers
from policies.placements.baselines import (
    MinDistancePlacement,
    best_site_position_m,
    best_snr_altitude_m,
    site_mean_loss_db,
)
from policies.registry import make_placement
from sim.association import associate_at, received_power_dbm
from sim.channel import NO_LINK_LOSS_DB, area_site
from sim.config import AreaConfig, NetworkConfig, RadioConfig
from sim.fleet import FleetConfig, FleetModel
from sim.scenarios import Scenario
from sim.sites import Site, path_loss_db, save_site
from sim.sites.format import quantise_loss_db
from sim.world import PAPER

SIZE_M = 200.0
CELL_M = 5.0
CELLS = round(SIZE_M / CELL_M)
XS = np.linspace(0.0, SIZE_M, 5)  # UAV grid every 50 m
ZS = np.array([25.0, 50.0, 75.0, 100.0])
AREA_SHAPE = {"size_x_m": SIZE_M, "size_y_m": SIZE_M}


def _random_site(seed: int, height: np.ndarray | None = None) -> Site:
    """Every link covered, its loss drawn uniformly in 80-120 dB per grid point and ground cell:
    the lookup's values with no geometry behind them, so the search cannot lean on one."""
    rng = np.random.default_rng(seed)
    loss = rng.uniform(80.0, 120.0, (ZS.size, XS.size, XS.size, CELLS, CELLS))
    height = np.zeros((CELLS, CELLS), np.float32) if height is None else height
    return Site(
        size_x_m=SIZE_M,
        size_y_m=SIZE_M,
        cell_m=CELL_M,
        user_height_m=1.5,
        uav_x_m=XS,
        uav_y_m=XS.copy(),
        uav_z_m=ZS,
        loss_code=quantise_loss_db(loss),
        building_height_m=height,
        walkable=height == 0,
        meta={},
    )


def _area(site: Site, directory: Path) -> AreaConfig:
    save_site(site, directory)
    return AreaConfig(**AREA_SHAPE, environment=f"site:{directory}")


def _volume_sample(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [rng.uniform(0, SIZE_M, n), rng.uniform(0, SIZE_M, n), rng.uniform(25.0, 100.0, n)]
    )


USERS = np.array([[12.0, 33.0], [150.0, 20.0], [97.0, 181.0], [60.0, 60.0], [190.0, 140.0]])


# ------------------------------------------------------------------------ min-distance-env


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_min_distance_env_finds_the_least_mean_loss_of_the_whole_volume(
    tmp_path: Path, seed: int
) -> None:
    """Between grid points the lookup is trilinear: with every link covered the mean loss is
    least at a lattice point, so nothing in the volume beats the choice."""
    site = _random_site(seed)
    area = _area(site, tmp_path / "site")
    placed = MinDistancePlacement(area, altitude="best-snr").place(Scenario("s", USERS, np.ones(5)))
    best = site_mean_loss_db(site, placed[None], USERS, None)[0]
    sample = _volume_sample(5000, seed)
    assert best <= site_mean_loss_db(site, sample, USERS, None).min() + 1e-9
    grid = np.stack(np.meshgrid(XS, XS, ZS, indexing="ij"), axis=-1).reshape(-1, 3)
    assert best <= site_mean_loss_db(site, grid, USERS, None).min() + 1e-9
    plain = MinDistancePlacement(area).place(Scenario("s", USERS, np.ones(5)))
    assert best < site_mean_loss_db(site, plain[None], USERS, None)[0]
    assert np.all(placed >= [0, 0, area.z_min_m]) and np.all(placed <= [200, 200, area.z_max_m])


def test_min_distance_env_is_the_registry_s_and_deterministic(tmp_path: Path) -> None:
    area = _area(_random_site(7), tmp_path / "site")
    world = replace(PAPER, area=area)
    policy = make_placement("min-distance-env", world)
    users = ReportedUsers(USERS, np.array([1e6, 2e6, 3e6, 4e6, 30e6]))
    first = policy.place(users)
    assert np.array_equal(first, policy.place(users))
    site = area_site(area)
    assert site is not None
    expected = best_site_position_m(USERS, area, site, None, np.array([0.0, 0.0, 25.0]))
    assert site_mean_loss_db(site, first[None], USERS, None)[0] == pytest.approx(
        site_mean_loss_db(site, expected[None], USERS, None)[0], abs=1e-9
    )
    assert policy.name == "min-distance-env"


def test_reaching_every_user_comes_first(tmp_path: Path) -> None:
    """User 0 has a path only from the grid points at x = 200 m; every other link is 20 dB
    better from x = 0. The choice reaches user 0, as a placement the model can serve must."""
    site = _random_site(4)
    loss = np.full((ZS.size, XS.size, XS.size, CELLS, CELLS), 100.0)
    loss[:, :, XS < 150.0] -= 20.0  # everybody is better heard from the west ...
    row, column = int(USERS[0, 1] // CELL_M), int(USERS[0, 0] // CELL_M)
    loss[:, :, XS < 200.0, row, column] = np.inf  # ... but user 0 only from x = 200 m
    site = replace(site, loss_code=quantise_loss_db(loss))
    area = _area(site, tmp_path / "site")
    placed = MinDistancePlacement(area, altitude="best-snr").place(Scenario("s", USERS, np.ones(5)))
    assert np.isfinite(path_loss_db(site, placed, USERS)).all()
    assert placed[0] >= 175.0 - 1e-9  # within half a grid spacing of x = 200 m: covered


def test_min_distance_env_never_chooses_a_place_inside_a_building(tmp_path: Path) -> None:
    """A tower whose roof is as high as the best place of the free site, 85 m across, put
    under it: the choice leaves the tower's volume (above its roof or beside it)."""
    free = _random_site(5)
    scenario = Scenario("s", USERS, np.ones(5))
    best = MinDistancePlacement(_area(free, tmp_path / "free"), altitude="best-snr").place(scenario)
    height = np.zeros((CELLS, CELLS), np.float32)
    column, row = np.minimum(best[:2] // CELL_M, CELLS - 1).astype(int)
    height[max(row - 8, 0) : row + 9, max(column - 8, 0) : column + 9] = best[2]
    towered = replace(free, building_height_m=height, walkable=height == 0)
    area = _area(towered, tmp_path / "tower")
    placed = MinDistancePlacement(area, altitude="best-snr").place(scenario)
    column, row = np.minimum(placed[:2] // CELL_M, CELLS - 1).astype(int)
    assert placed[2] > height[row, column]
    assert not np.allclose(placed, best)
    # Still the least mean loss among the lattice's places above the roofs.
    grid = np.stack(np.meshgrid(XS, XS, ZS, indexing="ij"), axis=-1).reshape(-1, 3)
    cells = np.minimum(grid[:, :2] // CELL_M, CELLS - 1).astype(int)
    above = grid[grid[:, 2] > height[cells[:, 1], cells[:, 0]]]
    cost = site_mean_loss_db(towered, placed[None], USERS, None)[0]
    assert cost <= site_mean_loss_db(towered, above, USERS, None).min() + 1e-9


def test_load_weighted_env_on_a_site_follows_the_heavy_user(tmp_path: Path) -> None:
    site = _random_site(6)
    area = _area(site, tmp_path / "site")
    load = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1.0]) * 40e6
    placed = MinDistancePlacement(area, load_weighted=True, altitude="best-snr").place(
        Scenario("s", USERS, load)
    )
    alone = best_site_position_m(USERS[4:], area, site)
    weighted = site_mean_loss_db(site, placed[None], USERS, load)[0]
    assert weighted <= site_mean_loss_db(site, alone[None], USERS, load)[0] + 1e-9
    assert path_loss_db(site, placed, USERS[4:])[0] < np.mean(path_loss_db(site, placed, USERS))


def test_open_field_and_towns_are_unchanged() -> None:
    scenario = Scenario("s", USERS * 2.5, np.array([1e6, 2e6, 3e6, 4e6, 30e6]))
    plain = MinDistancePlacement(AreaConfig()).place(scenario)
    assert np.array_equal(
        MinDistancePlacement(AreaConfig(), altitude="best-snr").place(scenario), plain
    )
    urban = AreaConfig(environment="urban")
    placed = MinDistancePlacement(urban, altitude="best-snr").place(scenario)
    assert np.array_equal(placed[:2], plain[:2])
    z = best_snr_altitude_m(scenario.users_xy_m, plain[:2], urban, RadioConfig().frequency_hz)
    assert placed[2] == z


# ------------------------------------------------------------------------------ association


def _shadow_site(directory: Path) -> tuple[AreaConfig, Site]:
    """Free-space-like losses, except that the ground cell of (60, 100) has no path from any
    grid point with x < 100 m."""
    site = _random_site(8)
    grid_x, grid_y, grid_z = np.meshgrid(XS, XS, ZS, indexing="xy")
    centres = (np.arange(CELLS) + 0.5) * CELL_M
    gx, gy = np.meshgrid(centres, centres)
    d = np.sqrt(
        (grid_x.transpose(2, 0, 1)[..., None, None] - gx) ** 2
        + (grid_y.transpose(2, 0, 1)[..., None, None] - gy) ** 2
        + (grid_z.transpose(2, 0, 1)[..., None, None] - 1.5) ** 2
    )
    loss = 46.7 + 20 * np.log10(d)
    loss[:, :, XS < 100.0, int(100 // CELL_M), int(60 // CELL_M)] = np.inf
    site = replace(site, loss_code=quantise_loss_db(loss))
    return _area(site, directory), site


def test_association_on_a_site_hears_the_site_and_never_an_ap_without_a_path(tmp_path: Path):
    area, site = _shadow_site(tmp_path / "site")
    radio = NetworkConfig().radio
    uavs = np.array([[[50.0, 100.0, 25.0], [150.0, 100.0, 25.0]]])  # AP 0 is the nearer
    users = np.array([[60.0, 100.0], [40.0, 120.0], [140.0, 90.0]])
    rx = received_power_dbm(uavs, users, area, radio)
    loss = path_loss_db(site, uavs[0], users)
    assert np.array_equal(rx[0], radio.tx_power_dbm - np.minimum(loss, NO_LINK_LOSS_DB))
    assert rx[0, 0, 0] < radio.min_rssi_dbm  # no path: never heard
    association, handover = associate_at(uavs, users, area, radio, None, 3.0)
    assert association.tolist() == [[1, 0, 1]] and not handover.any()
    # In the open, the same geometry puts user 0 on the nearer AP: the site decided it.
    open_area = replace(area, environment="open")
    assert associate_at(uavs, users, open_area, radio, None, 3.0)[0].tolist() == [[0, 0, 1]]
    # The fleet model associates the same users the same way (what the estimate stands for).
    fleet = FleetModel(FleetConfig(n_uavs=2), NetworkConfig(), area)
    result = fleet.step(uavs, users, np.full(3, 5e6))
    assert np.array_equal(result.association, association)
    # Kept while heard, even when another AP is a little better; moved off an AP gone silent.
    moved, handover = associate_at(uavs, users, area, radio, np.array([[0, 1, 1]]), 300.0)
    assert moved.tolist() == [[1, 1, 1]] and handover.tolist() == [[True, False, False]]
