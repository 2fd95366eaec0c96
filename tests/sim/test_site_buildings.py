"""A site's buildings as exclusions (sim/envelope/buildings.py): every building cell that
reaches the flight band is covered up to its height plus the margin, every envelope over a site
holds them (the world's, a vehicle's, a document's), and what is flown over a site keeps out of
them."""

from __future__ import annotations

import numpy as np
import pytest

from sim.channel import area_site
from sim.config import AreaConfig, shipped_sites
from sim.envelope import area_envelope, envelope_from_document
from sim.envelope.buildings import BUILDING_MARGIN_M, LAYER_STEP_M, building_exclusions
from sim.envs import FapContinuousEnv
from sim.scenarios import generate_scenarios
from sim.world import get_world


def _tall_cells(site, floor_m: float) -> list[tuple[float, float, float]]:
    """(x, y, height) of the cell centres whose building reaches the band from ``floor_m``."""
    rows, columns = np.nonzero(site.building_height_m + BUILDING_MARGIN_M > floor_m)
    c = site.cell_m
    return [
        ((j + 0.5) * c, (i + 0.5) * c, float(site.building_height_m[i, j]))
        for i, j in zip(rows, columns, strict=True)
    ]


@pytest.mark.parametrize("name", shipped_sites())
def test_every_tall_cell_is_forbidden_up_to_its_roof_plus_the_margin(name: str) -> None:
    area = AreaConfig(environment=f"site:{name}")
    envelope = area_envelope(area)
    site = area_site(area)
    cells = _tall_cells(site, area.z_min_m)
    assert cells, "a shipped site has buildings in the band"
    c = site.cell_m
    for x, y, height in cells:
        z = min(max(height + BUILDING_MARGIN_M - 0.01, area.z_min_m), area.z_max_m)
        # the cell's corners, its centre, and a point just outside it within the margin
        for px, py in ((x, y), (x - c / 2, y - c / 2), (x + c / 2, y + c / 2)):
            assert envelope.violation((px, py, z)) is not None, (name, px, py, z, height)
        outside = min(x + c / 2 + BUILDING_MARGIN_M - 0.5, area.size_x_m)
        assert envelope.violation((outside, y, z)) is not None, (name, outside, y, z)


def test_a_low_group_is_not_capped_below_its_tallest_cell_and_lower_roofs_stay_open() -> None:
    site = area_site(AreaConfig(environment="site:munich"))
    exclusions = building_exclusions(site, 500.0, 500.0, 25.0, 100.0)
    floor = 25.0 - BUILDING_MARGIN_M
    lowest = [e for e in exclusions if e.ceiling_m <= floor + LAYER_STEP_M + BUILDING_MARGIN_M]
    assert lowest, "the first layer caps its groups at the next threshold"
    assert all(e.floor_m == 0.0 for e in exclusions)
    # every exclusion's ceiling is within one layer of a real roof under it: never invented
    tallest = float(site.building_height_m.max())
    assert max(e.ceiling_m for e in exclusions) == pytest.approx(tallest + BUILDING_MARGIN_M)
    # a point high above a low roof is legal (the envelope does not close the sky)
    envelope = area_envelope(AreaConfig(environment="site:munich"))
    x, y, height = min(_tall_cells(site, 25.0), key=lambda cell: cell[2])
    assert envelope.violation((x, y, 100.0)) is None, (x, y, height)


def test_every_envelope_over_a_site_holds_its_buildings_and_none_elsewhere() -> None:
    site_area = AreaConfig(environment="site:munich")
    buildings = len(area_envelope(site_area).exclusions)
    assert buildings > 10
    own = {
        "format": "tupa-envelope/1",
        "exclusions": [{"polygon": [[0, 0], [10, 0], [10, 10]], "floor_m": 0, "ceiling_m": 60}],
    }
    assert len(envelope_from_document(own, site_area).exclusions) == buildings + 1
    assert area_envelope(AreaConfig()).exclusions == ()


