"""``benchmarks/real_sitl.py``'s count of targets reached, on synthetic tracks (no SITL).

Issue 42: a target counted as reached only when another target followed it, so with one fixed
target (the oracle's, for users that do not move) the driver printed 0 reached while the
vehicle sat on it. Reached means: the vehicle came within the tolerance of the target while it
was the target, whether or not another one followed.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def real_sitl():
    spec = importlib.util.spec_from_file_location("real_sitl", ROOT / "benchmarks" / "real_sitl.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[spec.name]


def _flight(start, end, t0_s, t1_s, step_s=0.5):
    """A straight flight from ``start`` to ``end`` between two times, sampled every step."""
    n = round((t1_s - t0_s) / step_s)
    return [
        (t0_s + k * step_s, tuple(a + (b - a) * k / n for a, b in zip(start, end, strict=True)))
        for k in range(n + 1)
    ]


def test_one_fixed_target_the_vehicle_sits_on_is_reached(real_sitl) -> None:
    target = (137.5, 12.5, 25.0)
    track = _flight((0.0, 0.0, 25.0), target, 0.0, 10.0) + [(t, target) for t in range(11, 60)]
    (outcome,) = real_sitl.reached_targets([(0.0, target)], track, end_s=60.0)
    assert outcome.reached and outcome.closest_m == 0.0
    assert outcome.reached_after_s == 10.0
    assert outcome.held_s == 60.0


def test_a_target_replaced_before_the_vehicle_gets_there_is_not_reached(real_sitl) -> None:
    a, b = (100.0, 0.0, 25.0), (100.0, 50.0, 25.0)
    track = _flight((0.0, 0.0, 25.0), a, 0.0, 10.0, step_s=1.0)  # at (50, 0) after 5 s
    track += _flight(a, b, 11.0, 20.0, step_s=1.0)
    targets = [(0.0, a), (5.0, b)]
    first, second = real_sitl.reached_targets(targets, track, end_s=20.0)
    assert not first.reached and first.reached_after_s is None
    assert first.closest_m == pytest.approx(50.0)  # only the samples while it was the target
    assert second.reached and second.reached_after_s == 15.0


def test_the_tolerance_is_the_distance_in_three_dimensions(real_sitl) -> None:
    target = (10.0, 10.0, 25.0)
    near = [(1.0, (10.0, 10.0, 27.9)), (2.0, (12.0, 12.0, 25.0))]  # 2.9 m, then 2.83 m
    far = [(1.0, (10.0, 10.0, 28.5)), (2.0, (13.0, 10.0, 26.0))]
    assert real_sitl.reached_targets([(0.0, target)], near, end_s=3.0)[0].reached
    (outcome,) = real_sitl.reached_targets([(0.0, target)], far, end_s=3.0)
    assert not outcome.reached and outcome.closest_m == pytest.approx(3.16, abs=0.01)
    assert real_sitl.reached_targets([(0.0, target)], far, end_s=3.0, tolerance_m=3.5)[0].reached
