"""The world's flight inside an envelope (:mod:`sim.envelope.flight`): the fast path is
:func:`sim.flight.fly` exactly, routes are flown without ever leaving the envelope (single
vehicles and fleets of 3, hypothesis, every flown path sampled and held to the envelope with the
plain-distance check of ``test_envelope.py``), the fleet's separation holds on the paths, and
the world and its environments fly that way when given an envelope."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, event, given, settings
from hypothesis import strategies as st
from shapely.geometry import box

import sim.envelope.flight as flight_module
from sim.envelope import Envelope, Exclusion
from sim.envelope.flight import (
    Track,
    closest_approach_m,
    fly_along,
    fly_fleet,
    fly_route,
    fly_route_track,
    legal_position,
    plain_box,
    separate_tracks,
    separated_legal_targets,
)
from sim.envelope.route import Route
from sim.envs import FapContinuousEnv, FapDiscreteEnv
from sim.errors import InputError
from sim.fleet_env import FleetParallelEnv
from sim.flight import Flight, fly
from sim.scenarios import ScenarioSampler
from sim.vector_env import FapVectorEnv
from sim.world import CLOSED_LOOP, CLOSED_LOOP_MOVING, PAPER, World, world_with
from tests.sim.test_envelope import AREA, envelopes, independent_violations
from tests.sim.test_fleet_env import assert_one_uav_flies_as_the_single_environment

FLIGHT = Flight(10.0, 3.0)
SEPARATION_M = 10.0
STEP_M = 0.25

points3 = st.tuples(st.floats(-20, 220), st.floats(-20, 220), st.floats(0, 130))
inside3 = st.tuples(st.floats(0, 200), st.floats(0, 200), st.floats(25, 100))


def sampled_track(track: Track) -> np.ndarray:
    pieces = [
        np.linspace(a, b, max(2, math.ceil(math.dist(a, b) / STEP_M) + 1))
        for a, b in itertools.pairwise(track.points_m)
    ]
    return np.concatenate(pieces)


# -------------------------------------------------------------------------- the fast path


@settings(max_examples=200, deadline=None)
@given(start=inside3, target=points3, duration_s=st.sampled_from([0.5, 1.0, 3.0]))
def test_no_envelope_or_a_plain_box_flies_exactly_as_fly(start, target, duration_s) -> None:
    expected = fly(np.array(start), np.array(target), FLIGHT, duration_s)
    position, route = fly_route(None, start, target, FLIGHT, duration_s)
    assert np.array_equal(position, expected) and route.kind == "direct"
    envelope = Envelope.for_area(AREA)
    legal = tuple(np.clip(target, (0, 0, 25), (200, 200, 100)))
    position, route = fly_route(envelope, start, legal, FLIGHT, duration_s)
    assert np.array_equal(position, fly(np.array(start), np.array(legal), FLIGHT, duration_s))
    # A target outside the box: flown to its nearest point of the box.
    assert np.array_equal(fly_route(envelope, start, target, FLIGHT, duration_s)[0], position)
    assert route.target_m == legal


def test_the_fast_path_makes_no_shapely_call(monkeypatch: pytest.MonkeyPatch) -> None:
    envelope = Envelope.for_area(AREA)
    assert plain_box(envelope) == (0.0, 0.0, 25.0, 200.0, 200.0, 100.0)

    def forbidden(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("shapely reached on the fast path")

    for name in ("legal_target", "plan_route", "advance"):
        monkeypatch.setattr(flight_module, name, forbidden)
    monkeypatch.setattr(Envelope, "violation", forbidden)
    monkeypatch.setattr(Envelope, "segment_violation", forbidden)
    for _ in range(3):
        fly_route(envelope, (10, 10, 30), (150, 150, 90), FLIGHT, 1.0)
    fly_fleet(
        envelope, np.array([[10, 10, 30], [50, 10, 30]]), np.ones((2, 3)) * 60, FLIGHT, 1.0, 10
    )
    assert plain_box(Envelope.for_area(AREA, [Exclusion(box(1, 1, 9, 9), 0, 50)])) is None
    assert plain_box(Envelope.for_area(AREA, clearance_m=2.0)) is None


# -------------------------------------------------------------------------- one vehicle


@settings(max_examples=300, deadline=None)
@given(
    envelope=envelopes(),
    start=points3,
    goals=st.lists(st.tuples(points3, st.integers(1, 6)), min_size=1, max_size=4),
    duration_s=st.sampled_from([1.0, 2.5]),
)
def test_a_vehicle_never_leaves_the_envelope_on_its_way(
    envelope: Envelope, start, goals, duration_s: float
) -> None:
    here = legal_position(envelope, start)
    assume(envelope.violation(here) is None)
    route = None
    for goal, periods in goals:
        for _ in range(periods):
            flown = fly_route_track(envelope, here, goal, FLIGHT, duration_s, route)
            event(f"route {flown.route.kind}")
            assert independent_violations(envelope, sampled_track(flown.track)) == []
            assert flown.track.points_m[0] == tuple(here) and flown.track.times_s[-1] == duration_s
            assert np.array_equal(flown.track.points_m[-1], flown.position_m)
            # Never faster than the flight's limits, piece by piece.
            for (t0, a), (t1, b) in itertools.pairwise(
                zip(flown.track.times_s, flown.track.points_m, strict=True)
            ):
                span = t1 - t0
                assert math.hypot(b[0] - a[0], b[1] - a[1]) <= 10.0 * span + 1e-6
                assert abs(b[2] - a[2]) <= 3.0 * span + 1e-6
            here, route = flown.position_m, flown.route
    if not route.holding:  # given the time, it gets to the legal target
        for _ in range(200):
            here, route = fly_route(envelope, here, goal, FLIGHT, 5.0, route)
        assert route.target_m is not None
        assert np.allclose(here, route.target_m)


def test_a_diagonal_that_would_cut_a_block_as_fly_flies_it_is_flown_height_first() -> None:
    """fly() climbs at 3 m/s while covering 10 m/s: its dog-leg from (0, 100, 30) to
    (150, 100, 100) passes x = 90 m at 57 m, inside a block up to 60 m whose top the straight
    leg clears (72 m there). An autopilot flies it as fly() does, so the route (the link's as
    the world's) climbs first, then crosses; away from the block it is fly() exactly."""
    block = Exclusion(box(90, 90, 120, 110), 0.0, 60.0, "block")
    envelope = Envelope.for_area(AREA, [block])
    start, target = (0.0, 100.0, 30.0), (150.0, 100.0, 100.0)
    assert envelope.segment_violation(start, target) is None
    assert envelope.leg_violation(start, target) is not None
    here, route = np.array(start), None
    dog_leg = [np.array(start)]
    for _ in range(60):
        flown = fly_route_track(envelope, here, target, FLIGHT, 1.0, route)
        assert independent_violations(envelope, sampled_track(flown.track)) == []
        here, route = flown.position_m, flown.route
        if route is not None and len(route.waypoints) == 2:
            assert route.waypoints[0] == (0.0, 100.0, 100.0)  # height first
    for _ in range(120):
        dog_leg.append(fly(dog_leg[-1], np.array(target), FLIGHT, 0.25))
    assert np.array_equal(here, target)
    assert independent_violations(envelope, np.array(dog_leg)) != []  # fly() would have hit it
    # Far from the block, with the block in the envelope: fly()'s floats.
    far = (150.0, 10.0, 30.0), (190.0, 60.0, 90.0)
    position, _ = fly_route(envelope, far[0], far[1], FLIGHT, 1.0)
    assert np.array_equal(position, fly(np.array(far[0]), np.array(far[1]), FLIGHT, 1.0))


def test_a_leg_that_is_no_longer_legal_from_where_the_vehicle_is_gets_a_new_route() -> None:
    """Off its leg (as after a dog-leg), a vehicle whose straight flight and dog-leg to the
    waypoint both cross a block is given a new route from where it is, never flown through."""
    block = Exclusion(box(90, 90, 120, 110), 0.0, 60.0, "block")
    envelope = Envelope.for_area(AREA, [block])
    waypoint = (150.0, 100.0, 50.0)
    stale = Route(waypoint, waypoint, (waypoint,), "direct")
    here = (60.0, 100.0, 40.0)
    assert envelope.segment_violation(here, waypoint) is not None
    route = stale
    for _ in range(20):
        flown = fly_along(envelope, here, route, FLIGHT, 1.0)
        assert independent_violations(envelope, sampled_track(flown.track)) == []
        here, route = tuple(flown.position_m), flown.route
    assert route.kind in ("over", "around") and np.allclose(here, waypoint)


def test_a_route_is_kept_while_its_legal_target_stays_and_planned_again_otherwise() -> None:
    tower = Exclusion(box(80, 80, 120, 120), 0.0, 200.0, "tower")
    envelope = Envelope.for_area(AREA, [tower], clearance_m=5.0)
    _, route = fly_route(envelope, (50, 100, 40), (150, 100, 40), FLIGHT, 1.0)
    assert route.kind == "around" and len(route.waypoints) > 1
    _, kept = fly_route(envelope, (50, 100, 40), (150, 100, 40), FLIGHT, 1.0, route)
    assert kept.waypoints == route.waypoints  # nothing reached yet: the same route
    _, other = fly_route(envelope, (50, 100, 40), (50, 150, 40), FLIGHT, 1.0, route)
    assert other.target_m == (50.0, 150.0, 40.0) and other.kind == "direct"
    # A target inside the tower is flown to its nearest legal point.
    _, moved = fly_route(envelope, (50, 100, 40), (100, 100, 40), FLIGHT, 1.0)
    assert moved.adjusted and envelope.violation(moved.target_m) is None


# -------------------------------------------------------------------------- fleets


def test_closest_approach_is_exact_for_crossing_paths() -> None:
    a = Track((0.0, 1.0), ((0.0, 0.0, 50.0), (10.0, 0.0, 50.0)))
    b = Track((0.0, 1.0), ((10.0, -5.0, 50.0), (0.0, 5.0, 50.0)))
    # Relative motion: (-10, 5) + t (20, -10); nearest at t = 0.5, 0 m (they meet).
    assert closest_approach_m(a, b) == pytest.approx(0.0, abs=1e-12)
    still = Track.still((5.0, 3.0, 50.0), 1.0)
    assert closest_approach_m(a, still) == pytest.approx(3.0)
    assert closest_approach_m(still, still) == 0.0


def test_a_vehicle_whose_path_crosses_anothers_holds_the_lower_index_first() -> None:
    starts = [(0.0, 0.0, 50.0), (10.0, -20.0, 50.0), (100.0, 100.0, 50.0)]
    tracks = [
        Track((0.0, 1.0), ((0.0, 0.0, 50.0), (20.0, 0.0, 50.0))),
        Track((0.0, 1.0), ((10.0, -20.0, 50.0), (10.0, 20.0, 50.0))),
        Track((0.0, 1.0), ((100.0, 100.0, 50.0), (110.0, 100.0, 50.0))),
    ]
    assert separate_tracks(starts, tracks, 10.0, 1.0) == (False, True, False)
    # Vehicle 1 holding sits in vehicle 0's way: vehicle 0 holds too.
    starts[1] = (15.0, 5.0, 50.0)
    tracks[1] = Track((0.0, 1.0), ((15.0, 5.0, 50.0), (15.0, 4.0, 50.0)))
    assert separate_tracks(starts, tracks, 10.0, 1.0) == (True, True, False)
    # Two that start closer than the separation may part, never come closer.
    near = [(0.0, 0.0, 50.0), (5.0, 0.0, 50.0)]
    apart = [Track.still(near[0], 1.0), Track((0.0, 1.0), (near[1], (15.0, 0.0, 50.0)))]
    assert separate_tracks(near, apart, 10.0, 1.0) == (False, False)
    closer = [Track.still(near[0], 1.0), Track((0.0, 1.0), (near[1], (2.0, 0.0, 50.0)))]
    assert separate_tracks(near, closer, 10.0, 1.0) == (False, True)


@settings(max_examples=150, deadline=None)
@given(
    envelope=envelopes(),
    starts=st.lists(inside3, min_size=3, max_size=3),
    goals=st.lists(st.lists(points3, min_size=3, max_size=3), min_size=1, max_size=4),
    duration_s=st.sampled_from([1.0, 3.0]),
)
def test_a_fleet_of_three_keeps_to_the_envelope_and_apart_on_its_paths(
    envelope: Envelope, starts, goals, duration_s: float
) -> None:
    positions = separated_legal_targets(envelope, np.array(starts), SEPARATION_M, AREA)
    assume(all(envelope.violation(p) is None for p in positions))
    routes = None
    for goal in goals:
        targets = separated_legal_targets(envelope, np.array(goal), SEPARATION_M, AREA)
        for _ in range(4):
            result = fly_fleet(
                envelope, positions, targets, FLIGHT, duration_s, SEPARATION_M, routes
            )
            event(f"held {sum(result.held)}")
            for route in result.routes:
                event(f"route {route.kind}")
            for track in result.tracks:
                assert independent_violations(envelope, sampled_track(track)) == []
            for i, j in itertools.combinations(range(3), 2):
                floor = min(SEPARATION_M, float(np.linalg.norm(positions[i] - positions[j])))
                assert closest_approach_m(result.tracks[i], result.tracks[j]) >= floor - 1e-6
                # Sampled in time, apart from the exact closest approach.
                for t in np.linspace(0.0, duration_s, 41):
                    a, b = result.tracks[i].at(t), result.tracks[j].at(t)
                    assert math.dist(a, b) >= floor - 1e-6
            for k in range(3):
                if result.held[k]:
                    assert np.array_equal(result.positions_m[k], positions[k])
            positions, routes = result.positions_m, result.routes


# -------------------------------------------------------------------------- the world

TOWER = {
    "format": "tupa-envelope/1",
    "clearance_m": 5,
    "exclusions": [
        {"name": "tower", "polygon": [[200, 200], [300, 200], [300, 300], [200, 300]],
         "ceiling_m": 200},
        {"name": "hall", "polygon": [[0, 0], [150, 0], [150, 100], [0, 100]], "ceiling_m": 50},
    ],
}  # fmt: skip


def test_a_world_carries_its_envelope_as_a_document(tmp_path: Path) -> None:
    assert CLOSED_LOOP.envelope is None and CLOSED_LOOP.flight_envelope is None
    world = replace(CLOSED_LOOP, envelope=TOWER)
    assert isinstance(world.envelope, str) and hash(world) == hash(replace(world))
    assert world == replace(CLOSED_LOOP, envelope=json.dumps(TOWER, indent=1))  # canonical
    assert world.flight_envelope is world.flight_envelope  # parsed once
    assert [e.name for e in world.flight_envelope.exclusions] == ["tower", "hall"]
    saved = json.loads(json.dumps(world.to_dict()))
    assert saved["envelope"] == TOWER and saved["flight"] == {
        "horizontal_mps": 10.0, "vertical_mps": 3.0, "accel_mps2": 2.5, "latency_s": 0.05
    }  # fmt: skip
    assert CLOSED_LOOP.to_dict()["envelope"] is None
    path = tmp_path / "town.json"
    path.write_text(json.dumps(TOWER))
    loaded = world_with(CLOSED_LOOP, [f"envelope={path}"])
    assert loaded.envelope == world.envelope and loaded.name == "closed-loop*"
    assert world_with(loaded, ["envelope=none"]).envelope is None
    bad = dict(TOWER, ceiling_m=10)
    path.write_text(json.dumps(bad))
    with pytest.raises(InputError, match=r"world\.envelope: .*town\.json: ceiling_m: 10 m must"):
        world_with(CLOSED_LOOP, [f"envelope={path}"])
    with pytest.raises(InputError, match=r"world\.envelope: .*missing\.json: cannot read"):
        world_with(CLOSED_LOOP, [f"envelope={tmp_path / 'missing.json'}"])
    with pytest.raises(InputError, match=r"^envelope: format: must be"):
        World(envelope={"format": "x"})


def test_world_fly_with_no_envelope_is_fly() -> None:
    rng = np.random.default_rng(0)
    for p, t in zip(rng.uniform(0, 500, (50, 3)), rng.uniform(0, 500, (50, 3)), strict=True):
        assert np.array_equal(CLOSED_LOOP.fly(p, t), fly(p, t, CLOSED_LOOP.flight, 1.0))
        assert np.array_equal(PAPER.fly(p, t), t)


def _world(base: World = CLOSED_LOOP_MOVING, steps: int = 25) -> World:
    return replace(base, episode_steps=steps, envelope=TOWER)


@pytest.mark.parametrize("env_type", [FapContinuousEnv, FapDiscreteEnv])
def test_the_environments_fly_legal_routes(env_type: type) -> None:
    world = _world()
    envelope = world.flight_envelope
    env = env_type(ScenarioSampler(users=(3, 6)), world=world)
    _, info = env.reset(seed=3, options={"uav_xyz_m": [100.0, 50.0, 25.0]})  # inside the hall
    assert envelope.violation(info["uav_xyz_m"]) is None
    rng = np.random.default_rng(1)
    for _ in range(25):
        if env_type is FapContinuousEnv:
            action = rng.uniform(0, 1, 3).astype(np.float32)
        else:
            action = int(rng.choice(np.flatnonzero(env.action_masks())))
        _, _, _, _, info = env.step(action)
        assert envelope.violation(info["target_xyz_m"]) is None
        assert envelope.violation(info["uav_xyz_m"]) is None
    # A target inside the tower is moved out of it, and flown to around the hall.
    env.reset(seed=0, options={"uav_xyz_m": [20.0, 150.0, 30.0]})
    for _ in range(60):
        _, _, _, _, info = env.step_to([250.0, 250.0, 50.0])
    assert envelope.violation(info["target_xyz_m"]) is None
    assert not np.allclose(info["target_xyz_m"], [250.0, 250.0, 50.0])
    assert np.allclose(info["uav_xyz_m"], info["target_xyz_m"])


@pytest.mark.parametrize(
    ("fleet_kind", "single_env"), [("discrete", FapDiscreteEnv), ("continuous", FapContinuousEnv)]
)
def test_one_uav_flies_as_the_single_environment_in_an_envelope(
    fleet_kind: str, single_env: type
) -> None:
    assert_one_uav_flies_as_the_single_environment(
        fleet_kind,
        single_env,
        _world(steps=20),
        ScenarioSampler(families=("mixture",), users=(5, 10)),
        20,
    )


@pytest.mark.parametrize("kind", ["discrete", "continuous"])
def test_the_vectorised_environment_flies_as_the_single_one_in_an_envelope(kind: str) -> None:
    world = replace(_world(steps=8), stochastic=False)
    sampler = ScenarioSampler(users=(2, 4))
    vector = FapVectorEnv(3, kind, scenarios=sampler, world=world)
    singles = [
        (FapDiscreteEnv if kind == "discrete" else FapContinuousEnv)(sampler, world=world)
        for _ in range(3)
    ]
    obs, _ = vector.reset(seed=7)
    for e, single in enumerate(singles):
        single_obs, _ = single.reset(seed=7 + e)
        assert np.array_equal(obs[e], single_obs)
    rng = np.random.default_rng(7)
    for _ in range(7):
        if kind == "discrete":
            actions = rng.integers(0, 13, 3)
        else:
            actions = rng.uniform(0.0, 1.0, (3, 3)).astype(np.float32)
        obs, rewards, _, _, info = vector.step(actions)
        for e, single in enumerate(singles):
            single_obs, reward, _, _, single_info = single.step(actions[e])
            assert reward == rewards[e]
            assert np.array_equal(info["uav_xyz_m"][e], single_info["uav_xyz_m"])
            assert np.array_equal(obs[e], single_obs)


def test_a_fleet_in_an_envelope_keeps_to_it_and_apart() -> None:
    world = _world(CLOSED_LOOP, steps=40)
    envelope = world.flight_envelope
    env = FleetParallelEnv(3, "continuous", scenarios=ScenarioSampler(users=(3, 6)), world=world)
    env.reset(seed=2)
    rng = np.random.default_rng(2)
    same = np.array([0.5, 0.5, 0.1], dtype=np.float32)  # the tower's middle, for everyone
    for step in range(40):
        before = env.uav_xyz_m.copy()
        action = same if step < 20 else None
        actions = {
            a: (same if action is not None else rng.uniform(0, 1, 3).astype(np.float32))
            for a in env.agents
        }
        _, _, _, _, infos = env.step(actions)
        targets = np.stack([infos[a]["target_xyz_m"] for a in env.possible_agents])
        for k in range(3):
            assert envelope.violation(env.uav_xyz_m[k]) is None
            assert envelope.violation(targets[k]) is None
        for i, j in itertools.combinations(range(3), 2):
            floor = min(10.0, float(np.linalg.norm(before[i] - before[j]))) - 1e-6
            assert np.linalg.norm(env.uav_xyz_m[i] - env.uav_xyz_m[j]) >= floor
    assert env.held.dtype == bool and env.held.shape == (3,)
