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
* Planning runs on the ``planner`` given (an :class:`~concurrent.futures.Executor`): inline by
  default, so the plan is ready in the same call; the link gives a thread of its own
  (:func:`background_planner`), so that a slow plan (the first one in a height band builds the
  corners' graph: up to seconds for an envelope with many corners) never holds its I/O loop.
  While a plan is under way :meth:`LinkRoute.setpoint` streams the route flown so far when only
  the target changed (it is legal in the same envelope), else — a new envelope, a stream that
  (re)starts, no route yet — a hold at the vehicle's stopping point (where its momentum carries
  it anyway; :func:`~sim.envelope.route.stopping_point`). One plan at a time: a plan overtaken
  by a newer target or envelope is dropped when it ends and the newest is planned then.
  ``on_planned`` (if given) is called from the planner's thread when a plan ends.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, MutableMapping, Sequence
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass

from sim.envelope import Envelope, legal_target
from sim.envelope.route import (
    BRAKE_MPS2,
    RECOVER_M,
    SETTLE_M,
    Route,
    hold_at,
    plan_route_moving,
    stopping_point,
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


PLANNING = "planning the route"
"""The hold reason streamed while a plan is under way and the route flown so far cannot go on."""


class InlinePlanner(Executor):
    """Runs each plan at once in the caller's thread (deterministic; tests, the in-memory link)."""

    def submit(self, fn: Callable[..., Route], /, *args: object, **kwargs: object) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as exc:  # handed to the caller through the future
            future.set_exception(exc)
        return future


def background_planner(name: str = "route-planner") -> ThreadPoolExecutor:
    """A planner with a thread of its own (one plan at a time), for a link's routes."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)


@dataclass(frozen=True)
class _Pending:
    generation: int
    future: Future
    position: Vec3
    """Where the vehicle was when the plan was asked for (a failed plan holds there)."""


class LinkRoute:
    """The routing state of one vehicle link (see the module docstring). Not thread-safe: the
    link calls it under its own lock (plans run on ``planner`` from snapshots)."""

    def __init__(
        self,
        envelope: Envelope,
        planner: Executor | None = None,
        on_planned: Callable[[], None] | None = None,
    ) -> None:
        self.envelope = envelope
        self._planner = planner or InlinePlanner()
        self._on_planned = on_planned
        self._requested: Vec3 | None = None
        self._legal: Vec3 | None = None
        self._route: Route | None = None
        self._stale = False
        self._generation = 0  # bumped by whatever makes a plan under way out of date
        self._route_goes_on = False  # the route flown may go on while the next is planned
        self._pending: _Pending | None = None
        # What streams until the current generation's route is planned (None: the route flown
        # goes on), decided at the first setpoint of that generation.
        self._interim: Route | None = None
        self._interim_generation = -1
        self.counters = {
            "targets_moved": 0,
            "routes_planned": 0,
            "route_holds": 0,
            "plans_overtaken": 0,
            "plans_failed": 0,
        }

    def close(self) -> None:
        """Stop the planner (a plan under way is dropped)."""
        self._planner.shutdown(wait=False, cancel_futures=True)

    @property
    def planning(self) -> bool:
        """Whether a plan is under way."""
        return self._pending is not None

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
            self._mark_stale(route_goes_on=not holding)
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
        self._generation += 1
        self._interim = None
        self._route_goes_on = False

    def set_envelope(self, envelope: Envelope) -> None:
        """Replace the envelope; the route is planned again at the next setpoint."""
        self.envelope = envelope
        if self._requested is not None:
            self._mark_stale(route_goes_on=False)

    def replan(self) -> None:
        """Plan again at the next setpoint (the vehicle was handed back, or the stream paused)."""
        if self._requested is not None:
            self._mark_stale(route_goes_on=False)

    def _mark_stale(self, route_goes_on: bool) -> None:
        self._stale = True
        self._generation += 1
        self._interim = None  # decided again at the next setpoint
        self._route_goes_on = route_goes_on and self._route_goes_on

    def setpoint(
        self,
        position_m: Sequence[float] | None,
        velocity_mps: Sequence[float] | None = None,
        brake_mps2: float = BRAKE_MPS2,
        wait: Callable[[Future], object] | None = None,
    ) -> Vec3 | None:
        """The setpoint to stream now (area frame), or None when there is nothing to stream:
        no target, or no position to plan from yet. A route planned while the vehicle moves at
        ``velocity_mps`` (None: unknown) brakes first where its momentum would carry it into
        something (:func:`~sim.envelope.route.plan_route_moving`, stops reckoned at
        ``brake_mps2``). A plan asked for in this call is handed to ``wait`` (None: not waited
        for), which returns when it ended or it will not wait longer: most plans take
        milliseconds, and the new route then streams at once. The link's ``wait`` lets go of
        its lock meanwhile."""
        if self._requested is None:
            return None
        self._collect()
        if self._stale:
            if position_m is None:
                return None
            position: Vec3 = tuple(float(v) for v in position_m)  # type: ignore[assignment]
            if self._interim_generation != self._generation:
                self._interim = self._interim_for(position, velocity_mps, brake_mps2)
                self._interim_generation = self._generation
            if self._pending is None:
                self._submit(position, velocity_mps, brake_mps2)
                if wait is not None and self._pending is not None:
                    wait(self._pending.future)
                    # ``wait`` may have let go of the link's lock: another thread may have
                    # changed the target or the envelope meanwhile, so start again from there.
                    return self.setpoint(position_m, velocity_mps, brake_mps2)
                if self._collect():  # planned already: streamed as planned
                    return None if self._route is None else self._route.setpoint_m
        if self._waiting_for_plan() and self._interim is not None:
            return self._interim.setpoint_m
        if self._route is not None:
            self._route = advance_route(self.envelope, self._route, position_m)
        return None if self._route is None else self._route.setpoint_m

    def _waiting_for_plan(self) -> bool:
        """Whether the current generation's route is not planned yet."""
        return self._stale or self._pending is not None

    def _interim_for(
        self, position: Vec3, velocity_mps: Sequence[float] | None, brake_mps2: float
    ) -> Route | None:
        """What streams until the route is planned: None (the route flown goes on) when only
        the target changed, else a hold at the vehicle's stopping point."""
        if self._route_goes_on and self._route is not None:
            return None
        assert self._requested is not None
        stop = (
            position if velocity_mps is None else stopping_point(position, velocity_mps, brake_mps2)
        )
        return hold_at(self._requested, stop, PLANNING)

    def _submit(
        self, position: Vec3, velocity_mps: Sequence[float] | None, brake_mps2: float
    ) -> None:
        """Ask the planner for the route from ``position`` (one plan at a time)."""
        assert self._requested is not None
        future = self._planner.submit(
            plan_link_route,
            self.envelope,
            position,
            velocity_mps,
            self._requested,
            self._route,
            brake_mps2,
        )
        self._pending = _Pending(self._generation, future, position)
        self._stale = False
        if self._on_planned is not None and not future.done():
            future.add_done_callback(lambda _: self._on_planned())  # type: ignore[misc]

    def _collect(self) -> bool:
        """Take the plan under way if it has ended: adopted when it is still wanted, dropped
        when overtaken (the newest is asked for at once). Whether one was adopted."""
        pending = self._pending
        if pending is None or not pending.future.done():
            return False
        self._pending = None
        if pending.generation != self._generation:
            self.counters["plans_overtaken"] += 1
            return False
        try:
            route = pending.future.result()
        except Exception as exc:  # a plan that fails holds, and says why
            self.counters["plans_failed"] += 1
            log.exception("planning the route failed")
            assert self._requested is not None
            where = self._interim.setpoint_m if self._interim else pending.position
            route = hold_at(self._requested, where, f"planning the route failed: {exc}")
        if route.holding:
            self.counters["route_holds"] += 1
            log.warning("holding: %s", route.hold_reason)
        else:
            self.counters["routes_planned"] += 1
        self._route = route
        self._route_goes_on = True
        return True

    def view(self) -> RouteView | None:
        """The route as the link's state shows it (None before the first plan); while a plan is
        under way, what streams meanwhile."""
        route = self._route
        if self._waiting_for_plan() and self._interim is not None:
            route = self._interim
        if route is None:
            return None
        return RouteView(route.waypoints, route.kind, route.hold_reason)


def plan_link_route(
    envelope: Envelope,
    position: Vec3,
    velocity_mps: Sequence[float] | None,
    requested: Vec3,
    previous: Route | None,
    brake_mps2: float,
) -> Route:
    """The route a link streams from ``position`` to ``requested`` in ``envelope`` (pure: runs
    on the link's planner): :func:`~sim.envelope.route.plan_route_moving` from where the vehicle
    is, or from the floor above it after a take-off (:func:`_climbed_in`: it climbs there first);
    a route that holds holds where the vehicle is."""
    start = _climbed_in(envelope, position)
    moving = velocity_mps if start == position else None  # a climb-in starts from a stop
    route = plan_route_moving(envelope, start, moving, requested, previous, brake_mps2)
    if route.holding:
        return hold_at(requested, position, route.hold_reason or "holding")
    if start != position and position[2] < envelope.floor_m - SETTLE_M:
        route = Route(route.requested_m, route.target_m, (start, *route.waypoints), route.kind)
    return route


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
