"""Targets and paths inside an :class:`~sim.envelope.volume.Envelope`.

* :func:`legal_target`: the target itself when it is legal, else the nearest legal point found
  by moving it into the altitude band, into the inclusion, and out of (or over) any exclusion —
  or None when there is none nearby (the caller holds).
* :func:`plan_path`: how to fly from where the vehicle is to a legal target without ever leaving
  the envelope: straight when the segment is legal; else over the exclusions in the way (climb,
  cross, descend) when the ceiling allows; else around them at the current height, along the
  shortest path of a visibility graph over the corners of the exclusions' footprints grown by
  the clearance plus :data:`CORNER_MARGIN_M`. A :class:`Hold` says why there is no path.

Every leg of a returned path is checked with :meth:`Envelope.leg_violation` (the straight
segment, and every way an autopilot that reaches height and position at separate speeds may fly
it), so a path is never returned that leaves the envelope.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString, Point
from shapely.ops import nearest_points

from sim.envelope.volume import EDGE_EPS_M, Envelope, Vec3

CORNER_MARGIN_M = 0.5
"""How far outside the grown footprints the path's corners lie (so legs touch nothing)."""
CORRIDOR_M = 80.0
"""Exclusions this close to the straight line give the detour's corners first (all do when
those leave no way)."""
OVER_MARGIN_M = 1.0
"""How far above the highest blocking exclusion (plus clearance) a climb-over flies."""
PUSH_STEPS = 4
"""How many times :func:`legal_target` moves a point before it gives up."""


@dataclass(frozen=True)
class Hold:
    """No legal way there: the vehicle holds where it is, and this says why."""

    reason: str


@dataclass(frozen=True)
class FlightPath:
    """Waypoints from (excluding) the start to (including) the target; every leg is legal."""

    waypoints: tuple[Vec3, ...]
    kind: str
    """``direct``, ``over`` (climb over exclusions) or ``around`` (a detour at one height)."""

    @property
    def length_m(self) -> float:
        return sum(
            math.dist(a, b) for a, b in zip(self.waypoints, self.waypoints[1:], strict=False)
        )


def legal_target(envelope: Envelope, target_m: Sequence[float]) -> Vec3 | None:
    """``target_m`` when it is legal; else the nearest legal point found by moving it into the
    altitude band and the inclusion and out of every exclusion (over it when the ceiling allows
    and that is nearer); None when a few such moves find none."""
    x_m, y_m, z_m = (float(v) for v in target_m)
    if not all(math.isfinite(v) for v in (x_m, y_m, z_m)):
        return None
    point = (x_m, y_m, min(max(z_m, envelope.floor_m), envelope.ceiling_m))
    for _ in range(PUSH_STEPS):
        if envelope.violation(point) is None:
            return point
        point = _push(envelope, point)
    return point if envelope.violation(point) is None else None


def _push(envelope: Envelope, point: Vec3) -> Vec3:
    x_m, y_m, z_m = point
    allowed = envelope.allowed_footprint
    if allowed.is_empty:
        return point
    here = Point(x_m, y_m)
    if not allowed.covers(here):
        # The nearest point of the allowed footprint (on its edge, which is legal); where
        # rounding leaves that a hair outside, the nearest point a little further in.
        _, nearest = nearest_points(here, allowed)
        if not envelope.room.covers(nearest):
            inner = allowed.buffer(-CORNER_MARGIN_M)
            _, nearest = nearest_points(here, inner if not inner.is_empty else allowed)
        return (nearest.x, nearest.y, z_m)
    for grown, low, high in envelope.grown:
        if not (low < z_m < high and grown.buffer(EDGE_EPS_M).intersects(here)):
            continue
        over_z = high + OVER_MARGIN_M
        # Out to the side, but never out of the inclusion: the nearest allowed point at least
        # CORNER_MARGIN_M off this footprint.
        free = allowed.difference(grown.buffer(CORNER_MARGIN_M, join_style="mitre"))
        sideways = math.inf
        if not free.is_empty:
            _, nearest = nearest_points(here, free)
            sideways = math.hypot(nearest.x - x_m, nearest.y - y_m)
        if over_z <= envelope.ceiling_m and over_z - z_m <= sideways:
            return (x_m, y_m, over_z)
        if math.isinf(sideways):
            return point
        return (nearest.x, nearest.y, z_m)
    return point


def plan_path(
    envelope: Envelope, start_m: Sequence[float], target_m: Sequence[float]
) -> FlightPath | Hold:
    """A legal way from ``start_m`` to the legal ``target_m`` (see the module docstring)."""
    start = tuple(float(v) for v in start_m)
    target = tuple(float(v) for v in target_m)
    if (why := envelope.violation(target)) is not None:
        return Hold(f"the target is not legal: {why}")
    if (why := envelope.violation(start)) is not None:
        return Hold(f"the vehicle is outside its envelope ({why}): it holds until moved back")
    if envelope.leg_violation(start, target) is None:
        return FlightPath((target,), "direct")  # type: ignore[arg-type]
    if envelope.segment_violation(start, target) is None:
        # Straight is legal but the autopilot's own way of flying it may not be: height first
        # when climbing, position first when descending (else the other way round).
        up = target[2] > start[2]
        first = (start[0], start[1], target[2]) if up else (target[0], target[1], start[2])
        other = (target[0], target[1], start[2]) if up else (start[0], start[1], target[2])
        for corner in (first, other):
            path = _checked(envelope, start, [corner, target], "direct")  # type: ignore[list-item]
            if path is not None:
                return path
    over = _over(envelope, start, target)  # type: ignore[arg-type]
    around = _around(envelope, start, target)  # type: ignore[arg-type]
    options = [p for p in (over, around) if p is not None]
    if not options:
        return Hold("no legal path to the target: exclusions block every way at this height")
    return min(options, key=lambda p: p.length_m + math.dist(start, p.waypoints[0]))


