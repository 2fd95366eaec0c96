"""What a vehicle link streams inside its envelope (:mod:`service.routing`,
:mod:`sim.envelope.route`).

The property test flies a vehicle that tracks its setpoints perfectly (straight, a few metres a
tick) through random envelopes and random decisions, some of them mid-flight, and holds every
point it passes to the envelope with plain shapely distances (``independent_violations``, not
the module's own checks). The other tests pin the contract's cases one by one, on the in-memory
link and on the pymavlink link against the mock autopilot.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import box

from service.routing import LinkRoute
from sim.envelope import Envelope, Exclusion, legal_target
from tests.fakes import FakeLink
from tests.helpers import tcp_url, wait_for
from tests.service.conftest import AREA as LINK_AREA
from tests.service.conftest import FAST_VEHICLE, mock_in_area_m
from tests.sim.test_envelope import AREA, envelopes, independent_violations, points3

STEP_M = 3.0
"""How far the perfectly tracking vehicle moves per tick."""
TICKS = 400


def fly(route: LinkRoute, position: tuple[float, float, float], ticks: int) -> list[np.ndarray]:
    """Fly a vehicle that tracks each setpoint perfectly for ``ticks`` ticks; the points it
    passes, sampled every 0.25 m, one array per tick."""
    flown = []
    for _ in range(ticks):
        setpoint = route.setpoint(position)
        if setpoint is None:
            break
        gap = math.dist(position, setpoint)
        end = (
            setpoint
            if gap <= STEP_M
            else tuple(p + (s - p) * STEP_M / gap for p, s in zip(position, setpoint, strict=True))
        )
        n = max(2, math.ceil(math.dist(position, end) / 0.25) + 1)
        flown.append(np.linspace(position, end, n))
        position = end  # type: ignore[assignment]
        if gap == 0 and route.setpoint(position) == setpoint:
            break
    return flown


@settings(max_examples=150, deadline=None)
@given(
    envelope=envelopes(),
    start=points3,
    targets=st.lists(points3, min_size=1, max_size=3),
    interrupt=st.integers(1, 30),
)
def test_what_is_flown_never_leaves_the_envelope(envelope, start, targets, interrupt):
    position = legal_target(envelope, start)
    if position is None:
        return
    route = LinkRoute(envelope)
    for i, target in enumerate(targets):
        try:
            legal, _ = route.set_target(target)
        except ValueError:
            continue
        last = i == len(targets) - 1
        flown = fly(route, position, TICKS if last else interrupt)
        if flown:
            position = tuple(flown[-1][-1])  # type: ignore[assignment]
            assert independent_violations(envelope, np.concatenate(flown)) == []
        view = route.view()
        assert view is not None
        if view.kind == "hold":
            assert view.hold_reason
        elif last and legal is not None:
            assert position == pytest.approx(legal, abs=1e-6)


def test_a_descent_onto_a_target_beside_an_exclusion_never_clips_its_edge():
    """Found by the property test: the target lies 0.25 m beside a slab (no clearance), the
    climb-over's corner above it is reached to within the tracking tolerance, and the descent
    from there — not from the corner — would cut the slab's edge. The corner stays streamed
    until the flight down is legal."""
    slab = Exclusion(box(0.25, 0.0, 5.25, 37.0), 20.0, 30.0, "slab")
    envelope = Envelope.for_area(AREA, [slab], clearance_m=0.0)
    route = LinkRoute(envelope)
    legal, _ = route.set_target((0.0, 36.0, 0.0))
    flown = fly(route, (38.5, 12.0, 25.0), TICKS)
    assert independent_violations(envelope, np.concatenate(flown)) == []
    assert flown[-1][-1] == pytest.approx(legal)


TOWER = Exclusion(box(80, 80, 120, 120), 0.0, 100.0, "tower")
"""Up to the ceiling: the only way past is around."""


def test_a_target_behind_a_tower_is_flown_around_it():
    envelope = Envelope.for_area(AREA, [TOWER], clearance_m=5.0)
    route = LinkRoute(envelope)
    assert route.set_target((150.0, 150.0, 50.0)) == ((150.0, 150.0, 50.0), True)
    flown = fly(route, (50.0, 50.0, 50.0), TICKS)
    view = route.view()
    assert view is not None and view.kind == "around"
    assert independent_violations(envelope, np.concatenate(flown)) == []
    assert flown[-1][-1] == pytest.approx((150.0, 150.0, 50.0))


def test_the_same_target_again_is_not_planned_again_but_a_hold_is():
    route = LinkRoute(Envelope.for_area(AREA, [TOWER], clearance_m=5.0))
    route.set_target((150.0, 150.0, 50.0))
    route.setpoint((50.0, 50.0, 50.0))
    assert route.counters["routes_planned"] == 1
    for _ in range(5):
        assert route.set_target((150.0, 150.0, 50.0))[1] is False
        route.setpoint((50.0, 50.0, 50.0))
    assert route.counters["routes_planned"] == 1
    # A wall across the area: no way through, the vehicle holds where it is and says why...
    wall = Exclusion(box(95, 0, 105, 200), 0.0, 100.0, "wall")
    route.set_envelope(Envelope.for_area(AREA, [wall]))
    assert route.setpoint((50.0, 50.0, 50.0)) == (50.0, 50.0, 50.0)
    view = route.view()
    assert view is not None and view.kind == "hold" and "no legal path" in (view.hold_reason or "")
    # ... and the same target is planned again at the next decision (the wall may be gone).
    route.set_envelope(Envelope.for_area(AREA))
    route.set_target((150.0, 150.0, 50.0))
    assert route.setpoint((50.0, 50.0, 50.0)) == (150.0, 150.0, 50.0)


def test_a_new_envelope_that_the_vehicle_violates_makes_it_hold_where_it_is():
    route = LinkRoute(Envelope.for_area(AREA))
    route.set_target((150.0, 150.0, 50.0))
    assert route.setpoint((100.0, 100.0, 50.0)) == (150.0, 150.0, 50.0)
    route.set_envelope(Envelope.for_area(AREA, [TOWER]))  # the vehicle is inside the tower
    assert route.setpoint((100.0, 100.0, 50.0)) == (100.0, 100.0, 50.0)
    view = route.view()
    assert view is not None and view.kind == "hold"
    assert "outside its envelope" in (view.hold_reason or "")
    assert "tower" in (view.hold_reason or "")


def test_a_vehicle_below_the_floor_climbs_straight_into_the_envelope_first():
    route = LinkRoute(Envelope.for_area(AREA))  # floor 25 m
    route.set_target((150.0, 150.0, 50.0))
    assert route.setpoint((20.0, 20.0, 10.0)) == (20.0, 20.0, 25.0)
    # 1 m below the floor the straight line on is not legal yet; at it (up to the autopilot's
    # tracking error) it is the next waypoint.
    assert route.setpoint((20.0, 20.0, 24.0)) == (20.0, 20.0, 25.0)
    assert route.setpoint((20.0, 20.0, 24.7)) == (150.0, 150.0, 50.0)
    # A new target while at the floor, up to the tracking error: no climb point first.
    route.set_target((100.0, 150.0, 50.0))
    assert route.setpoint((30.0, 30.0, 24.8)) == (100.0, 150.0, 50.0)


def test_a_corner_is_cut_only_where_cutting_it_is_legal():
    envelope = Envelope.for_area(AREA, [TOWER], clearance_m=5.0)
    route = LinkRoute(envelope)
    route.set_target((150.0, 150.0, 50.0))
    start = (50.0, 50.0, 50.0)
    corner = route.setpoint(start)
    after = route.view().waypoints_m[1]  # type: ignore[union-attr]
    # 1.5 m short of the first corner on the leg to it: within the 2 m to go on, but the
    # straight line from there to the next corner cuts the tower's clearance.
    short = tuple(
        c - (c - s) * 1.5 / math.dist(start, corner) for s, c in zip(start, corner, strict=True)
    )
    assert envelope.segment_violation(short, after) is not None
    assert route.setpoint(short) == corner
    # At the corner the leg on is legal: the next corner is the setpoint.
    assert route.setpoint(corner) == after


def test_targets_and_an_envelope_on_the_in_memory_link():
    link = FakeLink(position_m=(50.0, 50.0, 50.0))
    link.set_envelope(Envelope.for_area(link.config.area, [TOWER], clearance_m=5.0))
    assert link.set_target((100.0, 100.0, 50.0)) != (100.0, 100.0, 50.0)  # moved out of it
    assert link.counters["geofence_clamps"] == 1
    target = link.set_target((150.0, 150.0, 50.0))
    for _ in range(200):
        link.advance(0.2)
        assert link.state().position_m is not None
        assert not TOWER.footprint.buffer(5.0 - 1e-6).contains(
            box(*link.state().position_m[:2], *link.state().position_m[:2])  # type: ignore[index]
        )
    assert link.state().position_m == pytest.approx(target)
    with pytest.raises(ValueError, match="not a finite point"):
        link.set_target((math.nan, 1.0, 1.0))


@pytest.mark.slow
def test_the_pymavlink_link_flies_the_mock_around_a_no_fly_zone(start_mock, open_link):
    """In the link tests' 60 m x 60 m area (home at (10, 20)): a no-fly block between the
    vehicle and its target, up to the ceiling; the mock is sampled every 50 ms on its way."""
    block = Exclusion(box(25, 10, 35, 50), 0.0, 20.0, "block")
    envelope = Envelope.for_area(LINK_AREA, [block], clearance_m=2.0)
    mock = start_mock("px4", **FAST_VEHICLE)
    link = open_link(tcp_url(mock), envelope=envelope)
    link.arm_and_takeoff().result(timeout=30.0)
    target = (50.0, 30.0, 8.0)
    assert link.set_target(target) == target
    closest_m = math.inf
    deadline = time.monotonic() + 40.0
    while math.dist(mock_in_area_m(mock), target) > 1.0 and time.monotonic() < deadline:
        x_m, y_m, _ = mock_in_area_m(mock)
        closest_m = min(closest_m, block.footprint.exterior.distance(box(x_m, y_m, x_m, y_m)))
        assert not block.footprint.contains(box(x_m, y_m, x_m, y_m)), (x_m, y_m)
        time.sleep(0.05)
    assert math.dist(mock_in_area_m(mock), target) <= 1.0, "the vehicle never got there"
    state = wait_for(lambda: (s := link.state()).route is not None and s, 5.0)
    assert state.route.kind == "around"
    print(f"\nclosest approach to the block: {closest_m:.2f} m (clearance 2 m)")
    assert closest_m >= 1.0


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_the_link_turns_a_fast_mock_round_a_block_without_cutting_into_it(
    start_mock, open_link, backend: str
):
    """The mock autopilot (ArduPilot's 2.5 m/s² acceleration, 10 m/s) flies east along a
    block's south side; short of its west end the service sends it north, a straight leg that
    passes the block's west side. The link knows the vehicle's velocity (LOCAL_POSITION_NED's,
    MAVSDK's position_velocity_ned) and brakes it before turning: sampled every 20 ms, the
    vehicle never enters the block (without the braking it flies ~8 m into it: the unit test
    above)."""
    block = Exclusion(box(36, 27, 60, 60), 0.0, 20.0, "block")
    envelope = Envelope.for_area(LINK_AREA, [block], clearance_m=1.5)
    mock = start_mock("ardupilot", max_speed_up_mps=5.0, accel_v_mps2=5.0)
    link = open_link(tcp_url(mock), backend=backend, envelope=envelope)
    link.arm_and_takeoff(8.0).result(timeout=60.0)
    link.set_target((58.0, 20.0, 8.0))
    wait_for(lambda: mock_in_area_m(mock)[0] >= 27.0 or None, 20.0, 0.01, "flying east")
    speed = math.hypot(*mock.state().velocity_ned_mps[:2])
    assert speed > 5.0, f"too slow to matter: {speed:.1f} m/s"
    target = (30.0, 58.0, 8.0)
    assert envelope.segment_violation(mock_in_area_m(mock), target) is None  # the leg is clear
    link.set_target(target)
    deadline = time.monotonic() + 40.0
    deepest_m = 0.0
    while math.dist(mock_in_area_m(mock), target) > 1.0 and time.monotonic() < deadline:
        x_m, y_m, _ = mock_in_area_m(mock)
        if block.footprint.contains(box(x_m, y_m, x_m, y_m)):
            deepest_m = max(deepest_m, block.footprint.exterior.distance(box(x_m, y_m, x_m, y_m)))
        time.sleep(0.02)
    assert deepest_m == 0.0, f"flew {deepest_m:.1f} m into the block"
    assert math.dist(mock_in_area_m(mock), target) <= 1.0, "the vehicle never got there"


def test_a_take_off_at_the_areas_very_corner_climbs_in_and_flies() -> None:
    """Found on a real ArduCopter SITL: with home on the area's corner (the default frame), the
    take-off ends a little below the floor and a few centimetres outside the box; the route
    must climb in at the nearest legal point, never hold there for ever."""
    envelope = Envelope.for_area(AREA)  # floor 25 m
    for start in ((-0.02, 0.013, 24.1), (0.02, 0.013, 24.1), (-0.02, -0.02, 3.0)):
        route = LinkRoute(envelope)
        route.set_target((150.0, 150.0, 50.0))
        flown = fly(route, start, TICKS)
        view = route.view()
        assert view is not None and view.kind != "hold", (start, view)
        assert flown[-1][-1] == pytest.approx((150.0, 150.0, 50.0))
        # Outside only on the climb in (a few centimetres from the edge), inside ever after.
        inside = next(i for i, f in enumerate(flown) if envelope.violation(f[-1]) is None)
        assert all(np.hypot(*(f[:, :2] - start[:2]).T).max() < 0.1 for f in flown[: inside + 1])
        assert independent_violations(envelope, np.concatenate(flown[inside + 1 :])) == []


def test_a_vehicle_a_little_off_its_envelope_is_brought_back_but_one_far_off_holds() -> None:
    envelope = Envelope.for_area(AREA, [TOWER], clearance_m=5.0)
    route = LinkRoute(envelope)
    route.set_target((150.0, 150.0, 50.0))
    # 1 m inside the tower's 5 m clearance (tracking error): back out to the nearest legal point.
    assert route.setpoint((76.0, 100.0, 50.0)) == pytest.approx((74.5, 100.0, 50.0))
    assert route.view().kind == "recover"  # type: ignore[union-attr]
    route = LinkRoute(envelope)
    route.set_target((150.0, 150.0, 50.0))
    assert route.setpoint((90.0, 100.0, 50.0)) == (90.0, 100.0, 50.0)  # deep inside: holds
    assert route.view().kind == "hold"  # type: ignore[union-attr]


def _fly_with_momentum(
    route: LinkRoute, position, velocity, seconds: float, use_velocity: bool
) -> list[tuple[float, float, float]]:
    """The loop's flight (sim.dynamics, the mock's kinematics) of the setpoints ``route``
    streams every 0.1 s, as the link streams them (the vehicle's velocity given to the route
    when ``use_velocity``); the positions at every tick."""
    from sim.dynamics import fly_accelerating

    here = np.array([position], dtype=float)
    speed = np.array([velocity], dtype=float)
    flown = []
    for _ in range(round(seconds / 0.1)):
        setpoint = route.setpoint(tuple(here[0]), tuple(speed[0]) if use_velocity else None)
        target = np.array([setpoint], dtype=float)
        here, speed = fly_accelerating(
            here, speed, target, target, duration_s=0.1, latency_s=0.0,
            max_h_mps=10.0, max_v_mps=3.0, accel_h_mps2=2.5, accel_v_mps2=2.5,
        )  # fmt: skip
        flown.append(tuple(float(v) for v in here[0]))
    return flown


def test_a_moving_vehicle_sent_round_a_corner_brakes_before_it_rather_than_cut_into_it() -> None:
    """Flying east at 10 m/s along a block's south side, just short of its west end, the
    vehicle is sent north: the straight leg north passes the block's west side, but the
    vehicle's momentum carries it up to 20 m further east while it turns, into the block. The
    route planned with its velocity brakes to its stopping point first and goes round; planned
    without it (the link before it knew the velocity), the same flight ends up inside."""
    block = Exclusion(box(100, 100, 160, 160), 0.0, 100.0, "block")
    envelope = Envelope.for_area(AREA, [block], clearance_m=5.0)
    start, velocity, target = (88.0, 92.0, 40.0), (10.0, 0.0, 0.0), (80.0, 190.0, 40.0)

    def inside(points) -> int:
        return sum(block.footprint.contains(box(x, y, x, y)) for x, y, _ in points)

    braking = LinkRoute(envelope)
    braking.set_target(target)
    flown = _fly_with_momentum(braking, start, velocity, 30.0, use_velocity=True)
    view = braking.view()
    assert view is not None and view.kind == "around"
    assert inside(flown) == 0
    assert independent_violations(envelope, np.array(flown)) == []
    assert math.dist(flown[-1], target) < 1.0, "it still gets there"

    blind = LinkRoute(envelope)
    blind.set_target(target)
    assert inside(_fly_with_momentum(blind, start, velocity, 30.0, use_velocity=False)) > 0


def test_a_moving_vehicle_with_a_clear_turn_is_not_made_to_stop() -> None:
    """In the open the route is the same with and without the velocity: no braking detour."""
    envelope = Envelope.for_area(AREA, [TOWER], clearance_m=5.0)
    with_velocity, without = LinkRoute(envelope), LinkRoute(envelope)
    for route in (with_velocity, without):
        route.set_target((20.0, 180.0, 50.0))
    position = (20.0, 20.0, 50.0)
    assert with_velocity.setpoint(position, (10.0, 0.0, 0.0)) == without.setpoint(position)
