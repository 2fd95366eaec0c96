"""Imitation of the fleet oracle (policies/training/fleet_imitation.py): the teacher's residual
actions and moves send each UAV to the oracle's target, teacher data are the same however many
workers collect them, the fit learns what the teacher does, and `tupa train --uavs K --imitate N`
writes a checkpoint that records it."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch as th

from policies.learned.fleet_checkpoint import FleetCheckpointPolicy
from policies.learned.fleet_residual import KMeansPrior, fleet_residual_targets
from policies.training.fleet_imitation import (
    TEACHERS,
    ImitationConfig,
    TeacherData,
    collect_teacher_data,
    fit_actor,
    symmetry,
    teacher_actions,
    teacher_moves,
)
from policies.training.fleet_training import (
    FleetTrainConfig,
    make_fleet_vec_env,
    train_fleet,
)
from policies.training.training import build_model
from sim.config import AreaConfig
from sim.errors import InputError
from sim.fleet_observation import fleet_observations
from sim.geometry import MOVES, assign_targets, move_masks, move_targets, zone_indices
from sim.observation import UserReports
from sim.scenarios import ScenarioSampler
from sim.world import get_world
from tests.helpers import tiny_preset

AREA = AreaConfig()
TINY_PRESET = tiny_preset()


def test_teacher_actions_send_each_uav_to_its_target() -> None:
    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 500, (30, 2))
    load = rng.uniform(1e6, 1e7, 30)
    report = UserReports(xy[:, 0], xy[:, 1], load, load, np.full(30, 0.01), np.zeros(30))
    here = np.array([[100.0, 100.0, 30.0], [400.0, 100.0, 30.0], [250.0, 400.0, 30.0]])
    priors = assign_targets(here, KMeansPrior(AREA, 10.0).place(report, 3))
    world = get_world("closed-loop")
    # Targets within the radius of each prior, inside the volume and apart.
    targets = priors + np.array([[40.0, -30.0, 0.0], [-60.0, 20.0, 0.0], [0.0, 90.0, 0.0]])
    targets[:, 0] = np.clip(targets[:, 0], 0, 500)
    targets[:, 1] = np.clip(targets[:, 1], 0, 500)
    targets[:, 2] = [25.0, 62.5, 100.0]
    actions, clipped = teacher_actions(targets, priors, world, 125.0)
    assert clipped == 0
    back = fleet_residual_targets(actions, report, here, AREA, 10.0, 125.0)
    np.testing.assert_allclose(back, targets, atol=1e-9)
    # A target beyond the radius is clipped, and counted.
    far = targets.copy()
    far[0, 0] = priors[0, 0] + 300.0
    actions, clipped = teacher_actions(far, priors, world, 125.0)
    assert clipped == 1 and actions[0, 0] == 1.0


def _world() -> object:
    return replace(get_world("closed-loop"), episode_steps=4, home="random")


@pytest.mark.process  # workers=2: a pool of spawned processes
def test_teacher_data_are_the_same_for_any_number_of_workers() -> None:
    world = _world()
    sampler = ScenarioSampler(families=("hotspots",), users=(6, 8), total_load_bps=80e6)
    runs = [
        collect_teacher_data(
            2,
            world,
            sampler,
            ImitationConfig(episodes=3, replan_every=2, workers=w, horizon_steps=6),
            125.0,
            seed=4,
            progress=False,
        )
        for w in (1, 2)
    ]
    one, two = runs
    assert one.observations.shape == (3 * 4 * 2, 9, AREA.n_zones_x, AREA.n_zones_y)
    assert one.actions.shape == (24, 3) and one.oracle_calls == 3 * 2
    assert np.all(np.abs(one.actions) <= 1.0)
    np.testing.assert_array_equal(one.episodes, np.repeat([0, 1, 2], 8))
    np.testing.assert_array_equal(one.observations, two.observations)
    np.testing.assert_array_equal(one.actions, two.actions)


@pytest.mark.training
def test_the_fit_learns_the_teachers_actions_and_keeps_the_best_epoch(tmp_path) -> None:
    config = FleetTrainConfig(
        n_uavs=2, episodes=1, out_dir=tmp_path, preset=TINY_PRESET, users=(6, 6),
        action="residual",
    )  # fmt: skip
    model = build_model("ddpg", make_fleet_vec_env(config), TINY_PRESET, 1, None)
    rng = np.random.default_rng(0)
    n = 400
    observations = np.zeros((n, 9, AREA.n_zones_x, AREA.n_zones_y), dtype=np.float32)
    side = rng.integers(0, 2, n)  # the teacher goes right where map 0 has users on the left
    observations[side == 0, 0, :5, :] = 1.0
    observations[side == 1, 0, -5:, :] = 1.0
    actions = np.where(side[:, None] == 0, [0.5, -0.2, 0.3], [-0.4, 0.1, 0.0]).astype(np.float32)
    data = TeacherData(observations, actions, np.arange(n) // 4, clipped=0, oracle_calls=100)
    record = fit_actor(model, data, ImitationConfig(episodes=100, epochs=30), progress=False)
    assert record["validation_mse"] < record["zero_action_validation_mse"] / 20
    assert 0 < record["best_epoch"] <= 30
    assert record["fit_samples"] + record["validation_samples"] == n
    with th.no_grad():
        got = model.actor(th.as_tensor(observations[:8], device=model.device)).cpu().numpy()
        target = model.actor_target(th.as_tensor(observations[:8], device=model.device))
    np.testing.assert_allclose(got, actions[:8], atol=0.15)
    np.testing.assert_array_equal(got, target.cpu().numpy())


@pytest.mark.training
def test_an_imitation_run_writes_a_checkpoint_that_records_it(tmp_path) -> None:
    config = FleetTrainConfig(
        n_uavs=2, episodes=0, out_dir=tmp_path / "run", preset=TINY_PRESET, users=(6, 8),
        families=("hotspots",), action="residual", imitate=2, imitate_replan_every=8,
        imitate_teacher="local", command="test", progress=False,
    )  # fmt: skip
    metadata = train_fleet(config)
    record = json.loads((tmp_path / "run" / "model.json").read_text())["imitation"]
    assert record == metadata["imitation"]
    assert record["teacher_episodes"] == 2
    assert record["teacher"] == {"oracle": "fleet-oracle", "name": "local", **TEACHERS["local"]}
    assert record["horizon_steps"] == get_world("closed-loop").episode_steps
    policy = FleetCheckpointPolicy.load(tmp_path / "run", AREA)
    assert policy.residual_radius_m == 125.0


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"imitate": 2}, "--imitate: fits a residual actor .* or the DDQN's moves"),
        ({"imitate": 2, "action": "residual", "algorithm": "ddqn"}, "--action"),
        ({"imitate": 1, "action": "residual"}, "at least 2 teacher episodes"),
        ({"imitate": -1, "action": "residual"}, "--imitate: must be >= 0"),
        ({"episodes": 0, "action": "residual"}, "--episodes: must be at least 1"),
        ({"imitate": 2, "action": "residual", "workers": 0}, "--workers"),
        ({"action": "residual", "workers": 2}, "--workers: spreads teacher episodes"),
        ({"imitate": 2, "action": "residual", "imitate_teacher": "exact"}, "--teacher: one of"),
        ({"action": "residual", "imitate_teacher": "local"}, "--teacher: chooses the teacher"),
        ({"action": "residual", "imitate_symmetries": True}, "--symmetries: fits --imitate"),
        ({"action": "residual", "imitate_rounds": 1}, "--dagger: refits --imitate"),
        ({"imitate": 2, "action": "residual", "imitate_rounds": -1}, "--dagger: must be >= 0"),
    ],
)
def test_imitation_settings_are_checked(tmp_path, changes, message) -> None:
    with pytest.raises(InputError, match=message):
        FleetTrainConfig(**{"n_uavs": 2, "episodes": 1, "out_dir": tmp_path, **changes})


@pytest.mark.parametrize(
    ("changes", "field"),
    [({"episodes": 0}, "episodes"), ({"horizon_steps": 0}, "horizon_steps"),
     ({"learning_rate": 0.0}, "learning_rate"), ({"validation_fraction": 1.0}, "validation"),
     ({"teacher": "exact"}, "teacher: one of search, local")],
)  # fmt: skip
def test_imitation_config_names_the_bad_field(changes, field) -> None:
    with pytest.raises(InputError, match=field):
        ImitationConfig(**{"episodes": 4, **changes})


def _users_on_four_sides(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` observations with users west, east, south or north (side 0–3, in turn) in map 0."""
    side = np.arange(n) % 4
    observations = np.zeros((n, 9, AREA.n_zones_x, AREA.n_zones_y), dtype=np.float32)
    observations[side == 0, 0, :5, :] = 1.0
    observations[side == 1, 0, -5:, :] = 1.0
    observations[side == 2, 0, :, :5] = 1.0
    observations[side == 3, 0, :, -5:] = 1.0
    return side, observations