def _checked(
    envelope: Envelope, start: Vec3, waypoints: list[Vec3], kind: str
) -> FlightPath | None:
    legs = [start, *waypoints]
    for a, b in itertools.pairwise(legs):
        if envelope.leg_violation(a, b) is not None:
            return None
    return FlightPath(tuple(waypoints), kind)


def _over(envelope: Envelope, start: Vec3, target: Vec3) -> FlightPath | None:
    """Climb above every exclusion in the way, cross, and descend onto the target."""
    z_over = max(start[2], target[2])
    for _ in range(len(envelope.exclusions) + 1):
        up, across = (start[0], start[1], z_over), (target[0], target[1], z_over)
        blocking = {
            *envelope.blocking(start, up),
            *envelope.blocking(up, across),
            *envelope.blocking(across, target),
        }
        if not blocking:
            break
        z_over = max(envelope.grown[i][2] for i in blocking) + OVER_MARGIN_M
        if z_over > envelope.ceiling_m:
            return None
    waypoints = [
        w for w in ((start[0], start[1], z_over), (target[0], target[1], z_over)) if w != start
    ]
    if waypoints and waypoints[-1] != target:
        waypoints.append(target)
    return _checked(envelope, start, waypoints or [target], "over")


def _around(envelope: Envelope, start: Vec3, target: Vec3) -> FlightPath | None:
    """At the start's height, the shortest detour through the corners of the grown footprints
    near the straight line (within :data:`CORRIDOR_M`), or of all of them when that finds none;
    then straight to the target (its own height)."""
    z_m = start[2]
    active = tuple(envelope.obstacles_at(z_m))
    line = LineString([start[:2], target[:2]])
    near = tuple(i for i in active if envelope.grown[i][0].distance(line) <= CORRIDOR_M)
    route = _detour(envelope, start, target, near, active)
    if route is None and near != active:
        route = _detour(envelope, start, target, active, active)
    if route is None:
        return None
    waypoints: list[Vec3] = [(x, y, z_m) for x, y in route]
    last = (target[0], target[1], z_m)
    if last != target:
        waypoints.append(last)
    waypoints.append(target)
    return _checked(envelope, start, waypoints, "around")


def _detour(
    envelope: Envelope,
    start: Vec3,
    target: Vec3,
    around: tuple[int, ...],
    active: tuple[int, ...],
) -> list[tuple[float, float]] | None:
    """The corners (x, y) of the shortest way from ``start`` to above/below ``target`` through
    the corners of the exclusions ``around`` that avoids every exclusion ``active`` at this
    height; None when there is none."""
    corners: list[tuple[float, float]] = []
    for i in around:
        ring = envelope.grown[i][0].buffer(CORNER_MARGIN_M, join_style="mitre")
        for polygon in getattr(ring, "geoms", [ring]):
            corners.extend(polygon.exterior.coords[:-1])
    nodes = np.array([start[:2], *corners, target[:2]], dtype=float)
    n = len(nodes)
    i_idx, j_idx = np.triu_indices(n, k=1)
    lines = shapely.linestrings(np.stack([nodes[i_idx], nodes[j_idx]], axis=1))
    free = shapely.covered_by(lines, envelope.room)
    if active:
        hit = envelope.solid_tree(active).query(lines, predicate="intersects")[0]
        free[hit] = False
    lengths = np.hypot(*(nodes[i_idx] - nodes[j_idx]).T)
    graph: list[list[tuple[int, float]]] = [[] for _ in range(n)]
    for i, j, length in zip(i_idx[free], j_idx[free], lengths[free], strict=True):
        graph[i].append((j, length))
        graph[j].append((i, length))
    route = _shortest(graph, 0, n - 1)
    if route is None:
        return None
    return [(float(nodes[k][0]), float(nodes[k][1])) for k in route[1:-1]]


def _shortest(graph: list[list[tuple[int, float]]], source: int, goal: int) -> list[int] | None:
    """Dijkstra over ``graph``: the node indices from ``source`` to ``goal``, or None."""
    best = {source: 0.0}
    previous: dict[int, int] = {}
    queue = [(0.0, source)]
    while queue:
        cost, node = heapq.heappop(queue)
        if node == goal:
            route = [goal]
            while route[-1] != source:
                route.append(previous[route[-1]])
            return route[::-1]
        if cost > best.get(node, math.inf):
            continue
        for nxt, length in graph[node]:
            new = cost + length
            if new < best.get(nxt, math.inf):
                best[nxt] = new
                previous[nxt] = node
                heapq.heappush(queue, (new, nxt))
    return None
