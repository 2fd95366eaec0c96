"""What a vehicle link streams on the way to its target, inside the vehicle's envelope.

:class:`LinkRoute` is the link's one piece of routing state (the envelope, the target asked for
and the :class:`~sim.envelope.route.Route` flown), kept by :class:`~service.vehicle_link.
VehicleLinkBase` under its lock. Contract:

* :meth:`LinkRoute.set_target` answers at once with the target that will be streamed at the end
  (:func:`~sim.envelope.paths.legal_target`: the target itself when legal, else the nearest legal
  point; None when there is none and the vehicle will hold). It plans nothing: the way there is
  planned by :meth:`LinkRoute.setpoint` when the next setpoint is due and the link may stream,
  from where the vehicle is *then* (after a take-off, not from the ground it left).
* :meth:`LinkRoute.setpoint` gives the setpoint to stream now: the current waypoint of the
  planned route, advanced as the vehicle flies (:func:`~sim.envelope.route.advance`), or the
  hold point. A vehicle below the envelope's floor (after a take-off to a lower altitude) with
  nothing above it climbs straight up into the envelope first.
* A route that holds is planned again at the next target set, even the same one (the vehicle
  may have been moved back into its envelope); a route that flies is not.
* :meth:`LinkRoute.set_envelope` replaces the envelope at run time: the route is planned again
  from where the vehicle is, so a vehicle that the new envelope finds outside holds there and
  the route says why (it never jumps).
"""

from __future__ import annotations

import logging
import math
from collections.abc import MutableMapping, Sequence
from dataclasses import dataclass

from sim.envelope import Envelope, legal_target
from sim.envelope.route import (
    BRAKE_MPS2,
    RECOVER_M,
    SETTLE_M,
    Route,
    hold_at,
    plan_route_moving,
    way_in,
)
from sim.envelope.route import advance as advance_route
from sim.envelope.volume import Vec3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RouteView:
    """The route as a link's state shows it."""

    waypoints_m: tuple[Vec3, ...]
    """The remaining waypoints, the current setpoint first (a hold point while holding)."""
    kind: str
    """``direct``, ``over``, ``around``, ``recover`` (back into the envelope first), ``hold``."""
    hold_reason: str | None


