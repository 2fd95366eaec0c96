"""The site families of the scenario generator (sim/scenarios.py, issue 38 item 3): ``streets``,
``squares`` and ``crowd`` put users where people are in a district — on its street corridors,
in its largest open squares, mostly within ~20 m of one point — on walkable ground only,
deterministic per seed; off a site they are refused in one line (the generator, the sampler and
``tupa scenarios generate --family``)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from service.cli import main
from sim.config import AreaConfig
from sim.errors import InputError
from sim.files import load_scenarios
from sim.scenarios import (
    FAMILIES,
    SITE_FAMILIES,
    FamilyConfig,
    ScenarioSampler,
    check_scenario_area,
    generate_scenarios,
    site_ground,
)
from sim.sites import Site, save_site
from sim.sites.ground import walkable_at

CELL_M = 5.0
SIZE_M = 500.0  # the default area's side: what the command lines use
CELLS = round(SIZE_M / CELL_M)
# Street corridors, 20 m wide, running across the whole area (cell index ranges, end exclusive).
STREET_ROWS = ((20, 24), (60, 64))  # y 100-120 m and 300-320 m
STREET_COLUMNS = ((20, 24), (76, 80))  # x 100-120 m and 380-400 m
PLAZA_ROWS, PLAZA_COLUMNS = (35, 55), (40, 60)  # a 100 m × 100 m square, x 200-300, y 175-275
NOOK = (slice(84, 87), slice(5, 7))  # 15 m × 10 m of walkable ground shut in by buildings


def _site(height: np.ndarray) -> Site:
    xs, zs = np.linspace(0.0, SIZE_M, 3), np.array([25.0, 100.0])
    return Site(
        size_x_m=SIZE_M,
        size_y_m=SIZE_M,
        cell_m=CELL_M,
        user_height_m=1.5,
        uav_x_m=xs,
        uav_y_m=xs.copy(),
        uav_z_m=zs,
        loss_code=np.full((zs.size, xs.size, xs.size, CELLS, CELLS), 1000, np.uint16),
        building_height_m=height,
        walkable=height == 0,
        meta={},
    )


def _district() -> np.ndarray:
    """Blocks 20 m tall, cut by two streets each way, a plaza and a nook."""
    height = np.full((CELLS, CELLS), 20.0, np.float32)
    for lo, hi in STREET_ROWS:
        height[lo:hi, :] = 0.0
    for lo, hi in STREET_COLUMNS:
        height[:, lo:hi] = 0.0
    height[slice(*PLAZA_ROWS), slice(*PLAZA_COLUMNS)] = 0.0
    height[NOOK] = 0.0
    return height


@pytest.fixture(scope="module")
def area(tmp_path_factory: pytest.TempPathFactory) -> AreaConfig:
    directory = tmp_path_factory.mktemp("sites") / "district"
    save_site(_site(_district()), directory)
    return AreaConfig(environment=f"site:{directory}")


@pytest.fixture(scope="module")
def site(area: AreaConfig) -> Site:
    from sim.channel import area_site

    loaded = area_site(area)
    assert loaded is not None
    return loaded


def _cells(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xy = np.asarray(xy)
    return (xy[:, 1] // CELL_M).astype(int), (xy[:, 0] // CELL_M).astype(int)


def _in_streets(xy: np.ndarray) -> np.ndarray:
    row, column = _cells(xy)
    on = np.zeros(len(row), bool)
    for lo, hi in STREET_ROWS:
        on |= (row >= lo) & (row < hi)
    for lo, hi in STREET_COLUMNS:
        on |= (column >= lo) & (column < hi)
    return on


def _in_plaza(xy: np.ndarray) -> np.ndarray:
    row, column = _cells(xy)
    return (
        (row >= PLAZA_ROWS[0])
        & (row < PLAZA_ROWS[1])
        & (column >= PLAZA_COLUMNS[0])
        & (column < PLAZA_COLUMNS[1])
    )


# ----------------------------------------------------------------------------- the ground


def test_the_ground_analysis_finds_the_streets_and_the_plaza(site: Site, area: AreaConfig):
    ground = site_ground(site, area, FamilyConfig())
    centres = np.stack(np.meshgrid((np.arange(CELLS) + 0.5) * CELL_M,
                                   (np.arange(CELLS) + 0.5) * CELL_M), axis=-1)  # fmt: skip
    street_xy = centres[ground.street]
    assert ground.street.sum() > 0 and _in_streets(street_xy).all()  # streets only
    assert not ground.street[NOOK].any()  # 15 m long: a nook, not a street
    assert not ground.street[slice(*PLAZA_ROWS), slice(*PLAZA_COLUMNS)].any()
    # 20 m wide corridors away from the plaza are streets their whole width.
    assert ground.street[STREET_ROWS[0][0] : STREET_ROWS[0][1], 2:18].all()
    # The plaza is the one open piece: its middle is in it, nothing outside it is.
    (plaza,) = ground.squares
    assert _in_plaza(centres.reshape(-1, 2)[plaza]).all()
    assert ground.open[45, 50] and plaza.size > 0.8 * 20 * 20
    assert np.array_equal(ground.walkable, site.walkable)
    assert site_ground(site, area, FamilyConfig()) is ground  # computed once


# ---------------------------------------------------------------------------- the families


@pytest.mark.parametrize("n_users", [1, 3, 30])
def test_streets_put_every_user_on_a_street(area: AreaConfig, n_users: int):
    scenarios = generate_scenarios(40, n_users, seed=11, area=area, family="streets")
    for s in scenarios:
        assert s.id.endswith("-streets")
        assert _in_streets(s.users_xy_m).all(), s.id
        check_scenario_area(s, area)  # on walkable ground
        assert math.isclose(s.load_bps.sum(), 40e6, rel_tol=1e-9) and (s.load_bps > 0).all()
    # A stretch is at most street_segment_max_m long: users of one scenario are not spread
    # over the whole street network every time.
    spans = [np.ptp(s.users_xy_m, axis=0).max() for s in scenarios if n_users > 1]
    if spans:
        assert min(spans) < 200.0


def test_squares_put_every_user_in_the_largest_open_areas(area: AreaConfig):
    for s in generate_scenarios(30, 12, seed=4, area=area, family="squares"):
        assert _in_plaza(s.users_xy_m).all(), s.id
        check_scenario_area(s, area)


@pytest.mark.parametrize("n_users", [1, 2, 3, 10, 40])
def test_a_crowd_has_most_users_within_its_radius_of_one_walkable_point(
    area: AreaConfig, site: Site, n_users: int
):
    config = FamilyConfig()
    reach_m = config.crowd_radius_m + CELL_M * math.sqrt(0.5)  # a cell's centre, then inside it
    walkable = np.argwhere(site.walkable)
    centres = (walkable[:, ::-1] + 0.5) * CELL_M
    for s in generate_scenarios(25, n_users, seed=8, area=area, family="crowd"):
        check_scenario_area(s, area)
        gap = np.linalg.norm(centres[:, None, :] - s.users_xy_m[None, :, :], axis=-1)
        most = int((gap <= reach_m + 1e-9).sum(axis=1).max())
        assert most >= n_users // 2 + 1, (s.id, most)  # a strict majority at one point


def test_site_families_are_deterministic_per_seed_and_prefix_stable(area: AreaConfig):
    for family in SITE_FAMILIES:
        a = generate_scenarios(6, 10, seed=21, area=area, family=family)
        b = generate_scenarios(6, 10, seed=21, area=area, family=family)
        assert a == b
        assert generate_scenarios(3, 10, seed=21, area=area, family=family) == a[:3]
        other = generate_scenarios(6, 10, seed=22, area=area, family=family)
        assert any(
            not np.array_equal(x.users_xy_m, y.users_xy_m) for x, y in zip(a, other, strict=True)
        )


def test_the_sampler_draws_site_families_on_a_site(area: AreaConfig):
    sampler = ScenarioSampler(families=SITE_FAMILIES, users=(2, 20), area=area)
    rng = np.random.default_rng(3)
    labels = set()
    for _ in range(30):
        scenario = sampler.sample(rng)
        labels.add(scenario.id.split("-")[0])
        assert walkable_at(_site(_district()), scenario.users_xy_m).all()
    assert labels == set(SITE_FAMILIES)


def test_the_existing_families_are_unchanged():
    assert FAMILIES == ("exponential", "uniform", "hotspots", "corners", "mixture")
    assert not set(SITE_FAMILIES) & set(FamilyConfig().mixture_families)


# ------------------------------------------------------------------------------- refusals


@pytest.mark.parametrize("family", SITE_FAMILIES)
@pytest.mark.parametrize("environment", ["open", "urban"])
def test_off_a_site_the_site_families_are_refused_in_one_line(family: str, environment: str):
    area = AreaConfig(environment=environment)
    with pytest.raises(InputError) as exc:
        generate_scenarios(2, 5, seed=1, area=area, family=family)
    message = str(exc.value)
    assert message.startswith(f"family: {family!r} needs a site") and "\n" not in message
    assert environment in message
    with pytest.raises(InputError, match=r"^families: .* needs a site"):
        ScenarioSampler(families=("uniform", family), area=area)


def test_a_site_without_streets_or_squares_is_refused_naming_the_family(tmp_path: Path):
    field = tmp_path / "field"  # nothing stands anywhere: all open, no street
    save_site(_site(np.zeros((CELLS, CELLS), np.float32)), field)
    area = AreaConfig(environment=f"site:{field}")
    with pytest.raises(InputError, match=r"^family: 'streets': .* has no street"):
        generate_scenarios(1, 5, seed=1, area=area, family="streets")
    assert generate_scenarios(1, 5, seed=1, area=area, family="squares")  # one big square
    alleys = tmp_path / "alleys"  # only 10 m alleys: no open ground
    height = np.full((CELLS, CELLS), 10.0, np.float32)
    height[:, 10:12] = 0.0
    height[40:42, :] = 0.0
    save_site(_site(height), alleys)
    area = AreaConfig(environment=f"site:{alleys}")
    with pytest.raises(InputError, match=r"^family: 'squares': .* has no open walkable ground"):
        generate_scenarios(1, 5, seed=1, area=area, family="squares")
    for s in generate_scenarios(5, 5, seed=1, area=area, family="streets"):
        check_scenario_area(s, area)


# ------------------------------------------------------------------------ the command line


def test_generate_writes_a_site_family_on_a_site(area: AreaConfig, tmp_path: Path, capsys):
    out = tmp_path / "streets.json"
    argv = ["scenarios", "generate", "--n", "12", "--users", "6", "--family", "streets"]
    assert main([*argv, "--environment", area.environment, "--out", str(out)]) == 0
    assert json.loads(out.read_text())["generator"]["family"] == "streets"
    file_area, scenarios = load_scenarios(out)
    assert file_area.environment == area.environment and len(scenarios) == 12
    assert all(_in_streets(s.users_xy_m).all() for s in scenarios)
    assert "wrote 12 scenarios" in capsys.readouterr().out


@pytest.mark.parametrize("family", SITE_FAMILIES)
def test_generate_refuses_a_site_family_off_a_site_in_one_line(family: str, tmp_path: Path, capsys):
    out = tmp_path / "x.json"
    argv = ["scenarios", "generate", "--n", "2", "--family", family, "--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert f"--family: {family!r} needs a site" in err
    assert not out.exists()