def test_a_world_over_a_site_always_has_an_envelope_with_the_buildings() -> None:
    from dataclasses import replace

    world = replace(get_world("closed-loop"), area=AreaConfig(environment="site:munich"))
    assert world.envelope is not None
    assert len(world.flight_envelope.exclusions) == len(
        area_envelope(AreaConfig(environment="site:munich")).exclusions
    )
    assert replace(get_world("closed-loop")).envelope is None


def _in_a_building(site, xyz_m) -> bool:
    x, y, z = (float(v) for v in xyz_m)
    heights = site.building_height_m
    row = min(int(y // site.cell_m), heights.shape[0] - 1)
    column = min(int(x // site.cell_m), heights.shape[1] - 1)
    return z <= float(heights[row, column])


def test_the_loops_flight_along_routes_over_munich_never_enters_a_building() -> None:
    """Random targets (the worst policy), a new one each second, flown with the loop's
    acceleration limit along the link's routes: checked every link tick, no point inside a
    building (raw heights, no margin)."""
    from dataclasses import replace

    from sim.envelope.flight import LINK_TICK_S, fly_route_period

    area = AreaConfig(environment="site:munich")
    world = get_world("closed-loop")
    flight = replace(world.flight, latency_s=0.0)
    envelope = area_envelope(area)
    site = area_site(area)
    rng = np.random.default_rng(5)
    position, velocity, route = np.array([250.0, 250.0, 25.0]), np.zeros(3), None
    ticks = round(1.0 / LINK_TICK_S)
    for _ in range(60):
        target = rng.uniform([0, 0, 25], [500, 500, 100])
        for _ in range(ticks):
            flown, velocity = fly_route_period(
                envelope, position, velocity, target, flight, LINK_TICK_S, route
            )
            position, route = flown.position_m, flown.route
            assert not _in_a_building(site, position), (position, route)


@pytest.mark.parametrize("preset", ["closed-loop", "closed-loop-moving"])
def test_what_the_world_flies_over_munich_never_enters_a_building(preset: str) -> None:
    """The environment's own step (latency, acceleration, routes): every period ends outside
    every building, and the target it reports is a legal point of the envelope."""
    from dataclasses import replace

    area = AreaConfig(environment="site:munich")
    world = replace(get_world(preset), area=area, episode_steps=12)
    site = area_site(area)
    scenarios = generate_scenarios(4, 10, seed=3, area=area)
    rng = np.random.default_rng(0)
    env = FapContinuousEnv(scenarios, world=world)
    for episode in range(4):
        env.reset(seed=episode)
        for _ in range(world.episode_steps):
            _, _, _, _, info = env.step_to(rng.uniform([0, 0, 25], [500, 500, 100]))
            assert not _in_a_building(site, env.uav_xyz_m)
            assert env.world.flight_envelope.violation(info["target_xyz_m"]) is None


def test_a_teleporting_world_over_a_site_is_at_the_legal_target_at_once() -> None:
    """The paper's protocol (no flight) over munich: the vehicle is at the legal point of each
    target, never inside a building, and nothing is planned on the way."""
    from dataclasses import replace

    area = AreaConfig(environment="site:munich")
    world = replace(get_world("paper"), area=area, episode_steps=20)
    envelope = world.flight_envelope
    site = area_site(area)
    env = FapContinuousEnv(generate_scenarios(2, 5, seed=1, area=area), world=world)
    env.reset(seed=0)
    rng = np.random.default_rng(2)
    for _ in range(world.episode_steps):
        target = rng.uniform([0, 0, 25], [500, 500, 100])
        _, _, _, _, info = env.step_to(target)
        assert env.uav_xyz_m.tolist() == pytest.approx(list(info["target_xyz_m"]))
        assert envelope.violation(env.uav_xyz_m) is None
        assert not _in_a_building(site, env.uav_xyz_m)
