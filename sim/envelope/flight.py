"""The world's flight inside an envelope: the routes the vehicle link streams, flown.

The service's link streams a :class:`~sim.envelope.route.Route` (:mod:`service.routing`): the
legal target, a route planned from where the vehicle is when the target changes, its waypoints
advanced as the vehicle flies. The world's flight model (training, evaluation) flies the same
routes here, so that what is learned and what is flown agree. Contract:

* :func:`route_toward` is the link's routing decision: the route kept (and advanced) while the
  legal target is the one it flies to and it does not hold; else planned again from where the
  vehicle is (:func:`~sim.envelope.route.plan_route`).
* :func:`fly_along` flies a route for a period, waypoint by waypoint, under the horizontal and
  vertical speed caps of :class:`sim.flight.Flight`. Each leg is flown as
  :func:`sim.flight.fly` flies (each axis at its own cap, the *dog-leg* an autopilot's position
  controller flies) when both pieces of that dog-leg are legal
  (:meth:`~sim.envelope.volume.Envelope.segment_violation`), else along the leg itself (both
  axes slowed to arrive together). Either way the vehicle reaches a waypoint when :func:`fly`
  would have, never leaves the envelope, and its path is returned as a :class:`Track`.
* A holding route keeps the vehicle where it is.
* Fast path: with no envelope, or an envelope that is a plain box (no exclusions, no clearance,
  an axis-aligned rectangle), the flight is exactly :func:`sim.flight.fly` toward the target
  (clamped into the box when it lies outside), without a single shapely call.
* Fleets (:func:`fly_fleet`): every vehicle flies its own route; :func:`separate_tracks` then
  holds, for the period, a vehicle whose flown path would come closer than the separation to
  another's (lower indices fly first), so that the separation holds *on the paths*, at every
  instant, not only at the targets (given starts that keep it).

The world's envelope is a ``tupa-envelope/1`` document (:mod:`sim.envelope.files`) kept in
:class:`sim.world.World` as canonical JSON text (:func:`canonical_document`), parsed once per
document and area (:func:`envelope_for`).
"""

from __future__ import annotations

import json
import math
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from sim.config import AreaConfig
from sim.envelope.files import envelope_from_document
from sim.envelope.paths import legal_target
from sim.envelope.route import BRAKE_MPS2, Route, advance, plan_route, plan_route_moving
from sim.envelope.volume import Envelope, Vec3
from sim.errors import InputError
from sim.flight import Flight, fly, fly_point
from sim.geometry import enforce_separation, min_pairwise_distance_m

__all__ = [
    "FleetFlight",
    "Flown",
    "Track",
    "canonical_document",
    "closest_approach_m",
    "envelope_for",
    "fly_along",
    "fly_fleet",
    "fly_route",
    "fly_route_period",
    "fly_route_track",
    "fly_vehicle_period",
    "legal_position",
    "plain_box",
    "read_document",
    "route_toward",
    "separate_tracks",
    "separated_legal_targets",
]

SEPARATION_TOLERANCE_M = 1e-9
"""How far below the separation two flown paths may come (floating-point rounding)."""
TARGET_ROUNDS = 3
"""How many times :func:`separated_legal_targets` separates and legalises a fleet's targets."""

Box = tuple[float, float, float, float, float, float]
"""x_min, y_min, z_min, x_max, y_max, z_max (metres)."""


# --------------------------------------------------------------------------------------------
# The world's envelope: a document, parsed once


def canonical_document(document: Any, area: AreaConfig) -> str:
    """A ``tupa-envelope/1`` document (a dict, or its JSON text) checked for ``area`` and
    written as canonical JSON (sorted keys, no spaces): what :class:`sim.world.World` keeps.
    InputError naming the field for anything :func:`envelope_from_document` refuses."""
    if isinstance(document, str):
        try:
            document = json.loads(document)
        except ValueError as exc:
            raise InputError(f"not JSON ({exc})") from None
    text = json.dumps(document, sort_keys=True, separators=(",", ":"), allow_nan=False)
    envelope_for(text, area)  # the checks (and the parse, kept)
    return text


