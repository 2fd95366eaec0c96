"""The geometric median and the min-distance / load-weighted baselines."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from policies.interface import Placement
from policies.placements.baselines import MinDistancePlacement, geometric_median
from policies.registry import PLACEMENTS, make_placement
from sim.config import AreaConfig
from sim.scenarios import Scenario
from sim.world import PAPER

AREA = AreaConfig()
HEIGHT_M = AREA.z_min_m - AREA.user_height_m

coordinate = st.floats(0.0, 500.0, allow_nan=False)
point = st.tuples(coordinate, coordinate)
weight = st.floats(0.0, 1e8, allow_nan=False)


def objective(p: np.ndarray, points: np.ndarray, weights: np.ndarray, height_m: float) -> float:
    return float(np.sum(weights * np.sqrt(np.sum((points - p) ** 2, axis=1) + height_m**2)))


def assert_locally_optimal(
    p: np.ndarray, points: np.ndarray, weights: np.ndarray, height_m: float
) -> None:
    """No point 0.05 m or 1 m away in 16 directions, and no user, does better (to rounding)."""
    best = objective(p, points, weights, height_m)
    angles = np.linspace(0.0, 2.0 * np.pi, 16, endpoint=False)
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    others = [*points, *(p + 0.05 * directions), *(p + 1.0 * directions)]
    slack = 1e-6 * max(best, 1.0)
    for q in others:
        assert best <= objective(q, points, weights, height_m) + slack


@pytest.mark.parametrize("height_m", [0.0, HEIGHT_M])
def test_single_user_is_its_own_median(height_m: float) -> None:
    assert np.allclose(geometric_median(np.array([[123.0, 45.0]]), height_m=height_m), [123, 45])


@settings(max_examples=40, deadline=None)
@given(a=point, b=point, height_m=st.sampled_from([0.0, HEIGHT_M]))
def test_two_equal_users_median_on_the_segment(a, b, height_m) -> None:
    points = np.array([a, b])
    p = geometric_median(points, height_m=height_m)
    length = np.linalg.norm(points[1] - points[0])
    # On the segment: the two distances add up to its length.
    assert np.linalg.norm(p - points[0]) + np.linalg.norm(p - points[1]) <= length + 1e-6
    if height_m > 0:  # strictly convex: the midpoint, exactly
        assert np.allclose(p, points.mean(axis=0), atol=1e-6)


@pytest.mark.parametrize("height_m", [0.0, HEIGHT_M])
def test_symmetric_square_median_is_its_centre(height_m: float) -> None:
    square = np.array([[100.0, 100.0], [300.0, 100.0], [300.0, 300.0], [100.0, 300.0]])
    assert np.allclose(geometric_median(square, height_m=height_m), [200.0, 200.0], atol=1e-3)


def test_user_at_the_start_is_handled_and_can_be_the_median() -> None:
    # The centroid (the first iterate) is exactly the middle user, the median of collinear users.
    collinear = np.array([[0.0, 0.0], [10.0, 0.0], [-10.0, 0.0]])
    assert np.array_equal(geometric_median(collinear), [0.0, 0.0])
    # The centroid is a user that is *not* the median: the iteration must step off it.
    points = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 1.0], [20.0, -1.0], [-60.0, 0.0]])
    p = geometric_median(points)
    assert np.all(np.isfinite(p))
    assert p[0] > 15.0  # pulled off the start toward the three close users
    assert_locally_optimal(p, points, np.ones(5), 0.0)


def test_dominant_weight_pulls_the_ground_median_onto_its_user() -> None:
    # A user holding more than half the weight is the weighted geometric median (ground metric).
    points = np.array([[50.0, 50.0], [400.0, 80.0], [200.0, 450.0]])
    p = geometric_median(points, np.array([3.0, 1.0, 1.0]))
    assert np.allclose(p, points[0], atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(
    points=st.lists(point, min_size=1, max_size=8),
    data=st.data(),
    height_m=st.sampled_from([0.0, HEIGHT_M]),
)
def test_median_is_a_minimiser(points, data, height_m) -> None:
    xy = np.array(points)
    weights = np.array(data.draw(st.lists(weight, min_size=len(xy), max_size=len(xy))))
    p = geometric_median(xy, weights, height_m=height_m)
    used = weights if weights.sum() > 0 else np.ones(len(xy))
    assert_locally_optimal(p, xy, used / used.sum(), height_m)


@settings(max_examples=40, deadline=None)
@given(
    points=st.lists(point, min_size=2, max_size=6, unique=True),
    heavy=st.integers(0, 5),
    factor=st.floats(2.0, 50.0),
)
def test_load_weighted_moves_toward_the_heavy_user(points, heavy, factor) -> None:
    xy = np.array(points)
    heavy %= len(xy)
    load = np.full(len(xy), 1e6)
    load[heavy] *= factor
    scenario = Scenario("s", xy, load)
    plain = MinDistancePlacement(AREA).place(scenario)
    weighted = MinDistancePlacement(AREA, load_weighted=True).place(scenario)
    # Raising one user's weight never moves the (unique, 3-D) minimiser away from that user.
    assert np.linalg.norm(weighted[:2] - xy[heavy]) <= np.linalg.norm(plain[:2] - xy[heavy]) + 1e-3


@settings(max_examples=60, deadline=None)
@given(
    points=st.lists(point, min_size=1, max_size=6),
    data=st.data(),
    name=st.sampled_from(["min-distance", "load-weighted"]),
)
def test_baseline_positions_lie_in_the_volume_at_minimum_altitude(points, data, name) -> None:
    xy = np.array(points)
    loads = data.draw(st.lists(st.floats(1.0, 4e7), min_size=len(xy), max_size=len(xy)))
    position = make_placement(name).place(Scenario("s", xy, np.array(loads)))
    assert position.shape == (3,)
    assert 0.0 <= position[0] <= AREA.size_x_m
    assert 0.0 <= position[1] <= AREA.size_y_m
    assert position[2] == AREA.z_min_m


def test_registry_and_unknown_name() -> None:
    assert list(PLACEMENTS) == ["min-distance", "load-weighted", "min-distance-env", "oracle"]
    for name in PLACEMENTS:
        policy = make_placement(name, replace(PAPER, episode_steps=5))
        assert policy.name == name
        assert isinstance(policy, Placement)
    with pytest.raises(ValueError, match="min-distance, load-weighted, min-distance-env, oracle"):
        make_placement("nearest")


def test_bad_weights_are_rejected() -> None:
    with pytest.raises(ValueError, match="weights"):
        geometric_median(np.zeros((2, 2)), np.array([1.0, -1.0]))
    with pytest.raises(ValueError, match="weights"):
        geometric_median(np.zeros((2, 2)), np.array([1.0]))
