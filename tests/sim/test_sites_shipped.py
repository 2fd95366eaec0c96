"""The sites shipped in the package (``sim/sites/data/NAME``) and ``site:NAME``: each loads and
its hash checks, its grid covers the default area's flight volume, it carries the map data's
attribution and licence, it is package data, and ``site:munich`` works in the area, the
network model and the command lines; an unknown name is refused in one line (sim/config.py,
sim/channel.py, sim/sites/). No ray tracer needed."""

from __future__ import annotations

import json
import tomllib
from fnmatch import fnmatch
from pathlib import Path

import numpy as np
import pytest

from sim.channel import area_site
from sim.config import (
    SHIPPED_SITES_DIR,
    AreaConfig,
    NetworkConfig,
    check_environment,
    environment_problem,
    is_site_name,
    shipped_sites,
    site_directory,
)
from sim.errors import InputError
from sim.network import NetworkModel
from sim.scenarios import generate_scenarios
from sim.sites import load_site, path_loss_db, save_site
from sim.sites.format import DATA_FILE, META_FILE, content_hash
from sim.sites.ground import walkable_at
from sim.utility import network_utility

ROOT = Path(__file__).resolve().parents[2]
MUNICH = SHIPPED_SITES_DIR / "munich"


@pytest.fixture(scope="module")
def munich():
    return load_site(MUNICH)  # checks the shapes and the content hash


SHIPPED = ("munich", "etoile", "florence")
"""The sites the package ships (docs/sites.md): each is checked alike."""
MAX_SITE_BYTES = 25e6
"""The most one shipped site may take (quantised to 0.1 dB, compressed: docs/sites.md)."""


@pytest.fixture(scope="module", params=SHIPPED)
def shipped(request: pytest.FixtureRequest):
    return request.param, load_site(SHIPPED_SITES_DIR / request.param)  # shapes and hash checked


def test_every_shipped_site_is_listed_and_its_hash_checks(shipped) -> None:
    name, site = shipped
    assert set(SHIPPED) == set(shipped_sites())
    directory = SHIPPED_SITES_DIR / name
    meta = json.loads((directory / META_FILE).read_text())
    assert meta["format"] == "tupa-site/1"
    assert meta["content_sha256"] == content_hash(site)  # load_site checked it too
    size = sum((directory / file).stat().st_size for file in (DATA_FILE, META_FILE))
    assert size <= MAX_SITE_BYTES, f"the shipped site {name} is {size / 1e6:.1f} MB"
    assert site.meta["scene"]["name"] == name


def test_every_shipped_site_covers_the_default_area_and_flight_volume(shipped) -> None:
    name, site = shipped
    area = AreaConfig()
    assert (site.size_x_m, site.size_y_m, site.cell_m) == (500.0, 500.0, 5.0)
    assert site.uav_x_m[0] == site.uav_y_m[0] == 0.0
    assert site.uav_x_m[-1] == area.size_x_m and site.uav_y_m[-1] == area.size_y_m
    assert site.uav_z_m[0] <= area.z_min_m == 25.0 and site.uav_z_m[-1] >= area.z_max_m
    assert np.diff(site.uav_x_m).max() <= 25.0 and np.diff(site.uav_z_m).max() <= 12.5
    assert area_site(AreaConfig(environment=f"site:{name}")) is not None  # the area's checks
    # Buildings and streets: some ground is walkable, not all of it.
    assert 0.1 < site.walkable.mean() < 0.9 and site.building_height_m.max() > 20


def test_every_shipped_site_carries_the_map_datas_attribution_and_licence(shipped) -> None:
    name, site = shipped
    scene = site.meta["scene"]
    assert "OpenStreetMap" in scene["attribution"] and scene["licence"].startswith("ODbL")
    notice = (SHIPPED_SITES_DIR / "README.md").read_text()
    assert "OpenStreetMap" in notice and "ODbL" in notice and f"`{name}`" in notice
    assert "build" in site.meta and site.meta["build"]["command"].startswith(
        f"tupa site build --scene {name}"
    )


def test_the_shipped_site_is_package_data() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    globs = config["tool"]["setuptools"]["package-data"]["sim"]
    for path in [*MUNICH.iterdir(), SHIPPED_SITES_DIR / "README.md"]:
        relative = path.relative_to(ROOT / "sim").as_posix()
        assert any(fnmatch(relative, pattern) for pattern in globs), relative


def test_site_munich_runs_in_the_network_model(munich) -> None:
    area = AreaConfig(environment="site:munich")
    model = NetworkModel(NetworkConfig(), area)
    assert model.site is not None and content_hash(model.site) == content_hash(munich)
    scenario = generate_scenarios(1, 5, seed=3, area=area)[0]
    assert walkable_at(munich, scenario.users_xy_m).all()
    uav = np.array([[250.0, 250.0, 75.0], [120.0, 380.0, 60.0]])
    for rng in (None, np.random.default_rng(1)):
        result = model.step(uav, scenario.users_xy_m, scenario.load_bps, rng=rng)
        utility = network_utility(
            result.throughput_bps, result.delay_s, result.plr, scenario.load_bps
        )
        assert np.isfinite(utility).all()
    # Mostly within reach from 75 m over the middle of the district.
    loss = path_loss_db(munich, uav[0], scenario.users_xy_m)
    assert np.isfinite(loss).any()


def test_an_unknown_shipped_name_is_refused_in_one_line() -> None:
    with pytest.raises(InputError) as info:
        AreaConfig(environment="site:paris")
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("environment: 'site:paris': no shipped site 'paris' (shipped: ")
    assert "munich" in message and "site:./paris" in message
    with pytest.raises(InputError, match=r"^--environment: 'site:paris': no shipped site"):
        check_environment("site:paris", "--environment", on_disk=True)
    assert environment_problem("site:munich", on_disk=True) is None


def test_a_path_with_a_separator_is_still_a_directory(tmp_path: Path, munich) -> None:
    assert is_site_name("munich") and not is_site_name("./munich")
    assert not is_site_name("sites/munich") and not is_site_name("~") and not is_site_name("..")
    assert site_directory("site:munich") == MUNICH
    assert site_directory("site:./munich") == Path("munich")
    assert site_directory("urban") is None
    save_site(munich, tmp_path / "copy")
    area = AreaConfig(environment=f"site:{tmp_path / 'copy'}")
    copy = area_site(area)
    assert copy is not None and content_hash(copy) == content_hash(munich)


def test_the_command_line_takes_site_munich(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    from service.cli import main
    from sim.files import load_scenarios

    out = tmp_path / "s.json"
    argv = ["scenarios", "generate", "--n", "2", "--users", "4", "--out", str(out)]
    assert main([*argv, "--environment", "site:munich"]) == 0
    area, scenarios = load_scenarios(out)
    assert area.environment == "site:munich" and len(scenarios) == 2
    capsys.readouterr()
    assert main([*argv, "--environment", "site:nowhere"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert err.startswith(
        "tupa scenarios: error: --environment: 'site:nowhere': no shipped site 'nowhere'"
    )
