"""Routes planned off the link's I/O loop (:mod:`service.routing`): what streams while a plan is
under way, plans overtaken or failed, and a link whose plan takes seconds that keeps streaming
(the PX4 flavour of the mock takes OFFBOARD away after 1 s without a setpoint).

The unit tests drive :class:`~service.routing.LinkRoute` with :class:`ManualPlanner`, whose
plans end when the test says so; the link test holds the real plan on an event.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any

import pytest
from shapely.geometry import box

import service.routing
from service.routing import PLANNING, LinkRoute
from sim.config import AreaConfig
from sim.envelope import Envelope, Exclusion
from sim.envelope.route import stopping_point
from sitl_mock.server import MockAutopilot
from tests.helpers import tcp_url, wait_for
from tests.service.conftest import AREA as LINK_AREA
from tests.service.conftest import FAST_VEHICLE, mock_in_area_m

AREA = AreaConfig()  # 500 m x 500 m, 25-100 m
TOWER = Exclusion(box(200.0, 200.0, 300.0, 300.0), 0.0, 100.0, "tower")


class ManualPlanner(Executor):
    """Keeps each plan asked for until :meth:`finish` runs it (or :meth:`fail` fails it)."""

    def __init__(self) -> None:
        self.asked: list[tuple[Future, Callable[..., Any], tuple[Any, ...]]] = []

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        future: Future = Future()
        self.asked.append((future, fn, args))
        return future

    def finish(self, index: int = -1) -> None:
        future, fn, args = self.asked[index]
        future.set_result(fn(*args))

    def fail(self, index: int = -1) -> None:
        self.asked[index][0].set_exception(RuntimeError("no memory left"))


def test_the_first_plan_under_way_holds_at_the_stopping_point_then_streams_the_route() -> None:
    planner = ManualPlanner()
    route = LinkRoute(Envelope.for_area(AREA, [TOWER]), planner)
    route.set_target((350.0, 350.0, 50.0))
    velocity = (6.0, 0.0, 0.0)
    setpoint = route.setpoint((100.0, 250.0, 50.0), velocity, 2.5)
    assert setpoint == pytest.approx(stopping_point((100.0, 250.0, 50.0), velocity, 2.5))
    assert setpoint == pytest.approx((107.2, 250.0, 50.0))
    view = route.view()
    assert view is not None and view.kind == "hold" and view.hold_reason == PLANNING
    assert route.setpoint((101.0, 250.0, 50.0)) == setpoint  # still planning: the same hold
    assert len(planner.asked) == 1  # one plan at a time
    planner.finish()
    setpoint = route.setpoint((102.0, 250.0, 50.0))
    view = route.view()
    assert view is not None and view.kind == "around" and view.hold_reason is None
    assert setpoint == view.waypoints_m[0] and route.counters["routes_planned"] == 1


def test_a_new_target_while_flying_keeps_the_route_flown_until_the_next_is_planned() -> None:
    planner = ManualPlanner()
    route = LinkRoute(Envelope.for_area(AREA, [TOWER]), planner)
    route.set_target((100.0, 50.0, 50.0))
    route.setpoint((50.0, 50.0, 50.0))
    planner.finish()
    first = route.setpoint((50.0, 50.0, 50.0))
    assert first == (100.0, 50.0, 50.0)
    route.set_target((50.0, 150.0, 50.0))
    assert route.setpoint((60.0, 50.0, 50.0), (5.0, 0.0, 0.0)) == first  # the route flown
    assert route.planning and route.view().kind == "direct"  # type: ignore[union-attr]
    planner.finish()
    assert route.setpoint((62.0, 50.0, 50.0)) != first
    assert not route.planning and route.view().waypoints_m[-1] == (50.0, 150.0, 50.0)  # type: ignore[union-attr]


def test_a_new_envelope_never_streams_the_old_route_while_the_new_one_is_planned() -> None:
    planner = ManualPlanner()
    route = LinkRoute(Envelope.for_area(AREA), planner)
    route.set_target((350.0, 250.0, 50.0))
    route.setpoint((100.0, 250.0, 50.0))
    planner.finish()
    assert route.setpoint((100.0, 250.0, 50.0)) == (350.0, 250.0, 50.0)  # straight through
    route.set_envelope(Envelope.for_area(AREA, [TOWER]))  # the tower is now in the way
    velocity = (5.0, 0.0, 0.0)
    setpoint = route.setpoint((150.0, 250.0, 50.0), velocity, 2.5)
    assert setpoint == pytest.approx(stopping_point((150.0, 250.0, 50.0), velocity, 2.5))
    planner.finish()
    route.setpoint((152.0, 250.0, 50.0))
    view = route.view()
    assert view is not None and view.kind == "around"


def test_a_plan_overtaken_by_a_newer_target_is_dropped_and_the_newest_is_planned() -> None:
    planner = ManualPlanner()
    route = LinkRoute(Envelope.for_area(AREA), planner)
    route.set_target((100.0, 100.0, 50.0))
    route.setpoint((50.0, 50.0, 50.0))
    route.set_target((300.0, 100.0, 50.0))
    route.setpoint((50.0, 50.0, 50.0))
    assert len(planner.asked) == 1  # the first still under way: nothing more asked
    planner.finish(0)
    route.setpoint((50.0, 50.0, 50.0))  # the first is dropped, the newest asked for
    assert route.counters["plans_overtaken"] == 1 and len(planner.asked) == 2
    planner.finish(1)
    assert route.setpoint((50.0, 50.0, 50.0)) == (300.0, 100.0, 50.0)
    assert route.counters["routes_planned"] == 1


def test_a_plan_that_fails_holds_and_says_why() -> None:
    planner = ManualPlanner()
    route = LinkRoute(Envelope.for_area(AREA), planner)
    route.set_target((100.0, 100.0, 50.0))
    route.setpoint((50.0, 50.0, 50.0))
    planner.fail()
    assert route.setpoint((50.0, 50.0, 50.0)) == (50.0, 50.0, 50.0)
    view = route.view()
    assert view is not None and view.kind == "hold"
    assert view.hold_reason == "planning the route failed: no memory left"
    assert route.counters["plans_failed"] == 1
    route.set_target((100.0, 100.0, 50.0))  # a holding route is planned again
    route.setpoint((50.0, 50.0, 50.0))
    planner.finish()
    assert route.setpoint((50.0, 50.0, 50.0)) == (100.0, 100.0, 50.0)


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_a_link_whose_plan_takes_seconds_keeps_streaming_and_px4_keeps_offboard(
    start_mock: Callable[..., MockAutopilot],
    open_link: Callable[..., Any],
    monkeypatch: pytest.MonkeyPatch,
    backend: str,
) -> None:
    """The plan of a new envelope is held for 3 s (three times PX4's 1 s offboard timeout):
    the vehicle holds at its stopping point meanwhile, the setpoints keep streaming, PX4 keeps
    OFFBOARD; once planned the vehicle flies round the new block to its target."""
    mock = start_mock("px4", **FAST_VEHICLE)
    link = open_link(tcp_url(mock), backend)
    link.arm_and_takeoff().result(timeout=30.0)
    target = (55.0, 20.0, 10.0)
    link.set_target(target)
    wait_for(lambda: mock_in_area_m(mock)[0] > 15.0, 20.0, message="on its way")
    assert mock.state().mode == "OFFBOARD"

    gate = threading.Event()
    real = service.routing.plan_link_route

    def held(*args: Any) -> Any:
        gate.wait(10.0)
        return real(*args)

    monkeypatch.setattr(service.routing, "plan_link_route", held)
    block = Exclusion(box(45.0, 5.0, 50.0, 35.0), 0.0, 100.0, "block")
    link.set_envelope(Envelope.for_area(LINK_AREA, [block], clearance_m=1.0))
    wait_for(lambda: (s := link.state().route) and s.hold_reason == PLANNING, 2.0)
    sent = link.state().counters["setpoints_sent"]
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:
        state = link.state()
        assert state.route is not None and state.route.hold_reason == PLANNING
        assert mock.state().mode == "OFFBOARD"
        x_m, y_m, _ = mock_in_area_m(mock)
        assert not block.footprint.contains(box(x_m, y_m, x_m, y_m))
        time.sleep(0.05)
    assert link.state().counters["setpoints_sent"] - sent >= 10  # 10 Hz for 3 s, under load
    gate.set()
    wait_for(lambda: math.dist(mock_in_area_m(mock), target) <= 1.0, 30.0, message="arrived")
    assert mock.state().mode == "OFFBOARD"
    assert link.state().route.kind == "around"


def test_after_a_hand_back_mid_plan_the_hold_is_where_the_vehicle_is_now() -> None:
    """A plan still under way from before the pilot had the vehicle must not make it fly back
    to where it was then: the new target's hold is at its position now."""
    planner = ManualPlanner()
    route = LinkRoute(Envelope.for_area(AREA, [TOWER]), planner)
    route.set_target((350.0, 350.0, 50.0))
    assert route.setpoint((100.0, 100.0, 50.0)) == (100.0, 100.0, 50.0)
    route.clear()  # the pilot takes the vehicle, and hands it back far away
    route.set_target((50.0, 400.0, 50.0))
    assert route.setpoint((400.0, 100.0, 60.0)) == (400.0, 100.0, 60.0)
    assert len(planner.asked) == 1  # the old plan still runs: nothing more asked yet
    planner.finish(0)
    assert route.setpoint((400.0, 100.0, 60.0)) == (400.0, 100.0, 60.0)
    assert route.counters["plans_overtaken"] == 1 and len(planner.asked) == 2
    planner.finish(1)
    route.setpoint((400.0, 100.0, 60.0))
    view = route.view()
    assert (
        view is not None and view.kind == "around" and view.waypoints_m[-1] == (50.0, 400.0, 50.0)
    )


def test_a_new_target_shows_the_route_flown_not_an_earlier_hold() -> None:
    """The hold streamed while the first route was planned is not what the link shows once a
    new target comes: the route flown goes on until the next one is planned."""
    planner = ManualPlanner()
    route = LinkRoute(Envelope.for_area(AREA), planner)
    route.set_target((100.0, 50.0, 50.0))
    route.setpoint((50.0, 50.0, 50.0))  # the first plan: a hold meanwhile
    planner.finish()
    route.setpoint((50.0, 50.0, 50.0))
    route.set_target((50.0, 150.0, 50.0))
    view = route.view()
    assert view is not None and view.kind == "direct" and view.hold_reason is None
    assert route.setpoint((55.0, 50.0, 50.0)) == (100.0, 50.0, 50.0)
    assert route.view().kind == "direct"  # type: ignore[union-attr]


def test_a_new_envelope_set_while_the_link_waits_for_a_plan_is_never_streamed_past() -> None:
    """The link lets go of its lock while it waits for a plan it just asked for: an envelope
    set meanwhile (by the API) makes the setpoint a hold at the stopping point of the new one's
    plan, never the route planned in the old envelope."""
    planner = ManualPlanner()
    route = LinkRoute(Envelope.for_area(AREA), planner)
    route.set_target((350.0, 350.0, 50.0))
    position = (100.0, 250.0, 50.0)

    def meanwhile(plan: Future) -> None:
        planner.finish()  # the straight route, planned in the old envelope
        route.set_envelope(Envelope.for_area(AREA, [TOWER]))  # the API, lock let go

    setpoint = route.setpoint(position, (0.0, 0.0, 0.0), 2.5, meanwhile)
    assert setpoint == pytest.approx(position)  # a hold: the new envelope's plan is under way
    assert route.view() is not None and route.view().hold_reason == PLANNING
    planner.finish()
    assert route.setpoint(position, (0.0, 0.0, 0.0), 2.5) != pytest.approx((350.0, 350.0, 50.0))
    assert route.route is not None and route.route.kind == "around"


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_the_link_lets_go_of_its_lock_while_it_waits_for_a_plan(
    monkeypatch: pytest.MonkeyPatch, backend: str
) -> None:
    """The I/O loop's wait for a plan must not hold the API and the workers up: a thread that
    needs the link's lock gets it while the loop waits (here the wait could last 5 s; it ends
    as soon as that thread, holding the lock, ends the plan)."""
    from service import links, vehicle_link
    from service.vehicle_link import LinkConfig

    monkeypatch.setattr(vehicle_link, "PLAN_WAIT_S", 5.0)
    link = links.open_link(backend, LinkConfig("tcp:127.0.0.1:9", area=LINK_AREA))
    plan: Future = Future()

    def end_the_plan_under_the_lock() -> None:
        with link._cond:
            plan.set_result(None)
            link._cond.notify_all()

    started = time.monotonic()
    with link._cond:
        threading.Thread(target=end_the_plan_under_the_lock, daemon=True).start()
        link._wait_for_plan(plan)
        assert plan.done()
    assert time.monotonic() - started < 4.0
    link.close()
