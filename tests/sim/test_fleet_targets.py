"""The fleet's last step before streaming (:mod:`sim.fleet_targets`), property-tested: the
guard never lets two targets closer than the separation, a target near a vehicle that cannot be
commanded, or a target outside the area volume (the geofence) through, whatever the policy
asked for; the assignment is the least-travel one."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.config import AreaConfig
from sim.envelope.flight import Track, closest_approach_m, fly_route_track
from sim.envelope.volume import Envelope
from sim.fleet_targets import (
    SEPARATION_TOLERANCE_M,
    assign_targets,
    check_targets,
    guard_targets,
    hold_crossing_paths,
    inside_volume,
    path_flight,
    paths_held,
)
from sim.flight import Flight
from sim.geometry import enforce_separation, volume_bounds

AREA = AreaConfig()
SMALL = AreaConfig(size_x_m=60.0, size_y_m=60.0, zone_m=5.0, z_min_m=5.0, z_max_m=20.0)

anywhere = st.floats(-200.0, 800.0, allow_nan=False)  # inside and well outside the volume
point = st.tuples(anywhere, anywhere, st.floats(-50.0, 200.0, allow_nan=False))


def _inside(area: AreaConfig) -> st.SearchStrategy[tuple[float, float, float]]:
    lower, upper = volume_bounds(area)
    return st.tuples(
        *(st.floats(float(lo), float(hi)) for lo, hi in zip(lower, upper, strict=True))
    )


def _min_gap(points: np.ndarray) -> float:
    if len(points) < 2:
        return np.inf
    return min(np.linalg.norm(a - b) for a, b in itertools.combinations(points, 2))


@settings(max_examples=300, deadline=None)
@given(
    wanted=st.lists(point, min_size=1, max_size=8),
    lost=st.lists(_inside(AREA), max_size=3),
    separation_m=st.floats(0.5, 40.0),
)
def test_guarded_targets_are_separated_fenced_and_clear_of_lost_vehicles(
    wanted: list[tuple[float, float, float]],
    lost: list[tuple[float, float, float]],
    separation_m: float,
) -> None:
    targets = guard_targets(np.array(wanted), np.array(lost).reshape(-1, 3), separation_m, AREA)
    assert targets.shape == (len(wanted), 3)
    assert np.all(inside_volume(targets, AREA))
    assert _min_gap(targets) >= separation_m - SEPARATION_TOLERANCE_M
    # Clear of every lost vehicle that is itself clear of the lost ones listed before it
    # (two lost vehicles closer than the separation count as one obstacle: the first).
    kept: list[np.ndarray] = []
    for obstacle in np.array(lost).reshape(-1, 3):
        if all(np.linalg.norm(obstacle - k) >= separation_m for k in kept):
            kept.append(obstacle)
    for obstacle in kept:
        assert np.min(np.linalg.norm(targets - obstacle, axis=1)) >= (
            separation_m - SEPARATION_TOLERANCE_M
        )


@settings(max_examples=200, deadline=None)
@given(wanted=st.lists(_inside(SMALL), min_size=1, max_size=6), separation_m=st.floats(1.0, 10.0))
def test_targets_already_safe_are_streamed_as_asked(
    wanted: list[tuple[float, float, float]], separation_m: float
) -> None:
    targets = np.array(wanted)
    if _min_gap(targets) < separation_m:
        targets = guard_targets(targets, np.empty((0, 3)), separation_m, SMALL)
        assert _min_gap(targets) >= separation_m - SEPARATION_TOLERANCE_M
    else:  # nothing to fix: nothing moves
        np.testing.assert_array_equal(guard_targets(targets, np.empty((0, 3)), separation_m, SMALL),
                                      targets)  # fmt: skip


def test_a_lost_vehicle_on_the_ground_is_no_obstacle() -> None:
    target = np.array([[100.0, 100.0, 25.0]])
    grounded = np.array([[100.0, 100.0, 0.0]])  # below the volume: below every target
    np.testing.assert_array_equal(guard_targets(target, grounded, 10.0, AREA), target)
    hovering = np.array([[100.0, 100.0, 30.0]])  # 5 m from the target: it must move away
    moved = guard_targets(target, hovering, 10.0, AREA)
    assert np.linalg.norm(moved[0] - hovering[0]) >= 10.0 - SEPARATION_TOLERANCE_M


def test_the_check_refuses_what_must_not_be_streamed() -> None:
    with pytest.raises(ValueError, match="apart"):
        check_targets(np.array([[100.0, 100.0, 30.0], [104.0, 100.0, 30.0]]), 10.0, AREA)
    with pytest.raises(ValueError, match="outside"):
        check_targets(np.array([[100.0, 100.0, 10.0]]), 10.0, AREA)
    with pytest.raises(ValueError, match="not finite"):
        check_targets(np.array([[np.nan, 100.0, 30.0]]), 10.0, AREA)
    with pytest.raises(ValueError, match="cannot be commanded"):
        check_targets(np.array([[100.0, 100.0, 30.0]]), 10.0, AREA, np.array([[100, 105, 30.0]]))
    with pytest.raises(ValueError, match="finite"):
        guard_targets(np.array([[100.0, 100.0, 30.0]]), np.array([[np.inf, 0, 30]]), 10.0, AREA)


@settings(max_examples=200, deadline=None)
@given(
    positions=st.lists(_inside(AREA), min_size=1, max_size=6),
    seed=st.integers(0, 2**16),
)
def test_assignment_is_the_least_total_travel(
    positions: list[tuple[float, float, float]], seed: int
) -> None:
    here = np.array(positions)
    targets = np.random.default_rng(seed).permutation(
        np.random.default_rng(seed + 1).uniform(0, 500, here.shape)
    )
    assigned = assign_targets(here, targets)
    # The same targets, each once ...
    assert sorted(map(tuple, assigned)) == sorted(map(tuple, targets))
    # ... in the order no other order beats.
    travel = np.linalg.norm(assigned - here, axis=1).sum()
    for order in itertools.permutations(range(len(here))):
        assert travel <= np.linalg.norm(targets[list(order)] - here, axis=1).sum() + 1e-9


def test_each_vehicle_keeps_the_target_above_it() -> None:
    here = np.array([[100.0, 100.0, 30.0], [400.0, 400.0, 30.0], [100.0, 400.0, 30.0]])
    swapped = here[[2, 0, 1]]
    np.testing.assert_array_equal(assign_targets(here, swapped), here)


# ---------------------------------------------------------------------- the paths


def test_two_flights_that_would_cross_at_once_hold_the_second_vehicle() -> None:
    """Two flights crossing at right angles, both at the crossing 5 s in: the second vehicle
    holds; when it starts farther away (there after the first has passed), both fly; swapping
    places head on, each would end where the other is: both hold."""
    flight = Flight(10.0, 3.0)
    positions = np.array([[100.0, 250.0, 50.0], [150.0, 200.0, 50.0]])
    targets = np.array([[200.0, 250.0, 50.0], [150.0, 300.0, 50.0]])
    assert paths_held([None, None], positions, targets, flight, 10.0) == (False, True)
    later = np.array([[100.0, 250.0, 50.0], [150.0, 100.0, 50.0]])
    assert paths_held([None, None], later, targets, flight, 10.0) == (False, False)
    swap = np.array([[100.0, 250.0, 50.0], [200.0, 250.0, 50.0]])
    assert paths_held([None, None], swap, swap[::-1], flight, 10.0) == (True, True)


def test_the_flight_speed_is_the_worlds_capped_by_the_envelopes() -> None:
    slow = Envelope.for_area(AREA, max_speed_mps=4.0)
    assert path_flight(Flight(None, None), [None]) == Flight(10.0, 3.0)
    assert path_flight(Flight(12.0, 2.0), [slow, None]) == Flight(4.0, 2.0)


@settings(max_examples=150, deadline=None)
@given(
    starts=st.lists(_inside(SMALL), min_size=2, max_size=4),
    wanted=st.lists(_inside(SMALL), min_size=4, max_size=4),
    separation_m=st.floats(2.0, 8.0),
)
def test_the_flights_that_go_keep_the_separation_at_every_instant(
    starts: list[tuple[float, float, float]],
    wanted: list[tuple[float, float, float]],
    separation_m: float,
) -> None:
    """Whatever the targets: the held vehicles stay, the others fly their predicted tracks, and
    no two come closer than the separation (or than they started) at any instant."""
    flight = Flight(5.0, 2.0)
    positions = np.array(starts)
    targets = np.array(wanted[: len(starts)])
    held = paths_held([None] * len(starts), positions, targets, flight, separation_m, 60.0)
    tracks = [
        Track.still(tuple(p), 60.0) if h else fly_route_track(None, p, t, flight, 60.0).track
        for h, p, t in zip(held, positions.tolist(), targets.tolist(), strict=True)
    ]
    for i, j in itertools.combinations(range(len(starts)), 2):
        floor = min(separation_m, float(np.linalg.norm(positions[i] - positions[j])))
        assert closest_approach_m(tracks[i], tracks[j]) >= floor - 1e-6


def test_a_vehicle_held_behind_a_hovering_one_goes_round_it_and_gets_there() -> None:
    """A straight flight that passes 8.9 m from a vehicle hovering over its own target would be
    held at every decision, for ever (found on the held-out grid): the vehicle goes round the
    hovering one instead, decision after decision, never within the separation of it, and
    reaches its target."""
    hovering = np.array([306.6, 339.6, 25.0])
    other = np.array([370.5, 327.5, 25.0])
    here, goal = np.array([237.5, 262.5, 25.0]), np.array([325.9, 380.1, 25.0])
    flight = Flight(10.0, 3.0)
    assert paths_held(
        [None] * 3, np.array([hovering, other, here]), np.array([hovering, other, goal]), flight,
        10.0,
    ) == (False, False, True)  # fmt: skip
    for _ in range(40):  # decisions 1 s apart, the vehicle flying 10 m/s straight at its target
        holds = hold_crossing_paths(
            [None] * 3, np.array([hovering, other, here]), np.array([hovering, other, goal]),
            flight, 10.0, AREA,
        )  # fmt: skip
        assert not any(holds.held)
        target = holds.targets_m[2]
        step = target - here
        distance = float(np.linalg.norm(step))
        track = fly_route_track(None, here, target, flight, 300.0).track
        assert closest_approach_m(track, Track.still(tuple(hovering), 300.0)) >= 10.0 - 1e-6
        here = target if distance <= 10.0 else here + step / distance * 10.0
        if np.linalg.norm(here - goal) < 1e-6:
            break
    np.testing.assert_allclose(here, goal)


@settings(max_examples=100, deadline=None)
@given(
    starts=st.lists(_inside(SMALL), min_size=2, max_size=4),
    wanted=st.lists(_inside(SMALL), min_size=4, max_size=4),
)
def test_holds_and_detours_keep_the_separation_at_every_instant(
    starts: list[tuple[float, float, float]], wanted: list[tuple[float, float, float]]
) -> None:
    """The targets :func:`hold_crossing_paths` gives (held, sent round a hovering vehicle, or as
    asked), flown as predicted, keep the separation (or the distance they start at) at every
    instant — unless it says it skipped the holds."""
    flight, separation_m = Flight(5.0, 2.0), 5.0
    positions = np.array(starts)
    targets = enforce_separation(np.array(wanted[: len(starts)]), separation_m, SMALL)
    holds = hold_crossing_paths(
        [None] * len(starts), positions, targets, flight, separation_m, SMALL
    )
    if holds.skipped:
        return
    tracks = [
        fly_route_track(None, p, t, flight, 300.0).track
        for p, t in zip(positions.tolist(), holds.targets_m.tolist(), strict=True)
    ]
    for i, j in itertools.combinations(range(len(starts)), 2):
        floor = min(separation_m, float(np.linalg.norm(positions[i] - positions[j])))
        assert closest_approach_m(tracks[i], tracks[j]) >= floor - 1e-6