@pytest.mark.parametrize("element", range(8))
def test_a_symmetry_turns_observations_and_actions_as_the_area_turns(element: int) -> None:
    """The observation of a mirrored or rotated fleet and users is the observation turned, and
    the residual action to the turned target is the action turned: fitting under symmetries
    teaches only true decisions."""
    world = get_world("closed-loop")
    zone, size = world.area.zone_m, world.area.size_x_m
    rng = np.random.default_rng(element)
    n = 14  # users and UAVs inside zones, off their edges (an edge point joins the zone above)

    def inside_zones(count: int) -> np.ndarray:
        return (
            rng.integers(0, world.area.n_zones_x, (count, 2)) + rng.uniform(0.2, 0.8, (count, 2))
        ) * zone

    def turn(points: np.ndarray) -> np.ndarray:
        out = np.array(points, dtype=float)
        if element & 4:
            out[:, [0, 1]] = out[:, [1, 0]]
        if element & 1:
            out[:, 0] = size - out[:, 0]
        if element & 2:
            out[:, 1] = size - out[:, 1]
        return out

    uav = np.column_stack([inside_zones(3), [30.0, 55.0, 80.0]])
    users = inside_zones(n)
    load = rng.uniform(1e5, 2e7, (4, n)) * np.array([[1.0], [0.8], [1e-7], [1e-7]])
    association = rng.integers(-1, 3, n)

    def report(xy: np.ndarray) -> UserReports:
        return UserReports(xy[:, 0], xy[:, 1], load[0], load[1], load[2], np.clip(load[3], 0, 1))

    seen = fleet_observations(uav, report(users), association, world)
    turned = fleet_observations(turn(uav), report(turn(users)), association, world)
    actions = rng.uniform(-1.0, 1.0, (3, 3)).astype(np.float32)
    got_x, got_a = symmetry(th.as_tensor(seen), th.as_tensor(actions), element)
    np.testing.assert_allclose(got_x.numpy(), turned, atol=1e-5)
    radius = 125.0  # the turned action moves the turned prior onto the turned target
    target = uav[:, :2] + actions[:, :2] * radius
    moved = turn(target) - turn(uav[:, :2])
    np.testing.assert_allclose(got_a.numpy()[:, :2] * radius, moved, atol=1e-3)
    np.testing.assert_array_equal(got_a.numpy()[:, 2], actions[:, 2])


