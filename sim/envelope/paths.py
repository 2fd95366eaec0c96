"""Targets and paths inside an :class:`~sim.envelope.volume.Envelope`.

* :func:`legal_target`: the target itself when it is legal, else the nearest legal point found
  by moving it into the altitude band, into the inclusion, and out of (or over) any exclusion —
  or None when there is none nearby (the caller holds).
* :func:`plan_path`: how to fly from where the vehicle is to a legal target without ever leaving
  the envelope: straight when the segment is legal; else over the exclusions in the way (climb,
  cross, descend) when the ceiling allows; else around them at the current height, along the
  shortest path of a visibility graph over the convex corners of the exclusions' footprints
  grown by the clearance plus :data:`CORNER_MARGIN_M` (corners at most
  :data:`CORNER_EDGE_MAX_M` apart linked first, all when that finds no way and they are few; the
  graph kept per envelope and height band). A
  :class:`Hold` says why there is no path.

Every leg of a returned path is checked with :meth:`Envelope.leg_violation` (the straight
segment, and every way an autopilot that reaches height and position at separate speeds may fly
it), so a path is never returned that leaves the envelope.
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Point
from shapely.ops import nearest_points

from sim.envelope.volume import Envelope, Vec3

CORNER_MARGIN_M = 0.5
"""How far outside the grown footprints the path's corners lie (so legs touch nothing)."""
CORNER_EDGE_MAX_M = 100.0
"""The longest edge between two corners of the detour graph tried first (a longer clear way
goes through corners between; the start's and the target's edges have no limit; with no way
found, every corner is linked). Bounds the graph's cost over a district: hundreds of corners at
the lowest level."""
SIMPLIFY_CORNERS_M = 1.0
"""How far outward a footprint's outline may move for its corners to become fewer (a curved
outline's many corners are the graph's cost; the simplified outline is used only where it covers
the grown footprint, so the corners stay outside it)."""
VISIBILITY_CHUNK = 50_000
"""Segments tested at once when a detour graph is built (bounds its memory)."""
FULL_GRAPH_MAX_CORNERS = 200
"""Up to this many corners the detour graph links every pair when the limited one finds no way
(its cost grows with the square of the corners: a district's lowest level has hundreds, and a
plan must not hold the link's setpoint stream for long)."""
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
    if not _blocking_here(envelope, here, z_m):
        return point
    # Over every exclusion stacked above the point (one after the other, as high as needed),
    # or out to the side of every exclusion forbidden at its height, never out of the
    # inclusion: the nearest allowed point at least CORNER_MARGIN_M off them. Whichever is
    # nearer; one push lands clear of all of them.
    over_z = z_m
    while (tops := _blocking_here(envelope, here, over_z)) and over_z <= envelope.ceiling_m:
        over_z = max(tops) + OVER_MARGIN_M
    free = envelope.free_at(z_m, CORNER_MARGIN_M)
    sideways = math.inf
    if not free.is_empty:
        _, nearest = nearest_points(here, free)
        sideways = math.hypot(nearest.x - x_m, nearest.y - y_m)
    if over_z <= envelope.ceiling_m and over_z - z_m <= sideways:
        return (x_m, y_m, over_z)
    if math.isinf(sideways):
        return point
    return (nearest.x, nearest.y, z_m)


def _blocking_here(envelope: Envelope, here: Point, z_m: float) -> list[float]:
    """The tops (widened bands' highs) of the exclusions that forbid ``here`` at ``z_m``."""
    return envelope.tops_at(here, z_m)


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
    forbidden there (:func:`_detour`); then straight to the target (its own height)."""
    z_m = start[2]
    route = _detour(envelope, start, target, tuple(envelope.obstacles_at(z_m)))
    if route is None:
        return None
    waypoints: list[Vec3] = [(x, y, z_m) for x, y in route]
    last = (target[0], target[1], z_m)
    if last != target:
        waypoints.append(last)
    waypoints.append(target)
    return _checked(envelope, start, waypoints, "around")


def _detour(
    envelope: Envelope, start: Vec3, target: Vec3, active: tuple[int, ...]
) -> list[tuple[float, float]] | None:
    """The corners (x, y) of the shortest way from ``start`` to above/below ``target`` through
    the corners of the exclusions ``active`` at this height that avoids every one of them;
    None when there is none. The corners' own visibility graph is built once per envelope and
    set of exclusions (:func:`_corner_graph`); only the start's and the target's edges are
    tested here. With corners linked only :data:`CORNER_EDGE_MAX_M` apart first, and when that
    finds no way and there are at most :data:`FULL_GRAPH_MAX_CORNERS` corners, all of them."""
    route = _detour_in(envelope, start, target, active, CORNER_EDGE_MAX_M)
    corners = _corner_graph(envelope, active, CORNER_EDGE_MAX_M)[0]
    if route is None and len(corners) <= FULL_GRAPH_MAX_CORNERS:
        route = _detour_in(envelope, start, target, active, math.inf)
    return route


def _detour_in(
    envelope: Envelope,
    start: Vec3,
    target: Vec3,
    active: tuple[int, ...],
    limit_m: float,
) -> list[tuple[float, float]] | None:
    """:func:`_detour` through the corner graph with edges at most ``limit_m`` long."""
    corners, graph = _corner_graph(envelope, active, limit_m)
    ends = np.array([start[:2], target[:2]], dtype=float)
    n = len(corners)
    # Node indices: the corners 0..n-1, the start n, the target n + 1.
    pairs = [(n, k) for k in range(n)] + [(n + 1, k) for k in range(n)] + [(n, n + 1)]
    nodes = np.concatenate([corners, ends]) if n else ends
    a_idx = np.array([a for a, _ in pairs], dtype=int)
    b_idx = np.array([b for _, b in pairs], dtype=int)
    free, lengths = _visible(envelope, active, nodes[a_idx], nodes[b_idx])
    # The start's and the target's edges, both ways; a corner's own edges come from the graph.
    extra: dict[int, list[tuple[int, float]]] = {n: [], n + 1: []}
    for a, b, length in zip(a_idx[free], b_idx[free], lengths[free], strict=True):
        extra.setdefault(int(a), []).append((int(b), float(length)))
        extra.setdefault(int(b), []).append((int(a), float(length)))

    def neighbours(node: int) -> list[tuple[int, float]]:
        return (graph[node] if node < n else []) + extra.get(node, [])

    route = _shortest(neighbours, n, n + 1)
    if route is None:
        return None
    return [(float(nodes[k][0]), float(nodes[k][1])) for k in route[1:-1]]


def _visible(
    envelope: Envelope, active: tuple[int, ...], a: np.ndarray, b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Whether each straight segment a[i]-b[i] (x, y) stays in the room and off every
    exclusion ``active``, and its length."""
    lines = shapely.linestrings(np.stack([a, b], axis=1))
    free = shapely.covered_by(lines, envelope.room)
    if active and len(lines):
        hit = envelope.solid_tree(active).query(lines, predicate="intersects")[0]
        free[hit] = False
    return free, np.hypot(*(a - b).T)


