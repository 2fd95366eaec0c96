"""Channel environments: the air-to-ground model (Al-Hourani et al. 2014) and everything that
takes the environment (model, files, worlds, baselines, settings)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sim.channel import (
    draw_link_channel,
    friis_path_loss_db,
    los_probability,
    mean_path_loss_db,
    optimal_elevation_deg,
)
from sim.config import ENVIRONMENTS, AreaConfig, UtilityConfig
from sim.errors import InputError
from sim.files import load_scenarios, save_scenarios
from sim.network import NetworkModel
from sim.scenarios import Scenario, generate_scenarios
from sim.utility import network_utility
from sim.world import PAPER, get_world, world_with

URBAN = ENVIRONMENTS[1:]
# The optimal elevation angles Al-Hourani et al. report (their Table II, at 2 GHz), degrees.
PUBLISHED_OPTIMAL_DEG = {
    "suburban": 20.34,
    "urban": 42.44,
    "dense-urban": 54.62,
    "highrise-urban": 75.52,
}


@pytest.mark.parametrize("environment", URBAN)
def test_the_optimal_elevation_is_the_published_one(environment: str) -> None:
    assert optimal_elevation_deg(environment, 2e9) == pytest.approx(
        PUBLISHED_OPTIMAL_DEG[environment], abs=0.01
    )


@pytest.mark.parametrize("environment", URBAN)
@pytest.mark.parametrize("max_loss_db", [100.0, 110.0])
def test_mean_path_loss_gives_the_widest_coverage_at_that_angle(
    environment: str, max_loss_db: float
) -> None:
    """For a fixed largest tolerable path loss, the altitude whose coverage radius (the ground
    distance where the mean loss reaches it) is widest sees its edge at the optimal angle."""
    ground_m = np.linspace(1.0, 5000.0, 50_000)
    best_radius, best_angle = 0.0, 0.0
    for height_m in np.arange(10.0, 3000.0, 5.0):
        loss = mean_path_loss_db(environment, ground_m, height_m, 2e9)
        inside = np.flatnonzero(loss <= max_loss_db)
        if len(inside) and inside[-1] == len(ground_m) - 1:
            pytest.fail("coverage beyond the grid: widen it")
        # The radius: the farthest ground distance still covered from this altitude.
        radius = ground_m[inside[-1]] if len(inside) else 0.0
        if radius > best_radius:
            best_radius, best_angle = radius, math.degrees(math.atan2(height_m, radius))
    assert best_radius > 0
    assert best_angle == pytest.approx(optimal_elevation_deg(environment, 2e9), abs=0.6)


def test_mean_path_loss_between_the_los_and_nlos_losses() -> None:
    ground = np.array([0.0, 50.0, 200.0, 800.0])
    free = friis_path_loss_db(np.hypot(ground, 50.0), 5.18e9)
    assert np.array_equal(mean_path_loss_db("open", ground, 50.0, 5.18e9), free)
    for environment in URBAN:
        excess = mean_path_loss_db(environment, ground, 50.0, 5.18e9) - free
        assert np.all(np.diff(excess) > 0)  # lower elevation: less line of sight, more loss
        p = los_probability(environment, np.degrees(np.arctan2(50.0, ground)))
        assert np.all((p > 0) & (p < 1))


@pytest.mark.parametrize(
    ("args", "field"),
    [
        (("mars", 10.0, 10.0, 2e9), "environment"),
        (("urban", 10.0, 10.0, 0.5e9), "frequency_hz"),
        (("urban", 10.0, 10.0, 8e9), "frequency_hz"),
        (("urban", 10.0, -1.0, 2e9), "height_m"),
        (("urban", np.array([1.0, np.nan]), 10.0, 2e9), "ground_distance_m"),
    ],
)
def test_bad_arguments_are_named(args: tuple, field: str) -> None:
    with pytest.raises(InputError, match=rf"^{field}: "):
        mean_path_loss_db(*args)


def test_drawn_link_states_and_fading() -> None:
    rng = np.random.default_rng(5)
    p = np.array([[0.2, 0.5, 0.9]])
    states, gains = [], []
    for _ in range(4000):
        los, gain = draw_link_channel(rng, p, 13.0, 8)
        states.append(los[0])
        gains.append(gain[0])
    states, gains = np.array(states), np.array(gains)  # (n, 3), (n, 3, 8)
    np.testing.assert_allclose(states.mean(axis=0), p[0], atol=0.03)
    los_gains = gains[states].ravel()
    nlos_gains = gains[~states].ravel()
    assert los_gains.mean() == pytest.approx(1.0, abs=0.02)
    assert nlos_gains.mean() == pytest.approx(1.0, abs=0.02)
    assert nlos_gains.var() == pytest.approx(1.0, abs=0.05)  # Rayleigh: exponential power
    assert los_gains.var() < 0.2  # Rician K = 13 dB: shallow fades


def _utility_by_altitude(environment: str, scenario: Scenario) -> np.ndarray:
    model = NetworkModel(area=AreaConfig(environment=environment))
    xy = np.average(scenario.users_xy_m, axis=0, weights=scenario.load_bps)
    positions = np.array([[xy[0], xy[1], z] for z in np.arange(25.0, 101.0, 5.0)])
    state = None
    for _ in range(10):
        result = model.step(positions, scenario.users_xy_m, scenario.load_bps, state)
        state = result.state
    return network_utility(
        result.throughput_bps, result.delay_s, result.plr, scenario.load_bps, UtilityConfig()
    )


def test_altitude_matters_in_towns_and_not_in_the_open() -> None:
    spread = Scenario(
        "spread",
        np.array([[100.0, 100.0], [400.0, 120.0], [250.0, 420.0]]),
        np.array([20e6, 12e6, 8e6]),
    )
    open_field = _utility_by_altitude("open", spread)
    assert np.ptp(open_field) < 0.01  # under free space altitude hardly matters
    town = _utility_by_altitude("urban", spread)
    assert np.argmax(town) > 0 and town.max() > town[0] + 0.05
    assert _utility_by_altitude("highrise-urban", spread).max() < town.max()


def test_stochastic_urban_steps_draw_and_stay_in_range() -> None:
    model = NetworkModel(area=AreaConfig(environment="dense-urban"))
    scenario = generate_scenarios(1, 6, seed=2)[0]
    rng = np.random.default_rng(0)
    state = None
    for _ in range(20):
        result = model.step(
            np.array([[250.0, 250.0, 60.0]]), scenario.users_xy_m, scenario.load_bps, state, rng
        )
        state = result.state
        assert np.all((result.plr >= 0) & (result.plr <= 1))
        assert np.all(result.throughput_bps <= scenario.load_bps * 1.01 + 1)


def test_the_urban_model_refuses_a_frequency_it_does_not_cover() -> None:
    from sim.config import NetworkConfig, RadioConfig

    config = replace(NetworkConfig(), radio=replace(RadioConfig(), frequency_hz=28e9))
    NetworkModel(config)  # free space: any frequency
    with pytest.raises(InputError, match=r"^frequency_hz: "):
        NetworkModel(config, AreaConfig(environment="urban"))


def test_files_carry_the_environment(tmp_path: Path) -> None:
    scenarios = generate_scenarios(2, 3, seed=1)
    plain, town = tmp_path / "plain.json", tmp_path / "town.json"
    save_scenarios(plain, AreaConfig(), scenarios)
    save_scenarios(town, AreaConfig(environment="urban"), scenarios)
    assert "environment" not in json.loads(plain.read_text())  # the paper's files unchanged
    assert json.loads(town.read_text())["environment"] == "urban"
    assert load_scenarios(town)[0].environment == "urban"
    assert load_scenarios(plain)[0].environment == "open"
    bad = json.loads(town.read_text())
    bad["environment"] = "moon"
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match=r"bad.json: environment: must be one of"):
        load_scenarios(tmp_path / "bad.json")


def test_worlds_take_the_environment() -> None:
    world = world_with(get_world("closed-loop"), ["environment=dense-urban"])
    assert world.environment == "dense-urban" and world.area.environment == "dense-urban"
    assert PAPER.environment == "open"
    with pytest.raises(InputError, match=r"^world\.environment: must be one of"):
        world_with(PAPER, ["environment=swamp"])


def test_environment_aware_min_distance_climbs_only_in_towns() -> None:
    from policies.registry import make_placement

    scenario = Scenario(
        "s", np.array([[100.0, 100.0], [400.0, 120.0], [250.0, 420.0]]), np.ones(3) * 1e6
    )
    plain = make_placement("min-distance").place(scenario)
    assert np.array_equal(make_placement("min-distance-env").place(scenario), plain)
    for environment in URBAN:
        world = replace(PAPER, area=AreaConfig(environment=environment))
        placed = make_placement("min-distance-env", world).place(scenario)
        np.testing.assert_array_equal(placed[:2], plain[:2])
        heights = np.arange(25.0, 101.0, 1.0)
        ground = np.hypot(*(scenario.users_xy_m - placed[:2]).T)
        losses = [mean_path_loss_db(environment, ground, h - 1.5, 5.18e9).mean() for h in heights]
        assert placed[2] == heights[int(np.argmin(losses))]
        assert placed[2] > 25.0


def test_the_service_refuses_an_unknown_environment() -> None:
    import argparse

    from api.cli import register, settings_from_args

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    base = ["serve", "--policy", "min-distance"]
    settings = settings_from_args(parser.parse_args([*base, "--environment", "urban"]))
    assert settings.policy_world().environment == "urban"
    with pytest.raises(InputError, match=r"^environment: .*must be one of"):
        settings_from_args(parser.parse_args([*base, "--environment", "mars"]))