@pytest.mark.training
def test_the_fit_under_symmetries_learns_a_decision_that_turns_with_the_area(tmp_path) -> None:
    """A teacher that flies towards the users, seen from four sides: fitted under the eight
    symmetries (each mini-batch turned), the actor still learns it."""
    config = FleetTrainConfig(
        n_uavs=2, episodes=1, out_dir=tmp_path, preset=TINY_PRESET, users=(6, 6),
        action="residual",
    )  # fmt: skip
    model = build_model("ddpg", make_fleet_vec_env(config), TINY_PRESET, 1, None)
    n = 400
    side, observations = _users_on_four_sides(n)
    towards = np.array([[-0.6, 0.0, 0.2], [0.6, 0.0, 0.2], [0.0, -0.6, 0.2], [0.0, 0.6, 0.2]])
    actions = towards[side].astype(np.float32)
    data = TeacherData(observations, actions, np.arange(n) // 4, clipped=0, oracle_calls=100)
    imitation = ImitationConfig(episodes=100, epochs=30, symmetries=True)
    record = fit_actor(model, data, imitation, progress=False)
    assert record["symmetries"] == 8
    assert record["validation_mse"] < record["zero_action_validation_mse"] / 10


def test_teacher_moves_head_for_each_uavs_target_and_stay_once_there() -> None:
    here = np.array(
        [[262.5, 262.5, 50.0], [12.5, 12.5, 25.0], [262.5, 262.5, 50.0], [100.0, 400.0, 75.0]]
    )
    targets = np.array(
        [
            [370.0, 262.5, 50.0],  # 107.5 m east: the five-zone move lands nearest
            [-40.0, 12.5, 25.0],  # west, off the area: that move is refused, so stay
            [266.0, 259.0, 52.0],  # inside its own zone: stay
            [100.0, 400.0 - 30.0, 75.0],  # about a zone south
        ]
    )
    moves, masks = teacher_moves(here, targets, AREA)
    np.testing.assert_array_equal(masks, move_masks(zone_indices(here, AREA), AREA))
    assert moves.tolist() == [7, 0, 0, 4]
    assert not masks[1, 2]  # west from the corner leaves the area
    landing, refused = move_targets(moves, here, AREA)
    assert not refused.any()
    # Nothing allowed lands nearer its target than the move chosen.
    for k in range(len(here)):
        for move in np.flatnonzero(masks[k]):
            other, _ = move_targets(np.array([move]), here[k : k + 1], AREA)
            assert (
                np.linalg.norm(other[0] - targets[k])
                >= np.linalg.norm(landing[k] - targets[k]) - 1e-9
            )


def test_teacher_data_in_moves_fly_the_moves_they_record() -> None:
    world = _world()
    sampler = ScenarioSampler(families=("hotspots",), users=(6, 8), total_load_bps=80e6)
    imitation = ImitationConfig(episodes=3, replan_every=2, horizon_steps=6)
    one, two = (
        collect_teacher_data(2, world, sampler, replace(imitation, workers=w), None, 4, False)
        for w in (1, 2)
    )
    assert one.moves and one.actions.shape == (24,) and one.masks.shape == (24, len(MOVES))
    assert one.actions.dtype == np.int64 and one.masks[np.arange(24), one.actions].all()
    np.testing.assert_array_equal(one.actions, two.actions)
    np.testing.assert_array_equal(one.observations, two.observations)


@pytest.mark.parametrize("element", range(8))
def test_a_symmetry_turns_moves_and_their_masks_as_the_area_turns(element: int) -> None:
    """The turned move steps as the turned area does, and the masks are those of the turned
    zones, so a move fitted under a symmetry is one the turned UAV may take."""
    n = AREA.n_zones_x
    rng = np.random.default_rng(element)
    index = np.column_stack([rng.integers(0, n, (40, 2)), rng.integers(0, AREA.n_levels_z, 40)])
    index[:4, :2] = [[0, 0], [n - 1, 0], [0, n - 1], [n - 1, n - 1]]  # corners: masks matter
    moves = np.tile(np.arange(len(MOVES)), 4)[:40]

    def turn(idx: np.ndarray) -> np.ndarray:
        out = np.array(idx)
        if element & 4:
            out[:, [0, 1]] = out[:, [1, 0]]
        if element & 1:
            out[:, 0] = n - 1 - out[:, 0]
        if element & 2:
            out[:, 1] = n - 1 - out[:, 1]
        return out

    masks = move_masks(index, AREA)
    x = th.zeros((40, 9, n, n))
    _, got_moves, got_masks = symmetry(x, th.as_tensor(moves), element, th.as_tensor(masks))
    np.testing.assert_array_equal(got_masks.numpy(), move_masks(turn(index), AREA))
    stepped = turn(index + MOVES[moves]) - turn(index)
    np.testing.assert_array_equal(MOVES[got_moves.numpy()], stepped)


@pytest.mark.training
def test_the_fit_learns_the_teachers_moves_within_their_masks(tmp_path) -> None:
    config = FleetTrainConfig(
        n_uavs=2, episodes=1, out_dir=tmp_path, preset=TINY_PRESET, users=(6, 6), algorithm="ddqn"
    )
    model = build_model("ddqn", make_fleet_vec_env(config), TINY_PRESET, 1, None)
    n = 400
    side, observations = _users_on_four_sides(n)
    moves = np.array([8, 7, 10, 9])[side]  # five zones west, east, south, north
    masks = np.ones((n, len(MOVES)), dtype=bool)
    masks[side == 1, 7] = False  # at the east edge: the long move is refused, the short one left
    moves[side == 1] = 1
    data = TeacherData(observations, moves, np.arange(n) // 4, 0, 100, masks=masks)
    imitation = ImitationConfig(episodes=100, epochs=20, symmetries=True)
    record = fit_actor(model, data, imitation, progress=False)
    assert record["symmetries"] == 8 and record["validation_accuracy"] == 1.0
    assert record["stay_validation_accuracy"] == 0.0 and "validation_mse" not in record
    picked, _ = model.predict(observations[:8], deterministic=True, action_masks=masks[:8])
    np.testing.assert_array_equal(picked, moves[:8])
    for a, b in zip(model.q_net.parameters(), model.q_net_target.parameters(), strict=True):
        assert th.equal(a, b)