def _corner_graph(
    envelope: Envelope, active: tuple[int, ...], limit_m: float
) -> tuple[np.ndarray, list[list[tuple[int, float]]]]:
    """The corner nodes (N, 2) of the exclusions ``active`` (:func:`_corners`) and the
    visibility graph between those at most ``limit_m`` apart (adjacency lists of (node,
    length)), kept per envelope, set of exclusions and limit."""
    kept = envelope.graphs.get((active, limit_m))
    if kept is None:
        corners = _corners(envelope, active, active)
        n = len(corners)
        graph: list[list[tuple[int, float]]] = [[] for _ in range(n)]
        if n > 1:
            points = shapely.points(corners)
            near = shapely.STRtree(points).query(
                points, predicate="dwithin", distance=min(limit_m, 1e12)
            )
            i_all, j_all = near[:, near[0] < near[1]]
            for start in range(0, len(i_all), VISIBILITY_CHUNK):
                i_idx = i_all[start : start + VISIBILITY_CHUNK]
                j_idx = j_all[start : start + VISIBILITY_CHUNK]
                free, lengths = _visible(envelope, active, corners[i_idx], corners[j_idx])
                for i, j, length in zip(
                    i_idx[free].tolist(), j_idx[free].tolist(), lengths[free].tolist(), strict=True
                ):
                    graph[i].append((j, length))
                    graph[j].append((i, length))
        kept = envelope.graphs[(active, limit_m)] = (corners, graph)
    return kept


def _corners(envelope: Envelope, around: tuple[int, ...], active: tuple[int, ...]) -> np.ndarray:
    """The graph's corner nodes (N, 2): the convex corners of the footprints ``around``, grown
    by the clearance and :data:`CORNER_MARGIN_M` (simplified outward by up to
    :data:`SIMPLIFY_CORNERS_M` where that covers them), that lie in the room and outside every
    exclusion ``active`` (a shortest way bends only round a convex corner, and never at one
    inside something; the footprints of a site's stacked layers lie inside each other)."""
    found = []
    for i in around:
        ring = _outward(envelope.grown[i][0].buffer(CORNER_MARGIN_M, join_style="mitre"))
        for polygon in getattr(ring, "geoms", [ring]):
            coords = np.asarray(polygon.exterior.coords)[:-1]
            if not polygon.exterior.is_ccw:
                coords = coords[::-1]
            before, after = np.roll(coords, 1, axis=0), np.roll(coords, -1, axis=0)
            u, v = coords - before, after - coords
            found.append(coords[u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0] > 0])  # left turns
    if not found:
        return np.empty((0, 2))
    corners = np.concatenate(found)
    points = shapely.points(corners)
    keep = shapely.covered_by(points, envelope.room)
    if active:
        keep[envelope.solid_tree(active).query(points, predicate="intersects")[0]] = False
    return corners[keep]


def _outward(ring: shapely.Geometry) -> shapely.Geometry:
    """``ring`` with fewer corners, moved only outward (:data:`SIMPLIFY_CORNERS_M`): the simpler
    outline when it covers ``ring`` and has fewer corners, else ``ring``."""
    simpler = ring.buffer(SIMPLIFY_CORNERS_M, join_style="mitre").simplify(SIMPLIFY_CORNERS_M)
    if (
        simpler.geom_type == ring.geom_type
        and simpler.is_valid
        and shapely.get_num_coordinates(simpler) < shapely.get_num_coordinates(ring)
        and simpler.covers(ring)
    ):
        return simpler
    return ring


def _shortest(
    neighbours: Callable[[int], list[tuple[int, float]]], source: int, goal: int
) -> list[int] | None:
    """Dijkstra over the graph ``neighbours`` gives: the node indices from ``source`` to
    ``goal``, or None."""
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
        for nxt, length in neighbours(node):
            new = cost + length
            if new < best.get(nxt, math.inf):
                best[nxt] = new
                previous[nxt] = node
                heapq.heappush(queue, (new, nxt))
    return None
