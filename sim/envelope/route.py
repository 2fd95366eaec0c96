"""The way a vehicle is flown to its target inside its envelope: what is streamed, leg by leg.

A :class:`Route` is planned once per decision from where the vehicle is (:func:`plan_route`)
and then advanced as the vehicle flies (:func:`advance`): the setpoint streamed is always the
current waypoint of a legal :class:`~sim.envelope.paths.FlightPath`, or a hold point when there
is none. Contract:

* The target streamed is :func:`~sim.envelope.paths.legal_target` of the decision's target; a
  target with no legal point near it gives a hold.
* A waypoint is left for the next one only when the vehicle is within ``accept_m`` of it
  **and** the flight from where the vehicle actually is to the next waypoint is legal
  (:meth:`~sim.envelope.volume.Envelope.leg_violation`), so cutting a corner never cuts an
  exclusion. Within :data:`SETTLE_M` of it (there, up to the autopilot's tracking error) a
  start a hair outside the altitude band is forgiven, never an exclusion on the way: a
  climb-over's descent onto a target that lies closer to an exclusion than the tracking error
  would otherwise clip the exclusion's edge. Until the flight on may go, the waypoint stays
  streamed (the vehicle settles onto it; the leg from the waypoint itself is legal).
* A vehicle outside its envelope (a new envelope it already violates, or a drift) is never sent
  anywhere else: the route holds where it is and says why. The exceptions are the autopilot's
  tracking error: a vehicle within ``recover_m`` of the leg it was flying is sent back onto
  that leg's waypoint first, and one within ``recover_m`` of its envelope (a hair outside the
  inclusion's edge, a little below the floor after a take-off) to the nearest legal point
  (:func:`way_in`), when the way there crosses no exclusion.
* Holding means streaming the position where the hold began (the vehicle keeps still), never
  the target.
* A moving vehicle is not turned onto a new route where its momentum would carry it into
  something: :func:`plan_route_moving` brakes it to its stopping point first unless its whole
  turn is clear.

Pure functions on frozen values: the service's link, the tests and the world's flight model use
the same ones.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from shapely.geometry import MultiPoint

from sim.envelope.paths import Hold, legal_target, plan_path
from sim.envelope.volume import Envelope, Vec3

ACCEPT_M = 2.0
"""Within this distance of a waypoint the vehicle may go on to the next one."""
SETTLE_M = 0.5
"""Within this distance of a point the vehicle is at it, up to its autopilot's tracking error."""
RECOVER_M = 3.0
"""A vehicle outside its envelope but this close to the leg it flies goes back onto the leg."""
BRAKE_MPS2 = 2.5
"""The deceleration a vehicle's stop is reckoned with (the loop's autopilots' default horizontal
acceleration, ArduPilot's 2.5 m/s²; PX4's is higher, so its stops are shorter than reckoned)."""
SWEEP_MARGIN_M = 1.0
"""How much wider than the triangle of its turn a moving vehicle's way onto a new route is
checked (the autopilot's tracking error)."""


@dataclass(frozen=True)
class Route:
    """What the link streams for one decision.

    ``waypoints`` are the remaining points, the current one first; the last is the (legal)
    target. A holding route has one waypoint, the hold point, and says why in ``hold_reason``.
    """

    requested_m: Vec3
    """The decision's target, as asked for."""
    target_m: Vec3 | None
    """The legal target streamed at the end (None when there is none: the route holds)."""
    waypoints: tuple[Vec3, ...]
    kind: str
    """``direct``, ``over``, ``around``, ``hold``."""
    hold_reason: str | None = None

    @property
    def setpoint_m(self) -> Vec3:
        """What is streamed now: the current waypoint (or the hold point)."""
        return self.waypoints[0]

    @property
    def holding(self) -> bool:
        return self.hold_reason is not None

    @property
    def adjusted(self) -> bool:
        """The target streamed differs from the one asked for (moved out of a forbidden place)."""
        return self.target_m is not None and any(
            abs(a - b) > 1e-9 for a, b in zip(self.target_m, self.requested_m, strict=True)
        )


def _vec(values: Sequence[float]) -> Vec3:
    x, y, z = (float(v) for v in values)
    return (x, y, z)


def hold_at(requested_m: Sequence[float], position_m: Sequence[float], reason: str) -> Route:
    """A route that keeps the vehicle where it is, saying why."""
    return Route(_vec(requested_m), None, (_vec(position_m),), "hold", reason)


def plan_route(
    envelope: Envelope,
    position_m: Sequence[float],
    target_m: Sequence[float],
    previous: Route | None = None,
    recover_m: float = RECOVER_M,
) -> Route:
    """The route from ``position_m`` to (the legal point nearest) ``target_m``.

    ``previous`` is the route being flown, if any: a vehicle slightly off its envelope near that
    route's current leg is brought back onto the leg first (module docstring)."""
    requested = _vec(target_m)
    position = _vec(position_m)
    legal = legal_target(envelope, requested)
    if legal is None:
        return hold_at(requested, position, "no legal point near the target: holding")
    start = position
    lead: tuple[Vec3, ...] = ()
    if (why := envelope.violation(position)) is not None:
        back = _back_onto_leg(envelope, previous, position, recover_m) or way_in(
            envelope, position, recover_m
        )
        if back is None:
            return hold_at(
                requested, position, f"the vehicle is outside its envelope ({why}): holding"
            )
        start, lead = back, (back,)
    path = plan_path(envelope, start, legal)
    if isinstance(path, Hold):
        return hold_at(requested, position, path.reason)
    return Route(requested, legal, lead + path.waypoints, path.kind if not lead else "recover")