@lru_cache(maxsize=32)
def envelope_for(document_json: str, area: AreaConfig) -> Envelope:
    """The envelope a canonical document describes over ``area``, parsed once (the geometry's
    prepared parts and caches are then shared by every step that flies in it)."""
    return envelope_from_document(json.loads(document_json), area)


def read_document(path: str | Path) -> dict[str, Any]:
    """The JSON document in the envelope file at ``path``; InputError naming the file."""
    try:
        document = json.loads(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read the envelope file ({exc.strerror})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not JSON ({exc})") from None
    if not isinstance(document, dict):
        raise InputError(f"{path}: not a JSON object")
    return document


_BOXES: dict[int, tuple[weakref.ref[Envelope], Box | None]] = {}


def plain_box(envelope: Envelope) -> Box | None:
    """The envelope as a box when it is one (no exclusions, no clearance, an axis-aligned
    rectangle for inclusion): then a legal point is a point of the box and every straight or
    dog-leg flight between two is legal. None otherwise. Kept per envelope (by identity)."""
    key = id(envelope)
    entry = _BOXES.get(key)
    if entry is not None and entry[0]() is envelope:
        return entry[1]
    box: Box | None = None
    if not envelope.exclusions and not envelope.clearance_m:
        x0, y0, x1, y1 = envelope.inclusion.bounds
        if abs(envelope.inclusion.area - (x1 - x0) * (y1 - y0)) <= 1e-9 * max(1.0, x1 - x0) ** 2:
            box = (x0, y0, envelope.floor_m, x1, y1, envelope.ceiling_m)
    _BOXES[key] = (weakref.ref(envelope, lambda _ref, k=key: _BOXES.pop(k, None)), box)
    return box


def legal_position(
    envelope: Envelope | None, xyz_m: Sequence[float], search: bool = False
) -> np.ndarray:
    """``xyz_m`` when it is legal, else the nearest legal point (:func:`legal_target`); with no
    envelope ``xyz_m`` itself. When :func:`legal_target` finds none near (a cluster of
    exclusions): ``xyz_m`` itself (a target: its route holds and says why), or with ``search``
    (a start: the world's own choice, which must be legal) the legal point nearest among those
    :func:`legal_target` finds from rings of points around it (:data:`SEARCH_RADII_M`)."""
    point = np.asarray(xyz_m, dtype=float)
    if envelope is None:
        return point
    box = plain_box(envelope)
    if box is not None:
        return np.clip(point, box[:3], box[3:])
    legal = legal_target(envelope, point)
    if legal is None and search:
        legal = _search_legal(envelope, _vec(point))
    return point if legal is None else np.array(legal, dtype=float)


SEARCH_RADII_M = (10.0, 25.0, 50.0, 100.0, 200.0, 400.0, 800.0)
"""The rings :func:`legal_position` searches (16 points each, at the point's height and at the
ceiling) when :func:`legal_target` finds no legal point near a start."""


def _search_legal(envelope: Envelope, point: Vec3) -> Vec3 | None:
    x0, y0, x1, y1 = envelope.inclusion.bounds
    for radius_m in SEARCH_RADII_M:
        found = []
        for i in range(16):
            angle = 2.0 * math.pi * i / 16
            x = min(max(point[0] + radius_m * math.cos(angle), x0), x1)
            y = min(max(point[1] + radius_m * math.sin(angle), y0), y1)
            for z in (point[2], envelope.ceiling_m):
                legal = legal_target(envelope, (x, y, z))
                if legal is not None:
                    found.append(legal)
        if found:
            return min(found, key=lambda q: math.dist(q, point))
    return None


# --------------------------------------------------------------------------------------------
# One vehicle


@dataclass(frozen=True)
class Track:
    """The path flown in one period: breakpoints (time from the period's start, point); the
    vehicle moves at constant velocity between two. The first is (0, start), the last is the
    end of the period (or of the motion, after which it stays)."""

    times_s: tuple[float, ...]
    points_m: tuple[Vec3, ...]

    @classmethod
    def still(cls, position_m: Vec3, duration_s: float) -> Track:
        return cls((0.0, duration_s), (position_m, position_m))

    def at(self, time_s: float) -> Vec3:
        """Where the vehicle is ``time_s`` into the period (the end point after the motion)."""
        times, points = self.times_s, self.points_m
        if time_s <= times[0]:
            return points[0]
        for i in range(1, len(times)):
            if time_s <= times[i]:
                span = times[i] - times[i - 1]
                f = 0.0 if span <= 0 else (time_s - times[i - 1]) / span
                return _lerp(points[i - 1], points[i], f)
        return points[-1]


@dataclass(frozen=True)
class Flown:
    """One vehicle's period: where it ends, the route it flies on (keep it for the next
    period), and the path it took."""

    position_m: np.ndarray
    route: Route
    track: Track


def _vec(values: Sequence[float]) -> Vec3:
    x, y, z = (float(v) for v in values)
    return (x, y, z)


def route_toward(
    envelope: Envelope,
    position_m: Sequence[float],
    target_m: Sequence[float],
    route: Route | None,
    velocity_mps: Sequence[float] | None = None,
    brake_mps2: float = BRAKE_MPS2,
) -> Route:
    """The route to fly this period, as the link decides it: ``route`` advanced from
    ``position_m`` (:func:`~sim.envelope.route.advance`) when it flies (does not hold) to the
    legal point of ``target_m``; else a route planned from ``position_m`` (module docstring),
    braking first where a vehicle moving at ``velocity_mps`` would carry into something
    (:func:`~sim.envelope.route.plan_route_moving`; None: not moving)."""
    requested = _vec(target_m)
    if route is not None and not route.holding:
        same = route.requested_m == requested or legal_target(envelope, requested) == route.target_m
        if same:
            return advance(envelope, route, position_m)
    return plan_route_moving(envelope, position_m, velocity_mps, requested, route, brake_mps2)


def _leg_times(p: Vec3, w: Vec3, flight: Flight) -> tuple[float, float]:
    """How long the horizontal and the vertical parts of the leg ``p``-``w`` take at full
    speed (0 for a speed of None: there at once)."""
    h, v = flight.horizontal_mps, flight.vertical_mps
    horizontal_s = 0.0 if h is None else math.hypot(w[0] - p[0], w[1] - p[1]) / h
    vertical_s = 0.0 if v is None else abs(w[2] - p[2]) / v
    return horizontal_s, vertical_s


def _knee(p: Vec3, w: Vec3, horizontal_s: float, vertical_s: float) -> Vec3 | None:
    """Where :func:`sim.flight.fly`'s dog-leg from ``p`` to ``w`` turns (one axis arrived, the
    other still going), or None when it is the straight leg itself."""
    if (w[0], w[1]) == (p[0], p[1]) or w[2] == p[2] or horizontal_s == vertical_s:
        return None
    if horizontal_s < vertical_s:
        f = horizontal_s / vertical_s
        return (w[0], w[1], p[2] + (w[2] - p[2]) * f)
    f = vertical_s / horizontal_s
    return (p[0] + (w[0] - p[0]) * f, p[1] + (w[1] - p[1]) * f, w[2])


def _lerp(a: Vec3, b: Vec3, f: float) -> Vec3:
    return (a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f, a[2] + (b[2] - a[2]) * f)


def fly_along(
    envelope: Envelope,
    position_m: Sequence[float],
    route: Route,
    flight: Flight,
    duration_s: float,
) -> Flown:
    """Fly ``route`` from ``position_m`` for ``duration_s`` (module docstring): waypoint by
    waypoint, each reached waypoint dropped as the link drops it
    (:func:`~sim.envelope.route.advance`); at the last one the vehicle stays. A holding route
    keeps the vehicle still."""
    here = _vec(position_m)
    if route.holding:
        return Flown(np.array(here), route, Track.still(here, duration_s))
    times, points = [0.0], [here]
    elapsed = 0.0
    replanned = False
    while elapsed < duration_s:
        waypoint = route.setpoint_m
        if here == waypoint:
            if len(route.waypoints) == 1:
                break
            route = advance(envelope, route, here)
            if route.setpoint_m == waypoint:  # advance kept it (cannot happen at 0 m): stop
                break
            continue
        left = duration_s - elapsed
        horizontal_s, vertical_s = _leg_times(here, waypoint, flight)
        leg_s = max(horizontal_s, vertical_s)
        knee = _knee(here, waypoint, horizontal_s, vertical_s)
        dog_leg = knee is not None and (
            envelope.segment_violation(here, knee) is None
            and envelope.segment_violation(knee, waypoint) is None
        )
        # Off the planned leg (on what remains of a dog-leg that rounding now finds touching
        # something): straight on only when that is legal, else a new route from here.
        if (
            knee is not None
            and not dog_leg
            and not replanned
            and envelope.segment_violation(here, waypoint) is not None
        ):
            route, replanned = plan_route(envelope, here, route.requested_m, route), True
            if route.holding:
                break
            continue
        if leg_s <= left:  # there within the period
            if dog_leg:
                assert knee is not None
                times.append(elapsed + min(horizontal_s, vertical_s))
                points.append(knee)
            elapsed += leg_s
            here = waypoint
            times.append(elapsed)
            points.append(here)
            continue
        # The period ends on the way.
        if dog_leg:
            assert knee is not None
            turn_s = min(horizontal_s, vertical_s)
            end = fly_point(*here, *waypoint, flight, left)
            if turn_s < left:
                times.append(elapsed + turn_s)
                points.append(knee)
        else:
            end = _lerp(here, waypoint, left / leg_s)
        here = end
        elapsed = duration_s
        times.append(elapsed)
        points.append(here)
    if times[-1] < duration_s:
        times.append(duration_s)
        points.append(here)
    return Flown(np.array(here), route, Track(tuple(times), tuple(points)))


def _straight(
    envelope: Envelope | None,
    box: Box | None,
    position_m: Sequence[float],
    target_m: Sequence[float],
    flight: Flight,
    duration_s: float,
) -> Flown:
    """The fast path: :func:`sim.flight.fly` toward the target (clamped into ``box``)."""
    requested = _vec(target_m)
    target = requested
    if box is not None:
        target = (
            min(max(requested[0], box[0]), box[3]),
            min(max(requested[1], box[1]), box[4]),
            min(max(requested[2], box[2]), box[5]),
        )
    start = _vec(position_m)
    end = fly(np.asarray(start), np.asarray(target), flight, duration_s)
    route = Route(requested, target, (target,), "direct")
    horizontal_s, vertical_s = _leg_times(start, target, flight)
    times, points = [0.0], [start]
    knee = _knee(start, target, horizontal_s, vertical_s)
    if knee is not None and min(horizontal_s, vertical_s) < duration_s:
        times.append(min(horizontal_s, vertical_s))
        points.append(knee)
    arrive_s = max(horizontal_s, vertical_s)
    if arrive_s < duration_s:
        times.append(arrive_s)
        points.append(target)
    times.append(duration_s)
    points.append(_vec(end))
    return Flown(end, route, Track(tuple(times), tuple(points)))


def fly_route_track(
    envelope: Envelope | None,
    position_m: Sequence[float],
    target_m: Sequence[float],
    flight: Flight,
    duration_s: float,
    route: Route | None = None,
) -> Flown:
    """One vehicle's period toward ``target_m`` inside ``envelope`` (module docstring), with
    the route to keep for the next period and the path flown."""
    return _track_period(envelope, position_m, target_m, flight, duration_s, route)[0]


def _track_period(
    envelope: Envelope | None,
    position_m: Sequence[float],
    target_m: Sequence[float],
    flight: Flight,
    duration_s: float,
    route: Route | None,
) -> tuple[Flown, Route | None]:
    """:func:`fly_route_track`, and the route chosen at the period's start (None on the fast
    path, which keeps none)."""
    box = None if envelope is None else plain_box(envelope)
    if envelope is None or box is not None:
        return _straight(envelope, box, position_m, target_m, flight, duration_s), None
    if flight.teleports:  # there at once: no way to plan, only the legal target
        flown = _teleport(envelope, position_m, target_m, duration_s)
        return flown, flown.route
    chosen = route_toward(envelope, position_m, target_m, route)
    return fly_along(envelope, position_m, chosen, flight, duration_s), chosen


@dataclass(frozen=True)
class VehiclePeriod:
    """One vehicle's decision period (:func:`fly_vehicle_period`)."""

    flown: Flown
    """Where it ends, the route to pass back next period, the path flown."""
    velocity_mps: np.ndarray
    """Its velocity at the end (3,): zero without an acceleration limit."""
    route_if_held: Route | None
    """The route it keeps when it is held where it was for the period (a fleet's separation):
    the one chosen at the period's start, not one advanced along a path it did not fly."""


def fly_vehicle_period(
    envelope: Envelope | None,
    position_m: Sequence[float],
    velocity_mps: Sequence[float],
    target_m: Sequence[float],
    flight: Flight,
    duration_s: float,
    route: Route | None = None,
) -> VehiclePeriod:
    """One vehicle's decision period, the one flight of the single, vector and fleet worlds:
    inside an envelope with an acceleration limit as the loop flies the link's routes
    (:func:`fly_route_period`, velocity carried); else :func:`fly_route_track` (at the speed
    caps, or at once for a teleporting flight; velocity zero)."""
    if envelope is not None and flight.accelerates:
        flown, velocity = fly_route_period(
            envelope, position_m, velocity_mps, target_m, flight, duration_s, route
        )
        return VehiclePeriod(flown, velocity, route)
    flown, chosen = _track_period(envelope, position_m, target_m, flight, duration_s, route)
    return VehiclePeriod(flown, np.zeros(3), chosen or flown.route)


def _teleport(
    envelope: Envelope, position_m: Sequence[float], target_m: Sequence[float], duration_s: float
) -> Flown:
    """A flight with no speed limits: at the legal target at once (where the vehicle is when
    there is none near: it holds)."""
    requested, here = _vec(target_m), _vec(position_m)
    legal = legal_target(envelope, requested)
    if legal is None:
        route = Route(requested, None, (here,), "hold", "no legal point near the target: holding")
        return Flown(np.array(here), route, Track.still(here, duration_s))
    route = Route(requested, legal, (legal,), "direct")
    return Flown(np.array(legal), route, Track((0.0, duration_s), (legal, legal)))


def fly_route(
    envelope: Envelope | None,
    position_m: Sequence[float],
    target_m: Sequence[float],
    flight: Flight,
    duration_s: float,
    route: Route | None = None,
) -> tuple[np.ndarray, Route]:
    """Where the vehicle at ``position_m`` is after ``duration_s`` flying toward ``target_m``
    along the route the link would stream, and that route (pass it back next period: it is
    planned again only when the legal target changes or it holds). With no envelope or a plain
    box and a legal target: exactly :func:`sim.flight.fly`'s result."""
    flown = fly_route_track(envelope, position_m, target_m, flight, duration_s, route)
    return flown.position_m, flown.route


LINK_TICK_S = 0.1
"""How often the vehicle link advances its route and streams a setpoint (its default
``setpoint_rate_hz``, 10 Hz): the accelerating flight along a route does the same."""


def fly_route_period(
    envelope: Envelope,
    position_m: Sequence[float],
    velocity_mps: Sequence[float],
    target_m: Sequence[float],
    flight: Flight,
    duration_s: float,
    route: Route | None = None,
) -> tuple[Flown, np.ndarray]:
    """One decision period along the link's routes as the loop flies them, for a flight with an
    acceleration limit (:mod:`sim.dynamics`): what was flown (its track sampled every link
    tick) and the velocity at its end. For the flight's ``latency_s`` (at most the period) the
    vehicle goes on along ``route`` (the one streamed before the decision; with none it keeps
    where it is), then along the route toward ``target_m`` (:func:`route_toward`). The setpoint
    is the route's current waypoint, advanced every :data:`LINK_TICK_S` as the link advances it
    (:func:`~sim.envelope.route.advance`); the vehicle follows it under the acceleration and
    speed limits, its velocity carried in and out."""
    here = np.array(position_m, dtype=float).reshape(1, 3)
    velocity = np.array(velocity_mps, dtype=float).reshape(1, 3)
    times, points = [0.0], [_vec(here[0])]
    latency_s = min(flight.latency_s, duration_s)
    if latency_s > 0:
        if route is None:  # nothing streamed yet: the vehicle keeps where it is
            route = Route(points[0], points[0], (points[0],), "direct")
        here, velocity, route = _follow(
            envelope, here, velocity, route, flight, latency_s, times, points
        )
    route = route_toward(envelope, here[0], target_m, route, velocity[0], flight.accel_mps2)
    here, velocity, route = _follow(
        envelope, here, velocity, route, flight, duration_s - latency_s, times, points
    )
    return Flown(here[0], route, Track(tuple(times), tuple(points))), velocity[0]


def _follow(
    envelope: Envelope,
    here: np.ndarray,
    velocity: np.ndarray,
    route: Route,
    flight: Flight,
    duration_s: float,
    times: list[float],
    points: list[Vec3],
) -> tuple[np.ndarray, np.ndarray, Route]:
    """Follow ``route`` for ``duration_s``, tick by tick (:func:`fly_route_period`), appending
    each tick's end to ``times`` and ``points``."""
    from sim.dynamics import fly_accelerating

    assert flight.horizontal_mps is not None and flight.vertical_mps is not None
    assert flight.accel_mps2 is not None
    limits = {
        "max_h_mps": flight.horizontal_mps,
        "max_v_mps": flight.vertical_mps,
        "accel_h_mps2": flight.accel_mps2,
        "accel_v_mps2": flight.accel_mps2,
    }
    left = duration_s
    first = True
    while left > 1e-9:
        if not first and len(route.waypoints) > 1:
            route = advance(envelope, route, _vec(here[0]))
        first = False
        setpoint = np.array(route.setpoint_m).reshape(1, 3)
        tick_s = min(LINK_TICK_S, left)
        here, velocity = fly_accelerating(
            here, velocity, setpoint, setpoint, duration_s=tick_s, latency_s=0.0, **limits
        )
        left -= tick_s
        times.append(times[-1] + tick_s)
        points.append(_vec(here[0]))
    return here, velocity, route


# --------------------------------------------------------------------------------------------
# Fleets


def closest_approach_m(a: Track, b: Track) -> float:
    """The least distance between two vehicles flying ``a`` and ``b`` over the same period
    (exact: both move at constant velocity between the merged breakpoints)."""
    times = sorted({*a.times_s, *b.times_s})
    best = math.inf
    previous = None
    for t in times:
        pa, pb = a.at(t), b.at(t)
        gap = (pa[0] - pb[0], pa[1] - pb[1], pa[2] - pb[2])
        if previous is None:
            best = math.hypot(*gap)
        else:
            change = (gap[0] - previous[0], gap[1] - previous[1], gap[2] - previous[2])
            speed2 = change[0] ** 2 + change[1] ** 2 + change[2] ** 2
            s = 1.0
            if speed2 > 0:
                s = (
                    -(previous[0] * change[0] + previous[1] * change[1] + previous[2] * change[2])
                    / speed2
                )
                s = min(max(s, 0.0), 1.0)
            best = min(
                best,
                math.hypot(*(previous[i] + change[i] * s for i in range(3))),
                math.hypot(*gap),
            )
        previous = gap
    return best


def separate_tracks(
    starts_m: Sequence[Vec3],
    tracks: Sequence[Track],
    separation_m: float,
    duration_s: float,
) -> tuple[bool, ...]:
    """Which vehicles hold where they are for the period so that no two flown paths come
    closer than ``separation_m`` (or closer than they started, for two that start closer).

    Lower indices have priority: while two paths (flown or held) conflict, the first such pair
    in index order loses its higher index's flight, or, when that one already holds (it sits in
    the other's way), its lower index's. Each round holds one more vehicle, and every vehicle
    held never conflicts, so at most K rounds. Pure."""
    k = len(tracks)
    held = [False] * k
    still = [Track.still(_vec(s), duration_s) for s in starts_m]

    def current(i: int) -> Track:
        return still[i] if held[i] else tracks[i]

    while True:
        conflict = None
        for i in range(k):
            for j in range(i + 1, k):
                if held[i] and held[j]:
                    continue
                start_gap = math.dist(still[i].points_m[0], still[j].points_m[0])
                floor = min(separation_m, start_gap) - SEPARATION_TOLERANCE_M
                if closest_approach_m(current(i), current(j)) < floor:
                    conflict = (i, j)
                    break
            if conflict is not None:
                break
        if conflict is None:
            return tuple(held)
        i, j = conflict
        held[j if not held[j] else i] = True


def separated_legal_targets(
    envelope: Envelope | None,
    targets_m: np.ndarray,
    separation_m: float,
    area: AreaConfig,
    search: bool = False,
) -> np.ndarray:
    """A fleet's targets (K, 3) separated (:func:`sim.geometry.enforce_separation`, lower
    indices first) and each made legal (:func:`legal_position`, ``search`` for starts), again
    while making them legal brought two closer than ``separation_m`` (at most
    :data:`TARGET_ROUNDS` rounds; the paths' separation, :func:`separate_tracks`, holds
    whatever the targets). A target with no legal point near stays as asked (its route holds
    and says why)."""
    targets = enforce_separation(targets_m, separation_m, area)
    if envelope is None:
        return targets
    for _ in range(TARGET_ROUNDS):
        legal = np.array([legal_position(envelope, t, search) for t in targets])
        if len(legal) < 2 or min_pairwise_distance_m(legal) >= separation_m:
            return legal
        targets = enforce_separation(legal, separation_m, area)
    return legal


@dataclass(frozen=True)
class FleetFlight:
    """A fleet's period: where each vehicle ends (K, 3), its route, its path, and which ones
    held for the separation (:func:`separate_tracks`)."""

    positions_m: np.ndarray
    routes: tuple[Route | None, ...]
    """Each vehicle's route to pass back next period (None: plan one from where it is)."""
    tracks: tuple[Track, ...]
    held: tuple[bool, ...]
    velocities_mps: np.ndarray | None = None
    """With an acceleration limit, each vehicle's velocity at the end (K, 3; zero when held)."""


def fly_fleet(
    envelope: Envelope | None,
    positions_m: np.ndarray,
    targets_m: np.ndarray,
    flight: Flight,
    duration_s: float,
    separation_m: float | None,
    routes: Sequence[Route | None] | None = None,
    velocities_mps: np.ndarray | None = None,
) -> FleetFlight:
    """K vehicles' period: each flies its own (:func:`fly_vehicle_period`; its route kept from
    ``routes``, its velocity from ``velocities_mps``, zero when None), then those whose paths
    would come too close hold where they are, on the route they had
    (:func:`separate_tracks`; no separation with ``separation_m`` None)."""
    positions = np.asarray(positions_m, dtype=float)
    targets = np.asarray(targets_m, dtype=float)
    previous = list(routes) if routes is not None else [None] * len(positions)
    accelerates = envelope is not None and flight.accelerates
    velocities = np.zeros_like(positions)
    if accelerates and velocities_mps is not None:
        velocities = np.array(velocities_mps, dtype=float).reshape(positions.shape)
    periods = [
        fly_vehicle_period(envelope, p, v, t, flight, duration_s, r)
        for p, v, t, r in zip(
            positions.tolist(), velocities.tolist(), targets.tolist(), previous, strict=True
        )
    ]
    flown = [period.flown for period in periods]
    starts = [_vec(p) for p in positions.tolist()]
    tracks = [f.track for f in flown]
    held = (
        (False,) * len(flown)
        if separation_m is None
        else separate_tracks(starts, tracks, separation_m, duration_s)
    )
    out = np.array([f.position_m for f in flown], dtype=float).reshape(len(flown), 3)
    kept: list[Route | None] = []
    for k, period in enumerate(periods):
        velocities[k] = period.velocity_mps
        if held[k]:
            out[k] = positions[k]
            tracks[k] = Track.still(starts[k], duration_s)
            kept.append(period.route_if_held)
            velocities[k] = 0.0  # held: stopped there (a stand-in, as the hold is)
        else:
            kept.append(period.flown.route)
    return FleetFlight(out, tuple(kept), tuple(tracks), held, velocities if accelerates else None)
