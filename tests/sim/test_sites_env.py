"""A site (``site:PATH``) everywhere an environment goes: the network model (per-link loss at
the UAV's exact position, fading by line of sight, no path = out of coverage), the batched
and fleet models, the Gymnasium, vector and fleet environments, users on walkable ground (the
generator, moving users, scenario files), and the one-line refusals of the command lines
(sim/network.py, sim/fleet.py, sim/scenarios.py, sim/users.py, sim/files.py, sim/config.py,
sim/sites/ground.py)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from sim.channel import NO_LINK_LOSS_DB, friis_path_loss_db
from sim.config import AreaConfig, NetworkConfig, check_environment, environment_problem
from sim.envs import CONTINUOUS_ENV_ID, DISCRETE_ENV_ID
from sim.errors import InputError
from sim.files import load_cases, load_scenarios, save_scenarios
from sim.fleet import FleetConfig, FleetModel
from sim.network import NetworkModel
from sim.scenarios import FAMILIES, Scenario, ScenarioSampler, generate_scenarios
from sim.sites import Site, path_loss_db, save_site
from sim.sites.format import quantise_loss_db
from sim.sites.ground import nearest_walkable_xy, walkable_at, walkable_path
from sim.sites.los import line_of_sight
from sim.users import UserDynamics
from sim.utility import network_utility
from sim.world import PAPER, Demand, Mobility

SIZE_M = 200.0
BLOCK_X_M = (80.0, 120.0)  # a 40 m tall block in the middle of the site
BLOCK_Y_M = (60.0, 140.0)
BLOCK_HEIGHT_M = 40.0
NLOS_EXCESS_DB = 25.0
WEST_UAV = (25.0, 100.0, 25.0)  # low on the west side: the east is in the block's shadow
WEST_USER = (30.0, 100.0)
EAST_USER = (160.0, 100.0)


def _blank_site(size_m: float, height: np.ndarray, xs: np.ndarray, zs: np.ndarray) -> Site:
    cells = height.shape[0]
    return Site(
        size_x_m=size_m,
        size_y_m=size_m,
        cell_m=5.0,
        user_height_m=1.5,
        uav_x_m=xs,
        uav_y_m=xs.copy(),
        uav_z_m=zs,
        loss_code=np.zeros((zs.size, xs.size, xs.size, cells, cells), np.uint16),
        building_height_m=height,
        walkable=height == 0,
        meta={},
    )


def _block_site() -> Site:
    """200 m × 200 m of 5 m cells with one block (BLOCK_*); UAV grid every 50 m at 25-100 m.
    Loss: free space, plus NLOS_EXCESS_DB where the block is in the way; no path into the block,
    nor from the lowest grid points west of it (x ≤ 50 m) to the ground east of it (x > 120 m)."""
    cells = round(SIZE_M / 5)
    height = np.zeros((cells, cells), np.float32)
    rows = slice(round(BLOCK_Y_M[0] / 5), round(BLOCK_Y_M[1] / 5))
    columns = slice(round(BLOCK_X_M[0] / 5), round(BLOCK_X_M[1] / 5))
    height[rows, columns] = BLOCK_HEIGHT_M
    xs = np.linspace(0.0, SIZE_M, 5)
    zs = np.array([25.0, 50.0, 75.0, 100.0])
    plain = _blank_site(SIZE_M, height, xs, zs)
    centres = (np.arange(cells) + 0.5) * 5.0
    cx, cy = np.meshgrid(centres, centres)  # [row j, column i]
    ground = np.stack([cx.ravel(), cy.ravel()], axis=1)
    loss = np.empty((zs.size, xs.size, xs.size, cells, cells))
    for iz, z in enumerate(zs):
        for iy, y in enumerate(xs):
            for ix, x in enumerate(xs):
                d = np.sqrt((ground[:, 0] - x) ** 2 + (ground[:, 1] - y) ** 2 + (z - 1.5) ** 2)
                value = friis_path_loss_db(d, 5.18e9)
                value = value + np.where(
                    line_of_sight(plain, [x, y, z], ground), 0.0, NLOS_EXCESS_DB
                )
                loss[iz, iy, ix] = value.reshape(cells, cells)
    loss[:, :, :, height > 0] = np.inf
    loss[0, :, :2, :, round(BLOCK_X_M[1] / 5) :] = np.inf
    return replace(plain, loss_code=quantise_loss_db(loss))


@pytest.fixture(scope="module")
def site_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("sites") / "block"
    save_site(_block_site(), directory)
    return directory


@pytest.fixture(scope="module")
def big_site_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """500 m × 500 m (the default area's size, what the command lines use), one 25 m block on
    x ∈ [100, 400], y ∈ [200, 300]; every loss 100 dB (the lookup is not what it is for)."""
    height = np.zeros((100, 100), np.float32)
    height[40:60, 20:80] = 25.0
    xs, zs = np.linspace(0.0, 500.0, 3), np.array([25.0, 100.0])
    big = _blank_site(500.0, height, xs, zs)
    big = replace(big, loss_code=np.full(big.loss_code.shape, 1000, np.uint16))
    directory = tmp_path_factory.mktemp("sites") / "big"
    save_site(big, directory)
    return directory


@pytest.fixture(scope="module")
def area(site_dir: Path) -> AreaConfig:
    return AreaConfig(size_x_m=SIZE_M, size_y_m=SIZE_M, environment=f"site:{site_dir}")


@pytest.fixture(scope="module")
def site(area: AreaConfig) -> Site:
    model = NetworkModel(NetworkConfig(), area)
    assert model.site is not None
    return model.site


def _in_block(xy: np.ndarray) -> np.ndarray:
    xy = np.asarray(xy).reshape(-1, 2)
    return (
        (xy[:, 0] >= BLOCK_X_M[0])
        & (xy[:, 0] < BLOCK_X_M[1])
        & (xy[:, 1] >= BLOCK_Y_M[0])
        & (xy[:, 1] < BLOCK_Y_M[1])
    )


# ------------------------------------------------------------------------- the network model


def test_a_step_on_a_site_gives_finite_metrics_and_utility(area: AreaConfig) -> None:
    model = NetworkModel(NetworkConfig(), area)
    users = np.array([[30.0, 30.0], [170.0, 170.0], [60.0, 180.0]])
    load = np.array([10e6, 20e6, 10e6])
    uav = np.array([[100.0, 30.0, 50.0], [37.5, 112.5, 62.5], [180.0, 180.0, 100.0]])
    for rng in (None, np.random.default_rng(3)):
        result = model.step(uav, users, load, rng=rng)
        for array in (result.throughput_bps, result.delay_s, result.plr, result.snr_db):
            assert array.shape == (3, 3) and np.isfinite(array).all()
        utility = network_utility(result.throughput_bps, result.delay_s, result.plr, load)
        assert np.isfinite(utility).all() and (utility > 0).all()


def test_the_model_uses_the_sites_loss_at_the_exact_position(area: AreaConfig, site: Site) -> None:
    model = NetworkModel(NetworkConfig(), area)
    radio = model.config.radio
    users = np.array([[30.0, 30.0], [170.0, 50.0]])
    uav = np.array([[37.5, 112.5, 62.5], [140.0, 20.0, 30.0]])  # off the grid
    result = model.step(uav, users, np.array([5e6, 5e6]))
    loss = path_loss_db(site, uav, users)
    assert np.allclose(result.snr_db, radio.tx_power_dbm - loss - radio.noise_dbm, atol=1e-9)
    # Not the open field's Friis: the site's loss is what the SNR follows.
    open_result = NetworkModel(NetworkConfig(), replace(area, environment="open")).step(
        uav, users, np.array([5e6, 5e6])
    )
    assert not np.allclose(result.snr_db, open_result.snr_db)


def test_a_user_with_no_path_is_out_of_coverage_and_gets_nothing(
    area: AreaConfig, site: Site
) -> None:
    model = NetworkModel(NetworkConfig(), area)
    users = np.array([WEST_USER, EAST_USER])
    assert np.isinf(path_loss_db(site, WEST_UAV, users)[1])
    load = np.array([10e6, 10e6])
    for rng in (None, np.random.default_rng(0)):
        state = None
        for _ in range(3):
            result = model.step(np.array([WEST_UAV]), users, load, state, rng)
            state = result.state
            assert result.connected[0].tolist() == [True, False]
            assert result.throughput_bps[0, 1] == 0.0 and result.plr[0, 1] == 1.0
            assert result.throughput_bps[0, 0] > 0.9 * load[0]
            # No NaN or infinity anywhere: the no-path loss is a finite stand-in.
            for array in (result.snr_db, result.delay_s, *result.state.arrays):
                assert np.isfinite(array).all()
            assert result.snr_db[0, 1] == pytest.approx(
                model.config.radio.tx_power_dbm - NO_LINK_LOSS_DB - model.config.radio.noise_dbm
            )


def test_fading_is_rician_in_line_of_sight_and_rayleigh_behind_the_block(
    area: AreaConfig, site: Site
) -> None:
    model = NetworkModel(NetworkConfig(), area)
    uav = np.array([25.0, 100.0, 50.0])
    clear, blocked = (40.0, 100.0), (140.0, 100.0)
    assert line_of_sight(site, uav, np.array([clear, blocked])).tolist() == [True, False]
    links = 3000
    loss, gains = model.link_channel_at(
        np.tile(uav, (links, 2, 1)), np.tile([clear, blocked], (links, 1, 1)),
        np.random.default_rng(1),
    )  # fmt: skip
    assert loss.shape == (links, 2) and gains is not None and gains.shape[:2] == (links, 2)
    assert np.allclose(loss, path_loss_db(site, uav, np.array([clear, blocked])))
    # Rician K = 13 dB: variance (2K + 1) / (K + 1)² ≈ 0.09; Rayleigh (exponential): 1.
    assert gains[:, 0].mean() == pytest.approx(1.0, abs=0.03)
    assert gains[:, 1].mean() == pytest.approx(1.0, abs=0.05)
    assert gains[:, 0].var() == pytest.approx(0.0914, rel=0.15)
    assert gains[:, 1].var() == pytest.approx(1.0, rel=0.15)


def test_expected_mode_is_deterministic_and_uses_the_mean_loss(area: AreaConfig) -> None:
    model = NetworkModel(NetworkConfig(), area)
    users = np.array([[30.0, 30.0], [170.0, 50.0], [100.0, 180.0]])
    load = np.array([5e6, 25e6, 10e6])
    uav = np.array([[60.0, 90.0, 40.0]])
    a = model.step(uav, users, load)
    b = NetworkModel(NetworkConfig(), area).step(uav, users, load)
    for x, y in zip(
        (a.throughput_bps, a.delay_s, a.plr, a.snr_db),
        (b.throughput_bps, b.delay_s, b.plr, b.snr_db),
        strict=True,
    ):
        assert np.array_equal(x, y)
    drawn = model.step(uav, users, load, rng=np.random.default_rng(5))
    assert np.array_equal(drawn.snr_db, a.snr_db)  # fading changes the rate, not the mean SNR


def test_step_many_rows_are_the_single_steps(area: AreaConfig) -> None:
    model = NetworkModel(NetworkConfig(), area)
    rng = np.random.default_rng(2)
    users = rng.uniform(0, 75, (4, 3, 2))  # west of the block: walkable
    load = rng.uniform(1e6, 15e6, (4, 3))
    uav = rng.uniform([0, 0, 25], [200, 200, 100], (4, 3))
    many = model.step_many(uav, users, load)
    for e in range(4):
        one = model.step(uav[e : e + 1], users[e], load[e])
        assert np.array_equal(many.throughput_bps[e], one.throughput_bps[0])
        assert np.array_equal(many.snr_db[e], one.snr_db[0])
    drawn = model.step_many(uav, users, load, rng=np.random.default_rng(0))
    assert np.isfinite(drawn.throughput_bps).all()


def test_link_channel_of_distances_refuses_a_site(area: AreaConfig) -> None:
    model = NetworkModel(NetworkConfig(), area)
    with pytest.raises(InputError, match=r"^environment: 'site:.*' is a site: .*link_channel_at"):
        model.link_channel(np.ones(2), np.ones(2), None)


def test_link_channel_at_is_link_channel_in_the_towns() -> None:
    model = NetworkModel(NetworkConfig(), AreaConfig(environment="urban"))
    rng = np.random.default_rng(4)
    uav = rng.uniform([0, 0, 25], [500, 500, 100], (5, 4, 3))
    users = rng.uniform(0, 500, (5, 4, 2))
    ground = np.hypot(uav[..., 0] - users[..., 0], uav[..., 1] - users[..., 1])
    height = np.maximum(uav[..., 2] - 1.5, 0.0)
    a = model.link_channel_at(uav, users, np.random.default_rng(9))
    b = model.link_channel(ground, height, np.random.default_rng(9))
    assert np.array_equal(a[0], b[0]) and a[1] is not None and np.array_equal(a[1], b[1])


# ---------------------------------------------------------------------------------- the fleet


@pytest.mark.parametrize("mode", ["distinct", "shared"])
def test_the_fleet_model_runs_on_a_site(area: AreaConfig, mode: str) -> None:
    fleet = FleetModel(FleetConfig(n_uavs=2, channel_mode=mode), NetworkConfig(), area)
    users = np.array([[30.0, 30.0], [40.0, 170.0], [170.0, 40.0], [180.0, 180.0], WEST_USER])
    load = np.full(5, 8e6)
    uav = np.array([[40.0, 100.0, 50.0], [160.0, 100.0, 50.0]])
    state = None
    for rng in (None, np.random.default_rng(0), np.random.default_rng(1)):
        result = fleet.step(uav, users, load, state, rng)
        state = result.state
        assert np.isfinite(result.utility).all() and result.utility[0] > 0
        assert np.isfinite(result.snr_db).all() and np.isfinite(result.throughput_bps).all()
        # Each user is on the AP on its own side of the block.
        assert result.association[0].tolist() == [0, 0, 1, 1, 0]


def test_a_fleet_of_one_on_a_site_is_the_single_model(area: AreaConfig) -> None:
    fleet = FleetModel(FleetConfig(n_uavs=1), NetworkConfig(), area)
    users = np.array([WEST_USER, EAST_USER, [60.0, 20.0]])
    load = np.array([5e6, 5e6, 5e6])
    one = fleet.step(np.array([WEST_UAV]), users, load)
    single = NetworkModel(NetworkConfig(), area).step(np.array([WEST_UAV]), users, load)
    assert np.array_equal(one.throughput_bps, single.throughput_bps)
    assert one.throughput_bps[0, 1] == 0.0 and not one.connected[0, 1]


def test_a_user_no_ap_reaches_is_not_served(area: AreaConfig) -> None:
    fleet = FleetModel(FleetConfig(n_uavs=2, channel_mode="shared"), NetworkConfig(), area)
    uav = np.array([WEST_UAV, [10.0, 60.0, 25.0]])  # both low in the west
    result = fleet.step(uav, np.array([WEST_USER, EAST_USER]), np.array([5e6, 5e6]))
    assert not result.connected[0, 1] and result.throughput_bps[0, 1] == 0.0
    assert not result.served[0, 1] and result.served[0, 0]


# ----------------------------------------------------------------------------- environments


def _world(area: AreaConfig, moving: bool = False):
    world = replace(PAPER, area=area, episode_steps=6)
    if moving:
        world = replace(
            world,
            mobility=Mobility(model="random-waypoint", speed_mps=(3.0, 6.0), pause_s=(0.0, 1.0)),
            demand=Demand(step_rate_per_s=0.1, quiet_rate_per_s=0.05),
        )
    return world


@pytest.mark.parametrize("env_id", [DISCRETE_ENV_ID, CONTINUOUS_ENV_ID])
def test_the_gymnasium_environments_run_on_a_site(area: AreaConfig, env_id: str) -> None:
    env = gym.make(env_id, world=_world(area, moving=True))
    observation, _ = env.reset(seed=3)
    assert env.observation_space.contains(observation)
    base = env.unwrapped
    for _ in range(6):
        observation, reward, _, truncated, _ = env.step(env.action_space.sample())
        assert np.isfinite(reward) and env.observation_space.contains(observation)
        assert walkable_at(base.model.site, base.users.xy_m).all()
    assert truncated
    env.close()


def test_a_scenario_with_a_user_in_a_building_is_refused_by_the_environment(
    area: AreaConfig,
) -> None:
    env = gym.make(DISCRETE_ENV_ID, world=_world(area))
    inside = Scenario("bad", [[30.0, 30.0], [100.0, 100.0]], [5e6, 5e6])
    with pytest.raises(InputError, match=r"^users\[1\]: \(100\.0, 100\.0\) is inside a building"):
        env.reset(seed=0, options={"scenario": inside})


def test_the_vector_environment_runs_on_a_site(area: AreaConfig) -> None:
    from sim.vector_env import FapVectorEnv

    env = FapVectorEnv(3, "continuous", world=_world(area, moving=True))
    observations, _ = env.reset(seed=1)
    assert observations.shape[0] == 3
    for _ in range(8):  # past the episode's end: the same-step reset too
        observations, rewards, _, _, _ = env.step(env.action_space.sample())
        assert np.isfinite(rewards).all() and np.isfinite(observations).all()
        for users in env.users:
            assert walkable_at(env.model.site, users.xy_m).all()
    env.close()


def test_the_fleet_environment_runs_on_a_site(area: AreaConfig) -> None:
    from sim.fleet_env import FleetParallelEnv

    env = FleetParallelEnv(n_uavs=2, action_kind="continuous", world=_world(area, moving=True))
    observations, _ = env.reset(seed=4)
    assert set(observations) == {"uav_0", "uav_1"}
    for _ in range(6):
        actions = {agent: env.action_space(agent).sample() for agent in env.agents}
        observations, rewards, _, _, _ = env.step(actions)
        assert all(np.isfinite(r) for r in rewards.values())
    assert gym.make("tupa/FleetDiscrete-v0", n_uavs=2, world=_world(area)).reset(seed=0)


# --------------------------------------------------------------------- users on walkable ground


@pytest.mark.parametrize("family", FAMILIES)
def test_generated_users_stand_on_walkable_ground(area: AreaConfig, family: str) -> None:
    for seed in range(6):
        scenarios = generate_scenarios(20, 12, seed, area=area, family=family)
        xy = np.concatenate([s.users_xy_m for s in scenarios])
        assert not _in_block(xy).any()
        assert ((xy > 0) & (xy < SIZE_M)).all()
        again = generate_scenarios(20, 12, seed, area=area, family=family)
        assert again == scenarios  # deterministic per seed


def test_the_generator_draws_again_from_the_layout_not_elsewhere(area: AreaConfig) -> None:
    """Only the users that landed in the block move: the same draws off the site keep theirs,
    and the loads do not change."""
    open_area = replace(area, environment="open")
    moved = kept = 0
    for seed in range(10):
        on_site = generate_scenarios(10, 20, seed, area=area, family="uniform")
        off_site = generate_scenarios(10, 20, seed, area=open_area, family="uniform")
        for a, b in zip(on_site, off_site, strict=True):
            assert np.array_equal(a.load_bps, b.load_bps)
            outside = ~_in_block(b.users_xy_m)
            assert np.array_equal(a.users_xy_m[outside], b.users_xy_m[outside])
            moved += int((~outside).sum())
            kept += int(outside.sum())
    assert moved > 0 and kept > moved


def test_the_sampler_puts_users_on_walkable_ground(area: AreaConfig) -> None:
    sampler = ScenarioSampler(families=FAMILIES, users=(1, 30), area=area)
    rng = np.random.default_rng(0)
    for _ in range(60):
        assert not _in_block(sampler.sample(rng).users_xy_m).any()


def test_with_almost_no_ground_users_go_to_the_nearest_walkable_cell(tmp_path: Path) -> None:
    """One walkable cell: after the bounded redraws every user lands on its centre."""
    height = np.full((40, 40), 30.0, np.float32)
    height[7, 31] = 0.0  # the cell (x 155-160 m, y 35-40 m)
    xs, zs = np.linspace(0.0, SIZE_M, 3), np.array([25.0, 100.0])
    save_site(_blank_site(SIZE_M, height, xs, zs), tmp_path / "dense")
    area = AreaConfig(size_x_m=SIZE_M, size_y_m=SIZE_M, environment=f"site:{tmp_path / 'dense'}")
    scenarios = generate_scenarios(3, 5, 7, area=area, family="hotspots")
    for s in scenarios:
        assert np.array_equal(s.users_xy_m, np.tile([157.5, 37.5], (5, 1)))
    assert generate_scenarios(3, 5, 7, area=area, family="hotspots") == scenarios


def test_nearest_walkable_cell_stays_inside_the_area(site: Site) -> None:
    got = nearest_walkable_xy(site, np.array([[100.0, 100.0], [81.0, 71.0]]), 100.0, 100.0)
    assert got.tolist() == [[77.5, 97.5], [77.5, 72.5]]  # west of the block, centres ≤ 100 m


@pytest.mark.parametrize("model", ["random-waypoint", "group"])
def test_moving_users_never_enter_a_building(area: AreaConfig, site: Site, model: str) -> None:
    mobility = Mobility(model=model, speed_mps=(4.0, 8.0), pause_s=(0.0, 2.0))
    rng = np.random.default_rng(11)
    start = generate_scenarios(1, 12, 3, area=area, family="uniform")[0]
    users = UserDynamics(start.users_xy_m, start.load_bps, mobility, Demand(), area, rng)
    travelled = 0.0
    for _ in range(300):
        before = users.xy_m
        users.advance(1.0, rng)
        assert walkable_at(site, users.xy_m).all()
        for u in range(12):
            assert walkable_path(site, before[u], users.xy_m[u])
        travelled += float(np.hypot(*(users.xy_m - before).T).sum())
    assert travelled > 12 * 300 * 1.0  # they do walk (at least 1 m/s on average)


def test_moving_users_off_a_site_draw_as_before() -> None:
    """Off a site the walkers' draws are unchanged: the same positions as a straight replay of
    the random-waypoint rule (the site checks draw nothing)."""
    area = AreaConfig()
    mobility = Mobility(model="random-waypoint", speed_mps=(1.0, 1.0), pause_s=(0.0, 0.0))
    start = np.array([[10.0, 10.0]])
    users = UserDynamics(start, [1e6], mobility, Demand(), area, np.random.default_rng(0))
    replay = np.random.default_rng(0)
    replay.choice(1, size=1, replace=False)
    waypoint = replay.uniform([0.0, 0.0], [500.0, 500.0])
    replay.uniform(1.0, 1.0)
    users.advance(1.0, np.random.default_rng(1))
    gap = waypoint - start[0]
    assert np.allclose(users.xy_m[0], start[0] + gap / np.hypot(*gap))


def test_a_user_that_starts_in_a_building_is_refused(area: AreaConfig) -> None:
    with pytest.raises(InputError, match=r"^users\[0\]: \(90\.0, 70\.0\) is inside a building"):
        UserDynamics([[90.0, 70.0]], [1e6], Mobility(), Demand(), area, np.random.default_rng(0))


def _scenario_doc(area: AreaConfig, users: list[tuple[float, float]]) -> dict:
    return {
        "format": "tupa-scenarios/1",
        "environment": area.environment,
        "area": {"size_x_m": 200, "size_y_m": 200, "zone_m": 25, "z_min_m": 25, "z_max_m": 100},
        "scenarios": [
            {"id": "s0", "users": [{"x_m": x, "y_m": y, "load_bps": 1e6} for x, y in users]}
        ],
    }


def test_a_scenario_file_with_a_user_in_a_building_is_refused(
    area: AreaConfig, tmp_path: Path
) -> None:
    good = tmp_path / "good.json"
    good.write_text(json.dumps(_scenario_doc(area, [(30.0, 30.0), (170.0, 100.0)])))
    loaded_area, scenarios = load_scenarios(good)
    assert loaded_area == area and scenarios[0].n_users == 2
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_scenario_doc(area, [(30.0, 30.0), (120.0 - 1e-9, 100.0)])))
    with pytest.raises(InputError) as info:
        load_scenarios(bad)
    message = str(info.value)
    assert "\n" not in message
    assert message == (
        f"{bad}: scenario s0: users[1]: (120.0, 100.0) is inside a building on {area.environment}"
    )
    with pytest.raises(InputError, match=r"scenario s0: users\[0\]: .* inside a building"):
        save_scenarios(tmp_path / "out.json", area, [Scenario("s0", [[100, 100]], [1e6])])
    assert not (tmp_path / "out.json").exists()


def test_a_case_file_on_a_site_is_checked_too(area: AreaConfig, tmp_path: Path) -> None:
    doc = _scenario_doc(area, [(100.0, 100.0)])
    doc["format"] = "tupa-cases/1"
    doc["cases"] = [{**doc.pop("scenarios")[0], "uav": {"x_m": 50, "y_m": 50, "z_m": 50}}]
    path = tmp_path / "cases.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r": case s0: users\[0\]: \(100\.0, 100\.0\) is inside"):
        load_cases(path)


def test_a_scenario_file_whose_site_is_missing_is_refused(tmp_path: Path) -> None:
    area = AreaConfig(size_x_m=200, size_y_m=200, environment=f"site:{tmp_path / 'gone'}")
    path = tmp_path / "s.json"
    path.write_text(json.dumps(_scenario_doc(area, [(30.0, 30.0)])))
    with pytest.raises(InputError, match=r"^.*s\.json: environment: 'site:.*gone': no site there"):
        load_scenarios(path)


# ------------------------------------------------------------------------ names and commands


def test_check_environment_names_the_field(site_dir: Path) -> None:
    assert check_environment("urban") == "urban"
    assert check_environment(f"site:{site_dir}", on_disk=True) == f"site:{site_dir}"
    assert check_environment("site:/nowhere") == "site:/nowhere"  # the syntax alone
    with pytest.raises(InputError, match=r"^--environment: 'site:/nowhere': no site there"):
        check_environment("site:/nowhere", "--environment", on_disk=True)
    with pytest.raises(InputError, match=r"^world\.environment: must be one of open, .* site:PATH"):
        check_environment("mars", "world.environment")
    assert environment_problem("site:") == "'site:' needs the site directory's path (site:PATH)"
    assert environment_problem(3) is not None


def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    from service.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    return err


def test_the_command_lines_refuse_a_missing_site_in_one_line(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    scenarios = tmp_path / "open.json"
    save_scenarios(scenarios, AreaConfig(), generate_scenarios(2, 3, 1))
    missing = f"site:{tmp_path / 'nowhere'}"
    want = f"--environment: '{missing}': no site there (site.json and site.npz)"
    err = _one_line_error(
        capsys,
        ["eval", "--policy", "min-distance", "--scenarios", str(scenarios), "--json",
         str(tmp_path / "e.json"), "--environment", missing, "--no-progress"],
    )  # fmt: skip
    assert err == f"tupa eval: error: {want}"
    err = _one_line_error(
        capsys,
        ["eval", "--policy", "min-distance", "--scenarios", str(scenarios), "--json",
         str(tmp_path / "e.json"), "--world-set", f"environment={missing}", "--no-progress"],
    )  # fmt: skip
    assert err == f"tupa eval: error: world.environment: '{missing}': no site there " + (
        "(site.json and site.npz)"
    )
    err = _one_line_error(
        capsys,
        ["scenarios", "generate", "--n", "2", "--environment", missing, "--out",
         str(tmp_path / "s.json")],
    )  # fmt: skip
    assert err == f"tupa scenarios: error: {want}"
    err = _one_line_error(
        capsys,
        ["train", "--algo", "ddpg", "--strategy", "gen500", "--test-scenarios", str(scenarios),
         "--out", str(tmp_path / "run"), "--environment", missing, "--episodes", "1"],
    )  # fmt: skip
    assert err == f"tupa train: error: {want}"
    assert not (tmp_path / "e.json").exists() and not (tmp_path / "s.json").exists()


def test_scenarios_generate_takes_a_site(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, site_dir: Path, big_site_dir: Path
) -> None:
    """``tupa scenarios generate --environment site:PATH``: the file records the site and
    every user stands on its walkable ground (a 500 m site: the command's area)."""
    from service.cli import main

    environment = f"site:{big_site_dir}"
    out = tmp_path / "s.json"
    argv = ["scenarios", "generate", "--n", "20", "--users", "8", "--family", "uniform"]
    assert main([*argv, "--environment", environment, "--out", str(out)]) == 0
    area, scenarios = load_scenarios(out)
    assert area.environment == environment and len(scenarios) == 20
    xy = np.concatenate([s.users_xy_m for s in scenarios])
    inside = (xy[:, 0] >= 100) & (xy[:, 0] < 400) & (xy[:, 1] >= 200) & (xy[:, 1] < 300)
    assert not inside.any()
    # A site smaller than the command's 500 m area: one line naming the option.
    err = _one_line_error(capsys, [*argv, "--environment", f"site:{site_dir}", "--out", str(out)])
    assert err.startswith(f"tupa scenarios: error: --environment: 'site:{site_dir}' is smaller")


def test_the_sweep_file_takes_a_site_and_refuses_a_missing_one(
    big_site_dir: Path, tmp_path: Path
) -> None:
    from policies.sweep.spec import parse_spec

    scenarios = tmp_path / "t.json"
    save_scenarios(scenarios, AreaConfig(), generate_scenarios(2, 3, 1))
    doc = {
        "test_sets": {"t": {"file": str(scenarios)}},
        "grid": {"environment": ["urban", f"site:{big_site_dir}"]},
        "train": {"algorithm": "ddpg", "strategy": "gen500", "episodes": 1, "seed": 1},
    }
    spec = parse_spec(doc, tmp_path / "sweep.yaml")
    assert {t.params["environment"] for t in spec.trials} == {"urban", f"site:{big_site_dir}"}
    doc["grid"]["environment"] = ["site:/nowhere"]
    with pytest.raises(
        InputError, match=r"sweep\.yaml: grid\.environment.*'site:/nowhere': no site"
    ):
        parse_spec(doc, tmp_path / "sweep.yaml")


def test_the_ns3_backend_takes_a_site_and_refuses_a_missing_one_in_one_line(
    site_dir: Path, tmp_path: Path
) -> None:
    from sim.ns3_backend import Ns3Settings

    assert Ns3Settings(environment=f"site:{site_dir}").environment == f"site:{site_dir}"
    with pytest.raises(InputError) as info:
        Ns3Settings(environment=f"site:{tmp_path / 'nowhere'}")
    assert str(info.value).startswith("environment: ")
    assert "\n" not in str(info.value)


def test_eval_runs_on_a_site_and_names_a_test_user_inside_a_building(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, big_site_dir: Path
) -> None:
    from service.cli import main

    environment = f"site:{big_site_dir}"
    on_site = tmp_path / "site.json"
    big_area = AreaConfig(environment=environment)
    save_scenarios(on_site, big_area, generate_scenarios(2, 4, 5, area=big_area))
    out = tmp_path / "e.json"
    argv = ["eval", "--policy", "min-distance", "--episode-steps", "3", "--no-progress"]
    assert main([*argv, "--scenarios", str(on_site), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["environment"] == environment and result["n_scenarios"] == 2
    assert 0 < result["mean_utility"] <= 1
    # An open-field file flown over the site: its user in the block is named, in one line.
    open_file = tmp_path / "open.json"
    save_scenarios(open_file, AreaConfig(), [Scenario("s7", [[50, 50], [250, 250]], [1e6, 1e6])])
    err = _one_line_error(
        capsys,
        [*argv, "--scenarios", str(open_file), "--json", str(tmp_path / "x.json"),
         "--environment", environment],
    )  # fmt: skip
    assert err == (
        f"tupa eval: error: {open_file}: scenario s7: users[1]: (250.0, 250.0) is inside a "
        f"building on {environment}"
    )
