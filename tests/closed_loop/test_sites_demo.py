"""``tupa demo`` and ``tupa controller-sim`` over a site (issue 38 items 2 and 6): ``--environment``
takes ``site:PATH`` through the one environment check (one-line errors naming the option,
before anything starts), the demo's users stand on walkable ground, and its track figures draw
the site's buildings as footprints shaded by height under the tracks (closed_loop/cli.py,
closed_loop/demo.py, closed_loop/fleet_demo.py)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pytest

import closed_loop.demo as demo
import closed_loop.fleet_demo as fleet_demo
from service.cli import main
from sim.config import AreaConfig
from sim.sites import Site, save_site
from sim.sites.ground import walkable_at

CELLS = 100  # 500 m of 5 m cells: the demo's area


def _site(size_m: float = 500.0) -> Site:
    """Four blocks of 10, 20, 35 and 60 m around the centre, the rest open ground."""
    cells = round(size_m / 5.0)
    height = np.zeros((cells, cells), np.float32)
    for (rows, columns), top in zip(
        [((10, 40), (10, 40)), ((10, 40), (60, 90)), ((60, 90), (10, 40)), ((60, 90), (60, 90))],
        [10.0, 20.0, 35.0, 60.0],
        strict=True,
    ):
        height[slice(*rows), slice(*columns)] = top
    xs, zs = np.linspace(0.0, size_m, 3), np.array([25.0, 100.0])
    return Site(
        size_x_m=size_m,
        size_y_m=size_m,
        cell_m=5.0,
        user_height_m=1.5,
        uav_x_m=xs,
        uav_y_m=xs.copy(),
        uav_z_m=zs,
        loss_code=np.full((zs.size, xs.size, xs.size, cells, cells), 1000, np.uint16),
        building_height_m=height,
        walkable=height == 0,
        meta={},
    )


@pytest.fixture(scope="module")
def site_env(tmp_path_factory: pytest.TempPathFactory) -> str:
    directory = tmp_path_factory.mktemp("sites") / "blocks"
    save_site(_site(), directory)
    return f"site:{directory}"


@pytest.fixture
def flown(monkeypatch) -> list:
    """The configs run_demo and run_fleet_demo got (nothing is flown)."""
    configs: list = []
    monkeypatch.setattr(demo, "run_demo", lambda cfg: configs.append(cfg) or {})
    monkeypatch.setattr(fleet_demo, "run_fleet_demo", lambda cfg: configs.append(cfg) or {})
    return configs


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


# ------------------------------------------------------------------------ the command lines


def test_the_demo_flies_over_a_site(flown, site_env: str, tmp_path: Path):
    assert main(["demo", "--environment", site_env, "--out", str(tmp_path)]) == 0
    (cfg,) = flown
    assert cfg.environment == site_env
    area, scenarios = demo.demo_scenarios(cfg)
    assert area.environment == site_env and len(scenarios) == 3
    site = _site()
    for scenario in scenarios:
        assert walkable_at(site, scenario.users_xy_m).all()
    assert main(["demo", "--uavs", "2", "--environment", site_env, "--out", str(tmp_path)]) == 0
    assert flown[-1].environment == site_env


@pytest.mark.parametrize(
    ("command", "message"),
    [
        (["demo"], "--environment: 'site:/nowhere/at/all': no site there"),
        (["demo", "--uavs", "3"], "--environment: 'site:/nowhere/at/all': no site there"),
        (["controller-sim"], "--environment: 'site:/nowhere/at/all': no site there"),
        (
            ["controller-sim", "--fleet-file", "/nowhere/fleet.yaml"],
            "--environment: 'site:/nowhere/at/all': no site there",
        ),
    ],
)
def test_a_missing_site_is_one_line_naming_the_option(capsys, flown, command, message):
    argv = [*command, "--environment", "site:/nowhere/at/all"]
    assert main(argv) == 2
    err = _one_line(capsys)
    assert err.startswith(f"tupa {command[0]}: error: {message}"), err
    assert flown == []


@pytest.mark.parametrize("command", [["demo"], ["controller-sim"]])
def test_an_unknown_environment_and_a_small_site_are_one_line(
    capsys, flown, command, tmp_path: Path
):
    assert main([*command, "--environment", "moon"]) == 2
    assert "--environment: must be one of open, suburban" in _one_line(capsys)
    assert main([*command, "--environment", "site:"]) == 2
    assert "--environment: 'site:' needs the site directory's path" in _one_line(capsys)
    small = tmp_path / "small"
    save_site(_site(200.0), small)
    assert main([*command, "--environment", f"site:{small}"]) == 2
    err = _one_line(capsys)
    assert err.startswith(f"tupa {command[0]}: error: --environment: ") and "smaller" in err
    assert flown == []


def test_help_says_the_environment_takes_a_site(capsys):
    for command in ("demo", "controller-sim"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert "site:PATH" in capsys.readouterr().out


# --------------------------------------------------------------------------- the figures


def test_buildings_are_drawn_as_footprints_shaded_by_height(site_env: str):
    fig, ax = plt.subplots()
    try:
        image = demo.draw_buildings(ax, AreaConfig(environment=site_env))
        assert image is not None and image.get_zorder() < 1
        heights = _site().building_height_m
        data = image.get_array()
        assert np.array_equal(data.mask, heights == 0)  # open ground is left blank
        assert np.array_equal(data.data[~data.mask], heights[heights > 0])
        assert image.get_extent() == [0.0, 500.0, 0.0, 500.0]
        assert image.get_clim() == (0.0, 60.0)
        shade = [np.mean(image.cmap(image.norm(h))[:3]) for h in (10.0, 20.0, 35.0, 60.0)]
        assert shade == sorted(shade, reverse=True)  # darker is taller
        assert shade[0] < 0.9 and shade[-1] < 0.05  # the lowest roof shaded, the tallest black
        assert any(a.get_ylabel() == "building height (m)" for a in fig.axes)
    finally:
        plt.close(fig)
    fig, ax = plt.subplots()
    try:
        assert demo.draw_buildings(ax, AreaConfig()) is None
        assert ax.get_images() == []
    finally:
        plt.close(fig)


def _result(scenario_xy: np.ndarray) -> dict:
    track = [
        {"position_m": [250.0 + 5 * t, 250.0, 25.0], "users_xy_m": scenario_xy.tolist()}
        for t in range(5)
    ]
    return {
        "world": "closed-loop",
        "heterogeneity": 0.4,
        "users_xy_m": scenario_xy.tolist(),
        "load_bps": [10e6, 20e6, 10e6],
        "achieved": 0.8,
        "min-distance": 0.7,
        "oracle": 0.85,
        "min-distance_target_m": [240.0, 250.0, 25.0],
        "oracle_target_m": [260.0, 240.0, 40.0],
        "track": track,
    }


def test_the_demo_track_figure_draws_the_site_under_the_track(
    site_env: str, tmp_path: Path, monkeypatch
):
    drawn: list = []
    original = demo.draw_buildings
    monkeypatch.setattr(demo, "draw_buildings", lambda ax, area: drawn.append(original(ax, area)))
    xy = np.array([[230.0, 250.0], [250.0, 120.0], [470.0, 260.0]])
    path = tmp_path / "track.png"
    area = AreaConfig(environment=site_env)
    demo.plot_tracks([_result(xy), _result(xy)], area, path, "oracle")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(drawn) == 2 and all(image is not None for image in drawn)
    demo.plot_tracks([_result(xy)], AreaConfig(), path, "oracle")  # open field: nothing drawn
    assert drawn[-1] is None


def test_the_demo_utility_figure_draws_every_loop_of_every_scenario(tmp_path: Path, monkeypatch):
    drawn: dict[str, list[float]] = {}
    import matplotlib.axes

    original = matplotlib.axes.Axes.plot

    def plot(ax, x, y, *args, label=None, **kwargs):
        drawn[label] = list(y)
        return original(ax, x, y, *args, label=label, **kwargs)

    monkeypatch.setattr(matplotlib.axes.Axes, "plot", plot)
    loops = {"planning-oracle": [0.0, 0.5, 0.7], "min-distance": [0.0, 0.2, 0.3]}
    row = {"world": "closed-loop", "heterogeneity": 0.3, "loop_utilities": loops}
    path = tmp_path / "utility.png"
    demo.plot_utilities([row, row], path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert drawn == {
        "planning-oracle (0.600)": [0.0, 0.5, 0.7],
        "min-distance (0.250)": [0.0, 0.2, 0.3],
    }


def test_the_fleet_demo_stands_its_users_on_walkable_ground_and_draws_the_site(
    site_env: str, tmp_path: Path, monkeypatch
):
    area = AreaConfig(environment=site_env)
    layout = fleet_demo.hot_spot_layout(2, 7, area, users_per_spot=8)
    again = fleet_demo.hot_spot_layout(2, 7, area, users_per_spot=8)
    assert np.array_equal(layout.users_xy_m, again.users_xy_m)
    site = _site()
    assert walkable_at(site, layout.users_xy_m).all()
    field = fleet_demo.hot_spot_layout(2, 7, AreaConfig(), users_per_spot=8)
    assert np.array_equal(field.centres_m, layout.centres_m)
    # The first hot spot's users already on walkable ground keep the open field's positions.
    first = slice(0, 8)
    kept = walkable_at(site, field.users_xy_m[first])
    assert np.array_equal(layout.users_xy_m[first][kept], field.users_xy_m[first][kept])
    assert not walkable_at(site, field.users_xy_m).all()  # the site did move someone

    drawn: list = []
    original = fleet_demo.draw_buildings
    monkeypatch.setattr(
        fleet_demo, "draw_buildings", lambda ax, area: drawn.append(original(ax, area))
    )
    steps = [
        {
            "users_xy_m": layout.users_xy_m.tolist(),
            "association": [u % 2 for u in range(len(layout.load_bps))],
            "load_bps": layout.load_bps.tolist(),
            "positions_m": {"uav1": [200.0 + t, 250.0, 30.0], "uav2": [300.0, 250.0 - t, 30.0]},
            "targets_m": {"uav1": [210.0, 250.0, 30.0], "uav2": [300.0, 240.0, 30.0]},
        }
        for t in range(4)
    ]
    metrics = {"utility": 0.7, "served_fraction": 0.9, "jain_fairness": 0.8, "handovers": 1}
    summary = {
        "policies": {"kmeans-scored": {"steps": steps, "metrics": metrics}},
        "hot_spots": {
            "centres_m": layout.centres_m.tolist(),
            "spread_m": layout.spread_m,
            "moving": layout.moving_spot,
        },
        "users": {"spot": layout.spot.tolist()},
    }
    path = tmp_path / "fleet-track.png"
    fleet_demo.plot_fleet_tracks(summary, area, path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(drawn) == 1 and drawn[0] is not None
