"""A fleet's targets before anything flies to them: who flies where, the safety guard and the
paths — one rule for the world (:class:`sim.fleet_env.FleetParallelEnv`, so training and
evaluation) and the service (:class:`service.fleet_placement.FleetPlacementService`).

Pure functions, property-tested (``tests/sim/test_fleet_targets.py``, hypothesis):

* :func:`sim.geometry.assign_targets` (re-exported): which vehicle takes which of the policy's
  targets: the assignment with the least total flight distance, exact (every permutation).
* :func:`guard_targets`: the separation guard. Every two targets at least ``separation_m``
  apart in 3-D, every target at least that far from where each vehicle that cannot be commanded
  was last seen (a lost vehicle may still be flying there: ArduPilot holds its last target),
  all inside the area volume (the geofence). Targets move as little as
  :func:`sim.geometry.enforce_separation`'s rule allows; those obstacles have priority.
* :func:`check_targets`: the final check, raising rather than letting a violation be streamed.
* :func:`paths_held`: the paths. Which vehicles hold where they are for this decision so that
  the flights from where the vehicles are to their targets keep the separation at every
  instant (:func:`sim.envelope.flight.separate_tracks` over the whole flight, not one period):
  each flight is predicted along the route its link streams
  (:func:`sim.envelope.flight.fly_route_track`) at :func:`path_flight`'s speed caps;
  :func:`hold_crossing_paths` applies it to a decision's targets.

A lost vehicle's last position counts as an obstacle only while it lies inside the volume (a
vehicle that never took off, or landed, is below every target). The paths are predicted, not
measured: a vehicle much slower or faster than the speed caps can meet another where the
prediction had one pass before the other; the check is made again at every decision from where
the vehicles are, and the targets' separation holds whatever the timing.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from shapely.geometry import Point

from sim.config import AreaConfig
from sim.envelope.flight import fly_route_track, legal_position, separate_tracks
from sim.envelope.route import plan_route
from sim.envelope.volume import Envelope, Exclusion
from sim.flight import Flight
from sim.geometry import assign_targets, enforce_separation, volume_bounds

__all__ = [
    "PATH_HORIZON_S",
    "SEPARATION_TOLERANCE_M",
    "PathHolds",
    "assign_targets",
    "check_targets",
    "detour_around",
    "guard_targets",
    "hold_crossing_paths",
    "inside_volume",
    "path_flight",
    "paths_held",
]

PATH_HORIZON_S = 300.0
"""How far ahead the paths are predicted: long enough for any flight across the area."""

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


def path_flight(flight: Flight, envelopes: Sequence[Envelope | None]) -> Flight:
    """The speed caps the paths are predicted with: the world's flight (its default's,
    10 m/s and 3 m/s, where the world teleports), the horizontal one no faster than any
    envelope's ``max_speed_mps``."""
    horizontal = flight.horizontal_mps or Flight().horizontal_mps
    vertical = flight.vertical_mps or Flight().vertical_mps
    for envelope in envelopes:
        if envelope is not None:
            horizontal = min(horizontal, envelope.max_speed_mps)  # type: ignore[type-var]
    return Flight(horizontal, vertical)


def paths_held(
    envelopes: Sequence[Envelope | None],
    positions_m: np.ndarray,
    targets_m: np.ndarray,
    flight: Flight,
    separation_m: float,
    horizon_s: float = PATH_HORIZON_S,
) -> tuple[bool, ...]:
    """Which of K vehicles at ``positions_m`` (K, 3) hold where they are, instead of flying to
    ``targets_m`` (K, 3) in their ``envelopes``, so that no two flights come closer than
    ``separation_m`` (or closer than they start) within ``horizon_s`` (module doc). Lower
    indices fly first. Pure."""
    positions = np.asarray(positions_m, dtype=float).reshape(-1, 3)
    targets = np.asarray(targets_m, dtype=float).reshape(-1, 3)
    tracks = [
        fly_route_track(envelope, p, t, flight, horizon_s).track
        for envelope, p, t in zip(envelopes, positions.tolist(), targets.tolist(), strict=True)
    ]
    starts = [(p[0], p[1], p[2]) for p in positions.tolist()]
    return separate_tracks(starts, tracks, separation_m, horizon_s)


STILL_M = 1.0
"""A vehicle whose target is within this of where it is hovers (or holds) for the decision: a
flight held behind it would wait for ever, so it goes round (:func:`detour_around`)."""
DETOUR_MARGIN = 1.05
"""A hovering vehicle is gone round at this many separations (its circle's 16-gon stays
outside the separation)."""


