"""The last step before a fleet's targets are streamed: who flies where, and the safety guard.

Pure functions, property-tested (``tests/service/test_fleet_targets.py``, hypothesis):

* :func:`sim.geometry.assign_targets` (re-exported): which vehicle takes which of the policy's
  targets: the assignment with the least total flight distance, exact (every permutation).
* :func:`guard_targets`: the separation guard. Every two targets at least ``separation_m``
  apart in 3-D, every target at least that far from where each vehicle that cannot be commanded
  was last seen (a lost vehicle may still be flying there: ArduPilot holds its last target),
  all inside the area volume (the geofence). Targets move as little as
  :func:`sim.geometry.enforce_separation`'s rule allows; those obstacles have priority.
* :func:`check_targets`: the final check, raising rather than letting a violation be streamed.

A lost vehicle's last position counts as an obstacle only while it lies inside the volume (a
vehicle that never took off, or landed, is below every target). The guard is about targets; the
paths between them are the autopilots' business (their own avoidance, if any).
"""

from __future__ import annotations

import numpy as np

from sim.config import AreaConfig
from sim.geometry import assign_targets, enforce_separation, volume_bounds

__all__ = [
    "SEPARATION_TOLERANCE_M",
    "assign_targets",
    "check_targets",
    "guard_targets",
    "inside_volume",
]

SEPARATION_TOLERANCE_M = 1e-6
"""How far below ``separation_m`` two checked targets may be (floating-point rounding)."""


def inside_volume(points_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Which of the points (N, 3) lie inside the area volume (N,)."""
    lower, upper = volume_bounds(area)
    points = np.asarray(points_m, dtype=float).reshape(-1, 3)
    return np.all((points >= lower) & (points <= upper), axis=1)


def guard_targets(
    targets_m: np.ndarray,
    obstacles_m: np.ndarray,
    separation_m: float,
    area: AreaConfig,
) -> np.ndarray:
    """``targets_m`` (K, 3) made safe to stream (module doc): separated from one another and
    from the obstacles (M, 3) inside the volume, all inside the volume. ValueError when the
    volume cannot hold them (a separation absurd for the area) or for non-finite input."""
    targets = np.asarray(targets_m, dtype=float).reshape(-1, 3)
    obstacles = np.asarray(obstacles_m, dtype=float).reshape(-1, 3)
    if not np.all(np.isfinite(obstacles)):
        raise ValueError("obstacles_m: must be finite positions")
    obstacles = obstacles[inside_volume(obstacles, area)]
    # Obstacles first: lower indices keep their places. Two obstacles closer than the
    # separation are merged into the first (they cannot both be kept in place).
    kept: list[np.ndarray] = []
    for point in obstacles:
        if all(np.linalg.norm(point - other) >= separation_m for other in kept):
            kept.append(point)
    fixed = np.array(kept).reshape(-1, 3)
    combined = enforce_separation(np.concatenate([fixed, targets]), separation_m, area)
    guarded = combined[len(fixed) :]
    check_targets(guarded, separation_m, area, fixed)
    return guarded


def check_targets(
    targets_m: np.ndarray,
    separation_m: float,
    area: AreaConfig,
    obstacles_m: np.ndarray | None = None,
) -> None:
    """ValueError unless every target is finite and inside the volume, and every two targets
    (and every target and obstacle) are at least ``separation_m`` apart."""
    targets = np.asarray(targets_m, dtype=float).reshape(-1, 3)
    if not np.all(np.isfinite(targets)):
        raise ValueError("targets: not finite")
    if not np.all(inside_volume(targets, area)):
        raise ValueError("targets: outside the area volume")
    floor = separation_m - SEPARATION_TOLERANCE_M
    gap = np.linalg.norm(targets[:, None, :] - targets[None, :, :], axis=-1)
    np.fill_diagonal(gap, np.inf)
    if gap.size and gap.min() < floor:
        raise ValueError(f"targets: two are {gap.min():.3f} m apart, under {separation_m} m")
    if obstacles_m is not None and len(obstacles_m):
        clearance = np.linalg.norm(targets[:, None, :] - np.asarray(obstacles_m)[None], axis=-1)
        if clearance.min() < floor:
            raise ValueError(
                f"targets: one is {clearance.min():.3f} m from a vehicle that cannot be "
                f"commanded, under {separation_m} m"
            )
