"""The planning oracle (policies/placements/planning.py): named, legal, deterministic, never below
the tracking oracle on its own objective, and close to an exhaustive search on a small case."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from policies.interface import ReportedUsers
from policies.placements.planning import PlanningConfig, PlanningPolicy
from policies.registry import POLICY_NAMES, close_names, resolve_policy, unknown_name
from sim.config import AreaConfig
from sim.envs import FapContinuousEnv
from sim.scenarios import Scenario, generate_scenarios
from sim.world import CLOSED_LOOP, CLOSED_LOOP_MOVING, World

SHORT = replace(CLOSED_LOOP, episode_steps=20)
TOWER = {
    "format": "tupa-envelope/1",
    "exclusions": [
        {"name": "tower", "polygon": [[300, 300], [420, 300], [420, 420], [300, 420]],
         "floor_m": 0, "ceiling_m": 90}
    ],
}  # fmt: skip


def _fly_episode(
    policy: PlanningPolicy, scenario: Scenario, world: World, seed: int = 0
) -> tuple[list[np.ndarray], list[np.ndarray], list[float]]:
    """Targets decided, positions flown and utilities of one episode (with the start)."""
    env = FapContinuousEnv([scenario], world=world)
    start = policy.begin_episode(scenario, world)
    options = {"scenario": scenario, "users_seed": seed + 1}
    if start is not None:
        options["uav_xyz_m"] = start
    _, info = env.reset(seed=seed, options=options)
    targets, positions, utilities = [], [info["uav_xyz_m"]], []
    for _ in range(world.episode_steps):
        target = policy.decide(info["reports"], info["uav_xyz_m"])
        targets.append(np.array(target))
        _, reward, _, _, info = env.step_to(target)
        positions.append(info["uav_xyz_m"])
        utilities.append(reward)
    return targets, positions, utilities


def test_resolves_by_name_and_is_listed() -> None:
    policy = resolve_policy("planning-oracle", SHORT)
    assert isinstance(policy, PlanningPolicy)
    assert (policy.name, policy.spec, policy.kind) == (
        "planning-oracle",
        "planning-oracle",
        "coordinates",
    )
    assert policy.world == SHORT
    assert "planning-oracle" in POLICY_NAMES and "oracle" in POLICY_NAMES
    close = close_names("planing-oracle", POLICY_NAMES)
    assert close[0] == "planning-oracle"
    assert "planning-oracle" in unknown_name("planing-oracle", close, POLICY_NAMES, "--policy")
    assert policy.describe()["metadata"]["horizon_steps"] == PlanningConfig().horizon_steps


def test_config_checks_its_knobs() -> None:
    with pytest.raises(ValueError, match="horizon_steps"):
        PlanningConfig(horizon_steps=0)
    with pytest.raises(ValueError, match="discount"):
        PlanningConfig(discount=0.0)
    with pytest.raises(ValueError, match="partway_fractions"):
        PlanningConfig(partway_fractions=(1.0,))


def test_flies_within_limits_and_the_envelope_with_legal_targets() -> None:
    # From the south-west corner to users beyond the tower: the way passes over or around it,
    # and the best places near the users are inside its footprint (made legal: over it).
    world = replace(SHORT, envelope=TOWER, episode_steps=10, home=(120.0, 120.0, 25.0))
    envelope = world.flight_envelope
    assert envelope is not None
    users = np.array([[360.0, 360.0], [330.0, 400.0], [440.0, 450.0], [400.0, 330.0]])
    scenario = Scenario("tower", users, np.full(4, 10e6))
    policy = PlanningPolicy(world)
    targets, positions, utilities = _fly_episode(policy, scenario, world)
    for target in targets:
        assert envelope.violation(target) is None, target
    for a, b in itertools.pairwise(positions):
        assert np.hypot(*(b[:2] - a[:2])) <= 10.0 + 1e-9
        assert abs(b[2] - a[2]) <= 3.0 + 1e-9
        assert envelope.violation(b) is None
        assert envelope.segment_violation(a, b) is None
    assert all(0.0 <= u <= 1.0 for u in utilities)
    # It flew toward the users.
    centre = users.mean(axis=0)
    assert np.hypot(*(positions[-1][:2] - centre)) < np.hypot(*(positions[0][:2] - centre)) - 50


def test_deterministic_for_the_same_inputs() -> None:
    world = replace(CLOSED_LOOP_MOVING, episode_steps=8)
    scenario = generate_scenarios(1, 5, seed=11)[0]
    first = _fly_episode(PlanningPolicy(world), scenario, world, seed=3)
    policy = PlanningPolicy(world)
    again = _fly_episode(policy, scenario, world, seed=3)
    repeated = _fly_episode(policy, scenario, world, seed=3)  # begin_episode forgets
    for other in (again, repeated):
        np.testing.assert_array_equal(np.array(first[0]), np.array(other[0]))
        assert first[2] == other[2]


@pytest.mark.parametrize("environment", ["open", "urban", "site:munich"])
def test_never_below_the_tracking_oracle_on_its_objective(environment: str) -> None:
    area = AreaConfig(environment=environment)
    world = replace(SHORT, area=area, episode_steps=30)
    policy = PlanningPolicy(world)
    oracle = resolve_policy("oracle", world)
    rng = np.random.default_rng(7)
    scenarios = generate_scenarios(3, 4, seed=23, area=area)
    better = 0
    for scenario in scenarios:
        policy.begin_episode(scenario, world)
        oracle.begin_episode(scenario, world)
        users = ReportedUsers(scenario.users_xy_m, scenario.load_bps)
        vehicle = world.home_position() + np.array([*rng.uniform(-100, 100, 2), 0.0])
        plan = policy.plan(users, vehicle, remaining_steps=30)
        # The tracking trajectory is the oracle policy's own target, held.
        np.testing.assert_array_equal(plan.tracking_trajectory_m[0], oracle.place(users))
        tracked = policy.score(plan.tracking_trajectory_m[None], users, vehicle, 30)[0]
        assert tracked == pytest.approx(plan.tracking_value, rel=1e-12)
        chosen = policy.score(plan.trajectory_m[None], users, vehicle, 30)[0]
        assert chosen == pytest.approx(plan.value, rel=1e-12)
        assert plan.value >= plan.tracking_value
        assert 0.0 <= plan.value <= 30.0
        assert np.all(plan.target_m >= [0, 0, area.z_min_m])
        assert np.all(plan.target_m <= [area.size_x_m, area.size_y_m, area.z_max_m])
        better += plan.value > plan.tracking_value + 1e-6
    # From a vehicle away from the answer, the way there is worth planning somewhere.
    assert better >= 1


def test_close_to_an_exhaustive_search_on_a_small_case() -> None:
    """Every 2-step sequence of 27 lattice targets, the tracking answer and staying put (841
    trajectories) over a town's short episode, on the planner's own objective: the planner is
    within 0.005 per step of the best, where the tracking oracle is well below it."""
    area = AreaConfig(environment="urban")
    steps = 30
    world = replace(SHORT, area=area, episode_steps=steps)
    policy = PlanningPolicy(world, PlanningConfig(horizon_steps=2))
    axis_xy = [area.size_x_m / 6, area.size_x_m / 2, 5 * area.size_x_m / 6]
    lattice = np.array(list(itertools.product(axis_xy, axis_xy, [25.0, 62.5, 100.0])))
    rng = np.random.default_rng(1)
    tracking_gaps = []
    for scenario in generate_scenarios(5, 3, seed=5, area=area):
        vehicle = np.array([*rng.uniform(0, 500, 2), rng.choice(area.altitude_levels_m())])
        policy.begin_episode(scenario, world)
        users = ReportedUsers(scenario.users_xy_m, scenario.load_bps)
        plan = policy.plan(users, vehicle, remaining_steps=steps)
        targets = np.concatenate([lattice, plan.tracking_trajectory_m[:1], vehicle[None]])
        pairs = np.array(list(itertools.product(targets, targets)))  # (841, 2, 3)
        best = float(policy.score(pairs, users, vehicle, steps).max())
        assert plan.value >= best - 0.005 * steps, (plan.value, best)
        assert best >= plan.tracking_value - 1e-12  # the tracking trajectory is among them
        tracking_gaps.append((best - plan.tracking_value) / steps)
    assert max(tracking_gaps) > 0.05  # a case where planning matters


@pytest.mark.parametrize("environment", ["open", "urban"])
def test_its_objective_is_what_the_world_scores(environment: str) -> None:
    """In a deterministic world with static users the tracking oracle's target never changes,
    so the utility its episode scores is the planner's value of its trajectory: the planner
    flies (speed, acceleration, latency: whatever the world's flight has), warms up and
    carries queues as the world does."""
    area = AreaConfig(environment=environment)
    world = replace(CLOSED_LOOP, area=area, episode_steps=30, stochastic=False)
    scenario = generate_scenarios(1, 4, seed=31, area=area)[0]
    oracle = resolve_policy("oracle", world)
    env = FapContinuousEnv([scenario], world=world)
    oracle.begin_episode(scenario, world)
    _, info = env.reset(seed=0, options={"scenario": scenario})
    start, total = info["uav_xyz_m"], 0.0
    for _ in range(world.episode_steps):
        _, reward, _, _, info = env.step_to(oracle.decide(info["reports"], info["uav_xyz_m"]))
        total += reward
    policy = PlanningPolicy(world)
    policy.begin_episode(scenario, world)
    plan = policy.plan(ReportedUsers(scenario.users_xy_m, scenario.load_bps), start, 30)
    assert plan.tracking_value == pytest.approx(total, abs=1e-6)
    assert np.linalg.norm(info["uav_xyz_m"] - start) > 20.0  # it did fly somewhere


def test_rollout_cap_counts_the_steps_not_simulated_as_the_last() -> None:
    world = replace(SHORT, episode_steps=40)
    scenario = generate_scenarios(1, 3, seed=2)[0]
    users = ReportedUsers(scenario.users_xy_m, scenario.load_bps)
    start = world.home_position()
    far = np.array([[[450.0, 450.0, 60.0]] * 3, [[start[0], start[1], 50.0]] * 3])
    full = PlanningPolicy(world).score(far, users, start, 40)
    same = PlanningPolicy(world, PlanningConfig(rollout_steps=40)).score(far, users, start, 40)
    np.testing.assert_array_equal(full, same)
    head = PlanningPolicy(world).score(far, users, start, 10)
    head_9 = PlanningPolicy(world).score(far, users, start, 9)
    capped = PlanningPolicy(world, PlanningConfig(rollout_steps=10)).score(far, users, start, 40)
    np.testing.assert_allclose(capped, head + 30 * (head - head_9), rtol=1e-12)
