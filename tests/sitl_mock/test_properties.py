"""Property tests of invariants: no accepted target outside the geofence, the vehicle never leaves
it, speed limits always hold, and the frame conversion round-trips."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from sitl_mock.flavours import ARDUPILOT, PX4
from sitl_mock.geo import GeoPoint, global_to_ned, ned_to_global
from sitl_mock.vehicle import FRAME_LOCAL_NED, POSITION_ONLY_MASK, Vehicle, VehicleConfig

RADIUS_M = 100.0
CEILING_M = 60.0
coordinate_m = st.floats(-1000.0, 1000.0, allow_nan=False)


def _airborne(fence_action: str) -> Vehicle:
    vehicle = Vehicle(
        ARDUPILOT,
        VehicleConfig(
            ready_delay_s=0.0,
            fence_radius_m=RADIUS_M,
            fence_alt_max_m=CEILING_M,
            fence_action=fence_action,
            accel_h_mps2=5.0,
            accel_v_mps2=5.0,
        ),
    )
    vehicle.step(0.02)
    vehicle.set_mode_by_name("GUIDED")
    vehicle.arm()
    vehicle.takeoff(10.0)
    while vehicle.landed_state != 2:
        vehicle.step(0.05)
    return vehicle


def _inside(point) -> bool:
    return math.hypot(point[0], point[1]) <= RADIUS_M + 1e-6 and -point[2] <= CEILING_M + 1e-6


@settings(max_examples=60, deadline=None)
@given(st.sampled_from(["reject", "clamp"]), coordinate_m, coordinate_m, coordinate_m)
def test_no_accepted_target_lies_outside_the_fence(fence_action, north, east, down):
    vehicle = _airborne(fence_action)
    outcome = vehicle.set_position_target_local(
        FRAME_LOCAL_NED, POSITION_ONLY_MASK, north, east, down, 0, 0, 0, 0
    )
    target = vehicle.echo_target()
    assert target is not None and target.position is not None
    assert _inside(target.position)
    if fence_action == "reject" and not _inside((north, east, down)):
        assert outcome == "rejected_fence"


@settings(max_examples=15, deadline=None)
@given(
    st.lists(st.tuples(coordinate_m, coordinate_m, st.floats(-80.0, 0.0)), min_size=1, max_size=4),
    st.sampled_from([ARDUPILOT, PX4]),
)
def test_the_vehicle_stays_in_the_fence_and_within_its_speed_limits(targets, flavour):
    vehicle = Vehicle(
        flavour,
        VehicleConfig(
            ready_delay_s=0.0,
            offboard_stream_min_s=0.0,
            fence_radius_m=RADIUS_M,
            fence_alt_max_m=CEILING_M,
            fence_action="clamp",
            max_speed_h_mps=8.0,
            max_speed_up_mps=2.5,
            max_speed_down_mps=2.0,
        ),
    )
    vehicle.step(0.02)
    for north, east, down in targets:
        vehicle.set_position_target_local(
            FRAME_LOCAL_NED, POSITION_ONLY_MASK, north, east, down, 0, 0, 0, 0
        )
    vehicle.set_mode_by_name(flavour.guided_mode)
    vehicle.arm()
    if flavour is ARDUPILOT:
        vehicle.takeoff(5.0)
    for north, east, down in targets:
        for _ in range(400):  # 8 s per target, setpoints streaming at 50 Hz
            vehicle.set_position_target_local(
                FRAME_LOCAL_NED, POSITION_ONLY_MASK, north, east, down, 0, 0, 0, 0
            )
            vehicle.step(0.02)
            v = vehicle.velocity
            assert math.hypot(v.n, v.e) <= 8.0 + 1e-9
            assert -2.5 - 1e-9 <= v.d <= 2.0 + 1e-9
            assert _inside(vehicle.position)
            assert vehicle.position.d <= 0.0  # never below the ground


@given(
    st.floats(-80.0, 80.0),
    st.floats(-179.0, 179.0),
    st.floats(-400.0, 4000.0),
    coordinate_m,
    coordinate_m,
    st.floats(-500.0, 500.0),
)
def test_frame_conversion_round_trips(lat, lon, alt, north, east, down):
    home = GeoPoint(lat, lon, alt)
    point = ned_to_global(home, north, east, down)
    back = global_to_ned(home, point.lat_deg, point.lon_deg, point.alt_amsl_m)
    assert math.dist(back, (north, east, down)) < 1e-5
