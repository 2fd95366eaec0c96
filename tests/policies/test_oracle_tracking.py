"""The oracle's fast paths: settled episodes, the staged screen, and tracking moving users."""

from __future__ import annotations

import numpy as np
import pytest

from policies.placements.baselines import MinDistancePlacement
from policies.placements.oracle import (
    OracleConfig,
    OraclePlacement,
    coarse_grid_positions_m,
    episode_utility,
)
from sim.config import AreaConfig, NetworkConfig
from sim.network import NetworkModel
from sim.scenarios import Scenario, generate_scenarios
from sim.utility import network_utility

AREA = AreaConfig()
STEPS = 30  # shorter than the paper's episode, to keep the tests fast; the logic is the same


def in_volume(position: np.ndarray, area: AreaConfig = AREA) -> bool:
    return bool(
        position.shape == (3,)
        and 0.0 <= position[0] <= area.size_x_m
        and 0.0 <= position[1] <= area.size_y_m
        and area.z_min_m <= position[2] <= area.z_max_m
    )


def stepped_episode_utility(
    model: NetworkModel, positions: np.ndarray, scenario: Scenario, steps: int, warmup: int
) -> np.ndarray:
    """The episode simulated step by step, every step of every position (the reference)."""
    users, load = scenario.users_xy_m, scenario.load_bps
    state = None
    for _ in range(warmup):
        state = model.step(positions, users, load, state).state
    values = []
    for _ in range(steps):
        result = model.step(positions, users, load, state)
        state = result.state
        values.append(network_utility(result.throughput_bps, result.delay_s, result.plr, load))
    return np.mean(values, axis=0)


def walk(scenario: Scenario, steps: int, step_m: float, seed: int) -> list[Scenario]:
    """The scenario's users walking ``step_m`` per step in random directions (loads fixed)."""
    rng = np.random.default_rng(seed)
    xy = np.array(scenario.users_xy_m)
    walked = []
    for t in range(steps):
        walked.append(Scenario(f"{scenario.id}-{t}", xy.copy(), scenario.load_bps))
        heading = rng.uniform(0.0, 2.0 * np.pi, len(xy))
        xy = np.clip(
            xy + step_m * np.stack([np.cos(heading), np.sin(heading)], axis=1),
            0.0,
            [AREA.size_x_m, AREA.size_y_m],
        )
    return walked


@pytest.mark.parametrize("queueing", ["fq-codel", "mac-only"])
@pytest.mark.parametrize("warmup", [0, 1, 2])
def test_settled_episodes_score_exactly_as_stepping_every_step(queueing: str, warmup: int) -> None:
    """Positions whose queues settle are filled in, not simulated: the scores do not change."""
    model = NetworkModel(NetworkConfig().with_queueing(queueing), AREA)
    grid = AREA.grid_positions_m()[::7]  # well and badly placed positions, settling or not
    for scenario in generate_scenarios(3, 4, seed=17, area=AREA):
        fast = episode_utility(model, grid, scenario, STEPS, warmup)
        reference = stepped_episode_utility(model, grid, scenario, STEPS, warmup)
        assert np.allclose(fast, reference, rtol=0.0, atol=1e-12)


def test_settled_positions_stop_being_simulated(monkeypatch) -> None:
    """A UAV right above a light user drains its queue at once: a step or two, not 31."""
    model = NetworkModel(NetworkConfig(), AREA)
    scenario = Scenario("light", [[250.0, 250.0]], [1e6])
    calls = []
    step = model.step
    monkeypatch.setattr(model, "step", lambda *a, **k: calls.append(1) or step(*a, **k))
    above = np.array([[250.0, 250.0, AREA.z_min_m]])
    fast = episode_utility(model, above, scenario, STEPS)
    assert len(calls) <= 3
    assert fast == pytest.approx(stepped_episode_utility(model, above, scenario, STEPS, 1))


@pytest.mark.parametrize("n_users", [3, 8])
def test_staged_screen_keeps_the_full_screens_best(n_users: int) -> None:
    """Regression check of the successive-halving screen: on these scenarios its best
    ``top_k`` are the whole grid's, in the same order, with the same scores."""
    staged = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS))
    whole = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS, screen_keep=()))
    k = staged.config.top_k
    for scenario in generate_scenarios(4, n_users, seed=23, area=AREA):
        fast = staged._screen(staged._grid_m, scenario)
        full = whole._screen(whole._grid_m, scenario)
        assert np.isfinite(full).all()
        top = np.argsort(-full, kind="stable")[:k]
        assert np.array_equal(np.argsort(-fast, kind="stable")[:k], top)
        assert np.array_equal(fast[top], full[top])


@pytest.mark.parametrize("n_users", [1, 3, 8])
def test_search_and_track_are_never_worse_than_the_baselines(n_users: int) -> None:
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS, track_full_every=4))
    baselines = (MinDistancePlacement(AREA), MinDistancePlacement(AREA, load_weighted=True))
    for scenario in generate_scenarios(3, n_users, seed=31 + n_users, area=AREA):
        oracle.reset_tracking()
        previous = None
        for moved in walk(scenario, 5, 3.0, seed=n_users):
            floor = episode_utility(
                oracle.model, np.stack([b.place(moved) for b in baselines]), moved, STEPS
            ).max()
            searched = oracle.search(moved)
            tracked = oracle.track_search(moved, previous)
            for result in (searched, tracked):
                assert in_volume(result.position_m)
                assert result.utility >= floor - 1e-12
                own = episode_utility(oracle.model, result.position_m, moved, STEPS)[0]
                assert own == pytest.approx(result.utility, abs=1e-12)
            previous = tracked.position_m