def detour_around(
    envelope: Envelope | None,
    area: AreaConfig,
    position_m: Sequence[float],
    target_m: Sequence[float],
    hovering_m: np.ndarray,
    separation_m: float,
) -> tuple[float, float, float] | None:
    """Where a vehicle at ``position_m`` flies now to get round the vehicles hovering at
    ``hovering_m`` (M, 3) on its way to ``target_m``: the first waypoint of the route that keeps
    ``DETOUR_MARGIN`` separations from each of them (a column of that radius, that much above
    and below it, as a no-fly volume of its envelope: the route goes round or over it); None
    when there is no such route or it is the straight flight."""
    base = envelope if envelope is not None else Envelope.for_area(area)
    radius_m = DETOUR_MARGIN * separation_m
    columns = tuple(
        Exclusion(
            Point(float(p[0]), float(p[1])).buffer(radius_m, quad_segs=4),
            float(p[2]) - radius_m,
            float(p[2]) + radius_m,
            name="a hovering vehicle",
            on_autopilot_fence=False,
        )
        for p in np.asarray(hovering_m, dtype=float).reshape(-1, 3)
    )
    if not columns:
        return None
    around = Envelope(
        base.inclusion, base.floor_m, base.ceiling_m, base.exclusions + columns,
        base.clearance_m, base.max_speed_mps,
    )  # fmt: skip
    route = plan_route(around, position_m, target_m)
    if route.holding or route.kind == "direct" or route.target_m is None:
        return None
    x_m, y_m, z_m = route.setpoint_m
    return (x_m, y_m, z_m)


class PathHolds(NamedTuple):
    """What :func:`hold_crossing_paths` decided."""

    targets_m: np.ndarray
    """The targets to fly (K, 3): a held vehicle's is where it is."""
    held: tuple[bool, ...]
    """Which vehicles hold for this decision."""
    skipped: bool
    """Whether holds were needed but none was made (two vehicles already that close)."""
    detoured: tuple[bool, ...]
    """Which vehicles, held behind a hovering one, fly a detour round it instead."""


def hold_crossing_paths(
    envelopes: Sequence[Envelope | None],
    positions_m: np.ndarray,
    targets_m: np.ndarray,
    flight: Flight,
    separation_m: float,
    area: AreaConfig,
    obstacles_m: np.ndarray | None = None,
) -> PathHolds:
    """``targets_m`` (K, 3) for the vehicles at ``positions_m`` (K, 3) in their
    ``envelopes``, each vehicle whose flight there would come too close to another's
    (:func:`paths_held`, at :func:`path_flight`'s caps of ``flight``) held where it is for this
    decision (its target: its position, made legal in its envelope) — or, held behind vehicles
    that hover or hold, sent along the first leg of the route round them
    (:func:`detour_around`) when that leg keeps clear of every other flight. When holding would
    leave two targets (or a target and one of the ``obstacles_m``) under the separation or
    outside the volume — two vehicles that already met that close, holding each other in place —
    nothing is held, and that is said (``skipped``). Pure."""
    targets = np.asarray(targets_m, dtype=float).reshape(-1, 3)
    positions = np.asarray(positions_m, dtype=float).reshape(-1, 3)
    caps = path_flight(flight, envelopes)
    held = paths_held(envelopes, positions, targets, caps, separation_m)
    none = (False,) * len(targets)
    if not any(held):
        return PathHolds(targets, held, False, none)
    wanted = targets.copy()
    detoured = [False] * len(targets)
    for k in [k for k, h in enumerate(held) if h]:
        out = _holding(envelopes, positions, wanted, held)
        hovering = [j for j in range(len(out)) if j != k and _still(positions[j], out[j])]
        detour = detour_around(
            envelopes[k], area, positions[k], targets[k], positions[hovering], separation_m
        )
        if detour is None:
            continue
        trial = wanted.copy()
        trial[k] = detour
        if not paths_held(envelopes, positions, trial, caps, separation_m)[k]:
            wanted, detoured[k] = trial, True
    held = paths_held(envelopes, positions, wanted, caps, separation_m)
    out = _holding(envelopes, positions, wanted, held)
    try:
        check_targets(out, separation_m, area, obstacles_m)
    except ValueError:
        return PathHolds(targets, none, True, none)
    went = tuple(d and not h for d, h in zip(detoured, held, strict=True))
    return PathHolds(out, held, False, went)


def _holding(
    envelopes: Sequence[Envelope | None],
    positions: np.ndarray,
    targets: np.ndarray,
    held: Sequence[bool],
) -> np.ndarray:
    """``targets`` with each held vehicle's replaced by where it is (made legal)."""
    out = targets.copy()
    for k, envelope in enumerate(envelopes):
        if held[k]:
            out[k] = legal_position(envelope, positions[k])
    return out


def _still(position: np.ndarray, target: np.ndarray) -> bool:
    return bool(np.linalg.norm(np.asarray(target) - np.asarray(position)) < STILL_M)
