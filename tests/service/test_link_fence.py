"""The autopilot's fence put on the vehicle by the link (``LinkConfig.autopilot_fence``, issue 39):
on both autopilot flavours of the mock, over the pymavlink backend, the envelope is uploaded and
read back before the take-off and before any setpoint; routes then keep out of the exclusions at
every height (the fence's polygons are 2-D); an upload the autopilot refuses keeps the vehicle
on the ground and the stream off, and says why."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import pytest
from shapely.geometry import Point, Polygon, box

from service.routing import PLANNING
from sim.envelope import Envelope, Exclusion
from sitl_mock.server import MockAutopilot
from tests.helpers import tcp_url, wait_for
from tests.service.conftest import AREA, FAST_VEHICLE, mock_in_area_m

pytestmark = pytest.mark.slow

BLOCK = Exclusion(box(25, 10, 35, 40), 0.0, 8.0, "low block")
"""Up to 8 m only: the envelope alone would climb over it; the fence forbids it at any height."""


@pytest.mark.parametrize(
    ("flavour", "backend"),
    [("ardupilot", "pymavlink"), ("px4", "pymavlink"), ("ardupilot", "mavsdk"), ("px4", "mavsdk")],
)
def test_the_fence_is_on_the_vehicle_before_the_take_off_and_routes_keep_out_of_it(
    start_mock: Callable[..., MockAutopilot],
    open_link: Callable[..., Any],
    flavour: str,
    backend: str,
) -> None:
    mock = start_mock(flavour, gcs_failsafe_action="none", **FAST_VEHICLE)
    envelope = Envelope.for_area(AREA, [BLOCK], clearance_m=2.0)
    link = open_link(tcp_url(mock), backend, envelope=envelope, autopilot_fence=True)
    wait_for(lambda: link.state().fence == "uploaded", 15.0, message="the fence uploaded")
    stats = mock.stats
    assert stats["fence_uploads"] == 1 and stats["fence_uploads_refused"] == 0
    fence = mock.with_vehicle(lambda v: (v.autopilot_fence.items, dict(v.autopilot_fence.params)))
    assert len(fence[0]) == 4 + 4  # the area's rectangle and the block's footprint
    if flavour == "ardupilot":
        assert fence[1]["FENCE_ENABLE"] == 1.0 and fence[1]["FENCE_ACTION"] == 1.0
    else:
        assert fence[1]["GF_ACTION"] == 3.0  # return
    link.arm_and_takeoff().result(timeout=30.0)
    # Over the block (z 15 m > its 8 m top) would be legal in the envelope; with the fence on
    # the route goes around it.
    target = (50.0, 25.0, 15.0)
    assert link.set_target(target) == target
    wait_for(
        lambda: (s := link.state()).streaming and s.route and s.route.hold_reason != PLANNING, 5.0
    )
    assert link.state().route.kind == "around"
    deadline = time.monotonic() + 40.0
    closest_m = math.inf
    while math.dist(mock_in_area_m(mock), target) > 1.5 and time.monotonic() < deadline:
        closest_m = min(closest_m, BLOCK.footprint.distance(Point(*_xy(mock))))
        assert closest_m > 0.0, "the vehicle flew into the block"
        time.sleep(0.05)  # sampling the track, not waiting for a condition
    assert math.dist(mock_in_area_m(mock), target) <= 1.5, "the vehicle never got there"
    assert closest_m >= 1.0, closest_m  # 2 m clearance, less the autopilot's tracking error
    assert mock.stats["fence_breaches"] == 0
    assert mock.stats["setpoints_rejected_fence"] == 0


def _xy(mock: MockAutopilot) -> tuple[float, float]:
    x_m, y_m, _ = mock_in_area_m(mock)
    return (x_m, y_m)


@pytest.mark.parametrize("backend", ["pymavlink", "mavsdk"])
def test_a_fence_the_autopilot_refuses_keeps_the_vehicle_down_and_says_why(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any], backend: str
) -> None:
    mock = start_mock("ardupilot", gcs_failsafe_action="none", **FAST_VEHICLE)
    # An inclusion of 80 corners: more than the 70 fence items ArduPilot stores.
    corners = [
        (30 + 29 * math.cos(2 * math.pi * i / 80), 30 + 29 * math.sin(2 * math.pi * i / 80))
        for i in range(80)
    ]
    envelope = Envelope(Polygon(corners), AREA.z_min_m, AREA.z_max_m)
    link = open_link(tcp_url(mock), backend, envelope=envelope, autopilot_fence=True)
    state = wait_for(lambda: (s := link.state()).fence.startswith("failed") and s, 30.0)
    if backend == "pymavlink":
        assert "70 items" in state.fence, state.fence  # the autopilot's reason, passed on
    else:  # MAVSDK reports only its result's name
        assert state.fence.startswith("failed: fence upload: "), state.fence
    assert mock.stats["fence_uploads_refused"] >= 1
    future = link.arm_and_takeoff(timeout_s=3.0)
    with pytest.raises(Exception, match="fence"):
        future.result(timeout=10.0)
    assert not mock.state().armed
    link.set_target((30.0, 30.0, 10.0))
    assert not link.state().streaming
    assert mock.stats["setpoints_received"] == 0


def test_the_fence_is_put_on_again_when_the_vehicles_origin_moves(
    start_mock: Callable[..., MockAutopilot], open_link: Callable[..., Any]
) -> None:
    """The fence is placed around GPS_GLOBAL_ORIGIN (a real PX4's early homes were 0.26-0.5 m
    off it); an origin that moves after the upload puts the fence on again around the new one."""
    from service.frames import GeoPoint

    mock = start_mock("px4", **FAST_VEHICLE)
    envelope = Envelope.for_area(AREA, [BLOCK], clearance_m=2.0)
    link = open_link(tcp_url(mock), envelope=envelope, autopilot_fence=True)
    wait_for(lambda: link.state().fence == "uploaded", 15.0, message="the fence uploaded")
    first = mock.with_vehicle(lambda v: v.autopilot_fence.items)
    with link._cond:
        origin = link._origin
        link._note_origin(GeoPoint(origin.lat_deg + 1e-5, origin.lon_deg, origin.alt_amsl_m))
        assert link._fence == "uploading: the vehicle's origin moved"
    wait_for(lambda: mock.stats["fence_uploads"] == 2, 15.0, message="the fence put on again")
    second = mock.with_vehicle(lambda v: v.autopilot_fence.items)
    assert len(second) == len(first) and second != first  # 1.1 m north: other vertices