def stopping_point(
    position_m: Sequence[float], velocity_mps: Sequence[float], brake_mps2: float
) -> Vec3:
    """Where a vehicle at ``position_m`` moving at ``velocity_mps`` (area frame) stops when it
    brakes at ``brake_mps2``, horizontally and vertically alike, straight along its way."""
    x_m, y_m, z_m = _vec(position_m)
    vx, vy, vz = _vec(velocity_mps)
    speed = math.hypot(vx, vy)
    return (
        x_m + vx * speed / (2.0 * brake_mps2),
        y_m + vy * speed / (2.0 * brake_mps2),
        z_m + vz * abs(vz) / (2.0 * brake_mps2),
    )


def plan_route_moving(
    envelope: Envelope,
    position_m: Sequence[float],
    velocity_mps: Sequence[float] | None,
    target_m: Sequence[float],
    previous: Route | None = None,
    brake_mps2: float = BRAKE_MPS2,
) -> Route:
    """:func:`plan_route` for a vehicle that may be moving: its momentum carries it on while it
    turns onto the new route, so the route first brakes to its stopping point
    (:func:`stopping_point`) unless the whole turn is clear. The turn is clear when the column
    over the triangle of the position, the stopping point and the route's first waypoint, by
    :data:`SWEEP_MARGIN_M` wider, between their lowest and highest heights, is legal
    (:meth:`~sim.envelope.volume.Envelope.region_violation`): the vehicle's way from its
    momentum onto the new leg stays within it. Else the route goes to the stopping point first
    (when the braking itself is legal: otherwise no route does better than the one planned) and
    is planned on from there. ``velocity_mps`` None (unknown), or a stopping point within
    :data:`SETTLE_M`: :func:`plan_route` itself."""
    route = plan_route(envelope, position_m, target_m, previous)
    if velocity_mps is None or route.holding:
        return route
    position = _vec(position_m)
    stop = stopping_point(position, velocity_mps, brake_mps2)
    if math.dist(position, stop) <= SETTLE_M:
        return route
    first = route.setpoint_m
    heights = (position[2], stop[2], first[2])
    sweep = MultiPoint([position[:2], stop[:2], first[:2]]).convex_hull.buffer(SWEEP_MARGIN_M)
    if envelope.region_violation(sweep, min(heights), max(heights)) is None:
        return route
    if envelope.leg_violation(position, stop) is not None:
        return route
    onward = plan_route(envelope, stop, target_m, None)
    if onward.holding:
        return hold_at(target_m, stop, onward.hold_reason or "holding")
    return Route(onward.requested_m, onward.target_m, (stop, *onward.waypoints), onward.kind)


def _back_onto_leg(
    envelope: Envelope, previous: Route | None, position: Vec3, recover_m: float
) -> Vec3 | None:
    """The nearest legal point of the leg ``previous`` was flying (from its hold or current
    waypoint), when the vehicle is within ``recover_m`` of it; else None."""
    if previous is None or previous.holding:
        return None
    waypoint = previous.setpoint_m
    if math.dist(waypoint, position) <= recover_m and envelope.violation(waypoint) is None:
        return waypoint
    return None


def way_in(envelope: Envelope, position_m: Sequence[float], recover_m: float) -> Vec3 | None:
    """The nearest legal point to a vehicle outside its envelope by no more than ``recover_m``
    (its tracking error: a hair outside the inclusion's edge, a little below the floor, a
    little into an exclusion's clearance) when the way there crosses no exclusion itself; else
    None (the vehicle holds)."""
    position = _vec(position_m)
    nearest = legal_target(envelope, position)
    if nearest is None or math.dist(position, nearest) > recover_m:
        return None
    return None if envelope.wall_crossing(position, nearest, clearance=False) else nearest


def _may_go_on(envelope: Envelope, position: Vec3, gap_m: float, next_m: Vec3) -> bool:
    """Whether a vehicle at ``position``, ``gap_m`` from its waypoint, may fly on to ``next_m``:
    the leg from where it is is legal; or, within :data:`SETTLE_M` of the waypoint (there up to
    the autopilot's tracking error), it crosses no exclusion however the autopilot flies it and
    is legal from the same point moved into the altitude band (a hair below the floor after a
    take-off is the autopilot's error, not a way into anything)."""
    if envelope.leg_violation(position, next_m) is None:
        return True
    if gap_m > SETTLE_M or envelope.wall_crossing(position, next_m) is not None:
        return False
    x_m, y_m, z_m = position
    banded = (x_m, y_m, min(max(z_m, envelope.floor_m), envelope.ceiling_m))
    return envelope.leg_violation(banded, next_m) is None


def advance(
    envelope: Envelope, route: Route, position_m: Sequence[float] | None, accept_m: float = ACCEPT_M
) -> Route:
    """``route`` with the waypoints the vehicle at ``position_m`` has reached dropped (module
    docstring: only when the straight flight on from there is legal). Unchanged without a
    position, while holding, or on the last waypoint."""
    if position_m is None or route.holding:
        return route
    position = _vec(position_m)
    waypoints = route.waypoints
    while len(waypoints) > 1 and (gap_m := math.dist(position, waypoints[0])) <= accept_m:
        if not _may_go_on(envelope, position, gap_m, waypoints[1]):
            break
        waypoints = waypoints[1:]
    return route if waypoints is route.waypoints else replace(route, waypoints=waypoints)