class LinkRoute:
    """The routing state of one vehicle link (see the module docstring). Not thread-safe: the
    link calls it under its own lock."""

    def __init__(self, envelope: Envelope) -> None:
        self.envelope = envelope
        self._requested: Vec3 | None = None
        self._legal: Vec3 | None = None
        self._route: Route | None = None
        self._stale = False
        self.counters = {"targets_moved": 0, "routes_planned": 0, "route_holds": 0}

    @property
    def route(self) -> Route | None:
        return self._route

    def set_target(
        self, target_m: Sequence[float], counters: MutableMapping[str, int] | None = None
    ) -> tuple[Vec3, bool]:
        """Fly to ``target_m`` from the next setpoint on. Returns the legal target streamed at
        the end and whether it differs from the one set before (a new target). A holding route
        is planned again either way. ValueError for a non-finite target or one with no legal
        point near it (nothing changes). ``counters`` (the link's) count the refused targets
        (``targets_rejected``) and the moved ones (``geofence_clamps``)."""
        counters = counters if counters is not None else {}
        try:
            legal, changed = self._set_target(target_m)
        except ValueError:
            counters["targets_rejected"] = counters.get("targets_rejected", 0) + 1
            raise
        if legal != tuple(float(v) for v in target_m):
            counters["geofence_clamps"] = counters.get("geofence_clamps", 0) + 1
        return legal, changed

    def _set_target(self, target_m: Sequence[float]) -> tuple[Vec3, bool]:
        x_m, y_m, z_m = (float(v) for v in target_m)
        requested = (x_m, y_m, z_m)
        if not all(map(math.isfinite, requested)):
            raise ValueError(f"target {tuple(target_m)}: not a finite point")
        legal = legal_target(self.envelope, requested)
        if legal is None:
            raise ValueError(f"target {requested}: no legal point near it")
        if legal != requested:
            self.counters["targets_moved"] += 1
            log.warning("target %s not legal in the envelope: moved to %s", requested, legal)
        changed = self._requested is None or legal != self._legal
        holding = self._route is not None and self._route.holding
        if changed or holding:
            self._requested, self._legal = requested, legal
            self._stale = True
        return legal, changed

    def legal(self, target_m: Sequence[float]) -> Vec3 | None:
        """The legal target :meth:`set_target` would fly to for ``target_m`` (None: none near
        it); changes nothing."""
        return legal_target(self.envelope, target_m)

    def clear(self) -> None:
        """No target: nothing streams."""
        self._requested = self._legal = None
        self._route = None
        self._stale = False

    def set_envelope(self, envelope: Envelope) -> None:
        """Replace the envelope; the route is planned again at the next setpoint."""
        self.envelope = envelope
        if self._requested is not None:
            self._stale = True

    def replan(self) -> None:
        """Plan again at the next setpoint (the vehicle was handed back, or the stream paused)."""
        if self._requested is not None:
            self._stale = True

    def setpoint(
        self,
        position_m: Sequence[float] | None,
        velocity_mps: Sequence[float] | None = None,
        brake_mps2: float = BRAKE_MPS2,
    ) -> Vec3 | None:
        """The setpoint to stream now (area frame), or None when there is nothing to stream:
        no target, or no position to plan from yet. A route planned while the vehicle moves at
        ``velocity_mps`` (None: unknown) brakes first where its momentum would carry it into
        something (:func:`~sim.envelope.route.plan_route_moving`, stops reckoned at
        ``brake_mps2``)."""
        if self._requested is None:
            return None
        if self._stale:
            if position_m is None:
                return None
            position = tuple(float(v) for v in position_m)
            self._route = self._plan(position, velocity_mps, brake_mps2)  # type: ignore[arg-type]
            self._stale = False
        elif self._route is not None:
            self._route = advance_route(self.envelope, self._route, position_m)
        return None if self._route is None else self._route.setpoint_m

    def _plan(
        self, position: Vec3, velocity_mps: Sequence[float] | None, brake_mps2: float
    ) -> Route:
        assert self._requested is not None
        envelope = self.envelope
        start = _climbed_in(envelope, position)
        moving = velocity_mps if start == position else None  # a climb-in starts from a stop
        route = plan_route_moving(envelope, start, moving, self._requested, self._route, brake_mps2)
        if route.holding:
            route = hold_at(self._requested, position, route.hold_reason or "holding")
            self.counters["route_holds"] += 1
            log.warning("holding: %s", route.hold_reason)
        else:
            self.counters["routes_planned"] += 1
            if start != position and position[2] < envelope.floor_m - SETTLE_M:
                route = Route(
                    route.requested_m, route.target_m, (start, *route.waypoints), route.kind
                )
        return route

    def view(self) -> RouteView | None:
        """The route as the link's state shows it (None before the first plan)."""
        route = self._route
        if route is None:
            return None
        return RouteView(route.waypoints, route.kind, route.hold_reason)


def _climb_point(envelope: Envelope, position: Vec3) -> Vec3:
    return (position[0], position[1], envelope.floor_m)


def _climbed_in(envelope: Envelope, position: Vec3) -> Vec3:
    """Where planning starts: a vehicle below the floor (after a take-off) plans from the point
    of the floor above it, or from the legal point of the floor nearest that one within
    :data:`~sim.envelope.route.RECOVER_M` (a take-off at the inclusion's very edge), when the
    climb there crosses no exclusion: the route climbs there first (unless the vehicle is within
    :data:`~sim.envelope.route.SETTLE_M` of the floor: at it, up to its tracking error). Else
    where it is."""
    if position[2] >= envelope.floor_m:
        return position
    above = _climb_point(envelope, position)
    if envelope.violation(above) is not None:
        above = way_in(envelope, above, RECOVER_M) or above
    if envelope.violation(above) is None and envelope.wall_crossing(position, above) is None:
        return above
    return position
