"""A site as the channel environment (``site:PATH``): the area's syntax, loading and coverage
checks, line of sight over the height map, Rician/Rayleigh fading by it (sim/channel.py,
sim/config.py, sim/sites/los.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sim.channel import air_to_ground, area_site, site_link_channel
from sim.config import AreaConfig, site_path
from sim.errors import InputError
from sim.sites import Site, save_site
from sim.sites.format import quantise_loss_db
from sim.sites.los import line_of_sight


def _site(size_m: float = 100.0, z_m: tuple[float, ...] = (25.0, 100.0)) -> Site:
    """A ``size_m`` square of 5 m cells, one 30 m block on x ∈ [40, 60], y ∈ [0, size];
    UAV grid every 50 m; loss 90 dB everywhere except no path from (0, 0, lowest)."""
    cells = round(size_m / 5)
    xs = np.linspace(0.0, size_m, round(size_m / 50) + 1)
    zs = np.asarray(z_m)
    height = np.zeros((cells, cells), np.float32)
    height[:, 8:12] = 30.0
    loss = np.full((zs.size, xs.size, xs.size, cells, cells), 90.0)
    loss[0, 0, 0] = np.inf
    return Site(
        size_x_m=size_m,
        size_y_m=size_m,
        cell_m=5.0,
        user_height_m=1.5,
        uav_x_m=xs,
        uav_y_m=xs.copy(),
        uav_z_m=zs,
        loss_code=quantise_loss_db(loss),
        building_height_m=height,
        walkable=height == 0,
        meta={},
    )


def test_the_area_takes_site_path_and_refuses_an_empty_one() -> None:
    area = AreaConfig(size_x_m=100, size_y_m=100, environment="site:/x/y")
    assert site_path(area.environment) == "/x/y" and site_path("urban") is None
    with pytest.raises(InputError, match=r"^environment: 'site:' needs the site directory"):
        AreaConfig(environment="site:")
    with pytest.raises(InputError, match=r"^environment: must be one of .* or site:PATH"):
        AreaConfig(environment="sight:/x")


def test_area_site_loads_checks_and_caches(tmp_path: Path) -> None:
    save_site(_site(), tmp_path / "s")
    area = AreaConfig(size_x_m=100, size_y_m=100, environment=f"site:{tmp_path / 's'}")
    site = area_site(area)
    assert site is not None and site.size_x_m == 100
    assert area_site(area) is site
    assert area_site(AreaConfig()) is None
    with pytest.raises(InputError, match=r"^environment: 'site:.*' is a site"):
        air_to_ground(area.environment)


def test_a_missing_or_broken_site_is_refused_naming_the_environment(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"^environment: 'site:.*nothing': no site there"):
        area_site(AreaConfig(environment=f"site:{tmp_path / 'nothing'}"))
    save_site(_site(), tmp_path / "s")
    (tmp_path / "s" / "site.json").write_text('{"format": "tupa-site/1"}')
    with pytest.raises(InputError, match=r"^environment: 'site:.*': .*size_x_m: must be a number"):
        area_site(AreaConfig(size_x_m=100, size_y_m=100, environment=f"site:{tmp_path / 's'}"))


def test_a_site_smaller_than_the_area_is_refused(tmp_path: Path) -> None:
    save_site(_site(), tmp_path / "s")
    with pytest.raises(InputError, match=r"smaller than the area \(size_x_m 100 m < 500 m"):
        area_site(AreaConfig(environment=f"site:{tmp_path / 's'}"))
    save_site(_site(z_m=(25.0, 50.0)), tmp_path / "low")
    with pytest.raises(InputError, match=r"uav_z_m 50 m < 100 m"):
        area_site(AreaConfig(size_x_m=100, size_y_m=100, environment=f"site:{tmp_path / 'low'}"))


def test_line_of_sight_over_the_height_map() -> None:
    site = _site()
    users = np.array([[20.0, 50.0], [80.0, 50.0], [42.0, 50.0]])
    # Low on the west side: the east user is behind the 30 m block; the user in the block's
    # westernmost cell (its own cell skipped) sees the UAV, as the ray leaves westwards.
    assert line_of_sight(site, [10.0, 50.0, 25.0], users).tolist() == [True, False, True]
    # High overhead the block: every link is clear.
    assert line_of_sight(site, [50.0, 50.0, 100.0], users).all()
    # A batch of positions: (N, M).
    both = line_of_sight(site, np.array([[10.0, 50.0, 25.0], [50.0, 50.0, 100.0]]), users)
    assert both.shape == (2, 3) and both[0, 1] == np.False_ and both[1].all()


def test_fading_is_rician_in_line_of_sight_and_rayleigh_behind_buildings() -> None:
    site = _site()
    users = np.array([[20.0, 50.0], [80.0, 50.0]])  # clear, blocked from (10, 50, 25)
    loss, gains = site_link_channel(
        site, [10.0, 50.0, 25.0], users, 13.0, np.random.default_rng(0), 20_000
    )
    assert loss.shape == (1, 2) and np.allclose(loss, 90.0)
    assert gains is not None and gains.shape == (1, 2, 20_000)
    clear, blocked = gains[0]
    assert clear.mean() == pytest.approx(1.0, abs=0.02) and blocked.mean() == pytest.approx(
        1.0, abs=0.03
    )
    # Rician K = 13 dB: variance (2K + 1) / (K + 1)² ≈ 0.09; Rayleigh (exponential): 1.
    assert clear.var() == pytest.approx(0.0914, rel=0.1) and blocked.var() == pytest.approx(
        1.0, rel=0.1
    )


def test_expected_mode_and_no_path() -> None:
    site = _site()
    loss, gains = site_link_channel(site, np.array([[0.0, 0.0, 25.0]]), [[5, 5]], 13.0, None, 4)
    assert gains is None and np.isinf(loss[0, 0])