def test_track_follows_slowly_moving_users() -> None:
    """Users walking 1.5 m per decision: the cheap path does most of the work, stays in the
    volume, and scores within a small tolerance of a full search at every step."""
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS))
    reference = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS))
    sources = []
    for scenario in generate_scenarios(3, 3, seed=41, area=AREA):
        oracle.reset_tracking()
        previous = None
        for moved in walk(scenario, 12, 1.5, seed=7):
            result = oracle.track_search(moved, previous)
            sources.append(result.source)
            assert in_volume(result.position_m)
            assert result.utility >= reference.search(moved).utility - 1e-3
            previous = result.position_m
    assert sources.count("track") >= len(sources) // 2


def test_track_cache_answers_identical_input_without_simulating(monkeypatch) -> None:
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS))
    scenario = generate_scenarios(1, 3, seed=5, area=AREA)[0]
    first = oracle.track_search(scenario)
    assert first.source == "search"

    def no_simulation(*args, **kwargs):
        raise AssertionError("a cached input was simulated again")

    monkeypatch.setattr(oracle.model, "step", no_simulation)
    same = Scenario("another id, same users", scenario.users_xy_m.copy(), scenario.load_bps)
    for previous in (None, first.position_m, np.array([1.0, 2.0, 30.0])):
        again = oracle.track_search(same, previous)
        assert again.source == "cache"
        assert np.array_equal(again.position_m, first.position_m)
        assert again.utility == first.utility
        position = oracle.track(same, previous)
        assert np.array_equal(position, first.position_m)
        position[:] = -1.0  # the caller's copy: the cache keeps its own
    assert np.array_equal(oracle.track(same, None), first.position_m)


def test_track_changes_with_the_input_and_forgets_on_reset() -> None:
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS, track_cache_size=1))
    a, b = generate_scenarios(2, 3, seed=9, area=AREA)
    first = oracle.track_search(a)
    assert oracle.track_search(b, first.position_m).source != "cache"
    assert oracle.track_search(a, first.position_m).source != "cache"  # evicted (size 1)
    assert oracle.track_search(a, first.position_m).source == "cache"
    oracle.reset_tracking()
    assert oracle.track_search(a, first.position_m).source != "cache"


@pytest.mark.parametrize("every", [1, 3])
def test_track_runs_a_full_search_periodically(every: int) -> None:
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=STEPS, track_full_every=every))
    scenario = generate_scenarios(1, 3, seed=13, area=AREA)[0]
    sources, previous = [], None
    for moved in walk(scenario, 8, 1.0, seed=3):
        result = oracle.track_search(moved, previous)
        sources.append(result.source)
        previous = result.position_m
    assert sources[0] == "search"  # no previous position: a full search
    assert "cache" not in sources
    if every == 1:
        assert set(sources) == {"search"}
    else:
        longest_cheap_run = max(len(run) for run in "".join(s[0] for s in sources).split("s"))
        assert longest_cheap_run <= every - 1


def test_coarse_grid_is_a_centred_subset_of_the_grid() -> None:
    grid = {tuple(p) for p in AREA.grid_positions_m()}
    coarse = coarse_grid_positions_m(AREA, 4)
    assert len(coarse) == 5 * 5 * AREA.n_levels_z
    assert all(tuple(p) in grid and in_volume(p) for p in coarse)
    xs = np.unique(coarse[:, 0])
    assert xs[0] - 0.0 == pytest.approx(AREA.size_x_m - xs[-1], abs=AREA.zone_m)
    small = AreaConfig(size_x_m=50.0, size_y_m=25.0)
    assert len(coarse_grid_positions_m(small, 4)) == small.n_levels_z
    assert len(coarse_grid_positions_m(AREA, 1)) == len(grid)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"track_full_every": 0}, "track_full_every"),
        ({"track_screen_stride": 0}, "track_screen_stride"),
        ({"track_top_k": 0}, "track_top_k"),
        ({"track_cache_size": -1}, "track_cache_size"),
        ({"track_step_m": 0.0}, "track_step_m"),
        ({"track_jump_tol": -1e-3}, "track_jump_tol"),
        ({"screen_keep": (600, 0)}, "screen_keep"),
        ({"initial_step_m": -1.0}, "initial_step_m"),
        ({"improvement_tol": float("nan")}, "improvement_tol"),
        ({"screen_steps": 0}, "screen_steps"),
    ],
)
def test_oracle_config_is_validated(changes: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        OracleConfig(**changes)


def test_oracle_config_keeps_screen_keep_a_tuple() -> None:
    assert OracleConfig(screen_keep=[400, 100]).screen_keep == (400, 100)
    assert OracleConfig(screen_keep=()).screen_keep == ()


@pytest.mark.parametrize("previous", [np.zeros(2), np.array([1.0, np.nan, 30.0])])
def test_track_rejects_a_bad_previous_position(previous: np.ndarray) -> None:
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=5))
    scenario = generate_scenarios(1, 2, seed=1, area=AREA)[0]
    with pytest.raises(ValueError, match="previous_m"):
        oracle.track(scenario, previous)


def test_track_clips_a_previous_position_outside_the_volume() -> None:
    oracle = OraclePlacement(AREA, config=OracleConfig(episode_steps=10))
    scenario = generate_scenarios(1, 3, seed=2, area=AREA)[0]
    assert in_volume(oracle.track(scenario, np.array([-50.0, 900.0, 500.0])))
