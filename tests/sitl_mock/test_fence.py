"""The uploaded fence on the mock (sitl_mock/fence.py, sitl_mock/mission.py): its rules, its
breach actions per flavour (stepped vehicles), its mission protocol (a fake link with a manual
clock) and the whole of it over the wire (raw pymavlink), as ArduCopter's and PX4's SITLs do."""

from __future__ import annotations

import struct
import time
from collections import Counter
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl_mock.config import VehicleConfig
from sitl_mock.fence import (
    ALT_MAX,
    CMD_CIRCLE_EXCLUSION,
    CMD_POLYGON_EXCLUSION,
    CMD_POLYGON_INCLUSION,
    CMD_RETURN_POINT,
    POLYGON,
    AutopilotFence,
    Breach,
    FenceItem,
    check_items,
    inside_polygon,
)
from sitl_mock.flavours import ARDUPILOT, PX4, px4_custom_mode
from sitl_mock.geo import GeoPoint, ned_to_global
from sitl_mock.kinematics import Vec3
from sitl_mock.mission import FenceMissionServer
from sitl_mock.params import parameter_table, set_parameter
from sitl_mock.vehicle import FRAME_LOCAL_NED, LANDED_IN_AIR, POSITION_ONLY_MASK, Vehicle
from tests.sitl_mock.helpers import MavClient, run_vehicle

MAV = mavlink
FENCE = MAV.MAV_MISSION_TYPE_FENCE
VELOCITY_ONLY_MASK = 0b0000_1100_0111
GUIDED = 4


def square(home: GeoPoint, command: int, n0: float, e0: float, n1: float, e1: float):
    """A rectangle's four fence items (NED corners around ``home``)."""
    corners = [(n0, e0), (n0, e1), (n1, e1), (n1, e0)]
    items = []
    for n, e in corners:
        point = ned_to_global(home, n, e, 0.0)
        items.append(
            FenceItem(command, 0, 4, round(point.lat_deg * 1e7), round(point.lon_deg * 1e7))
        )
    return items


def site(home: GeoPoint) -> list[FenceItem]:
    """Inclusion: 100 m square around home; exclusion: 20 m wide, 20 m east of home."""
    return square(home, CMD_POLYGON_INCLUSION, -50, -50, 50, 50) + square(
        home, CMD_POLYGON_EXCLUSION, -10, 20, 10, 40
    )


def airborne(flavour=ARDUPILOT, alt_m: float = 10.0, **config: Any) -> Vehicle:
    config.setdefault("ready_delay_s", 1.0)
    vehicle = Vehicle(flavour, VehicleConfig(**config))
    run_vehicle(vehicle, lambda v: v.ready, max_s=5.0)
    if flavour is ARDUPILOT:
        assert vehicle.set_mode_by_name("GUIDED").accepted
        assert vehicle.arm().accepted
        assert vehicle.takeoff(alt_m).accepted
    else:
        hover = (0.0, 0.0, -alt_m)
        run_vehicle(vehicle, lambda v: v.time_s > 2.5, 3.0, each_step=lambda v: goto(v, *hover))
        assert vehicle.set_mode_by_name("OFFBOARD").accepted
        assert vehicle.arm().accepted
    run_vehicle(
        vehicle,
        lambda v: v.landed_state == LANDED_IN_AIR and -v.position.d > alt_m - 0.3,
        30.0,
        each_step=(lambda v: goto(v, 0.0, 0.0, -alt_m)) if flavour is PX4 else None,
    )
    vehicle.drain_events()
    return vehicle


def goto(vehicle: Vehicle, n: float, e: float, d: float) -> str:
    return vehicle.set_position_target_local(
        FRAME_LOCAL_NED, POSITION_ONLY_MASK, n, e, d, 0, 0, 0, 0
    )


def velocity(vehicle: Vehicle, vn: float, ve: float) -> str:
    return vehicle.set_position_target_local(
        FRAME_LOCAL_NED, VELOCITY_ONLY_MASK, 0, 0, 0, vn, ve, 0, 0
    )


def fence_on(vehicle: Vehicle, **params: float) -> None:
    fence = vehicle.autopilot_fence
    fence.store(site(vehicle.home))
    defaults = (
        {"FENCE_TYPE": 5, "FENCE_ALT_MAX": 30, "FENCE_ACTION": 1, "FENCE_ENABLE": 1}
        if fence.ardupilot
        else {"GF_MAX_VER_DIST": 30, "GF_ACTION": 2}
    )
    for name, value in {**defaults, **params}.items():
        assert fence.set_param(name, value), name


def texts(vehicle: Vehicle) -> list[str]:
    return [event.text for event in vehicle.drain_events()]


# ---------------------------------------------------------------- rules


def test_items_are_checked_as_ardupilot_does():
    home = ARDUPILOT.default_home
    assert check_items(site(home), True) == (0, "")
    two = [FenceItem(CMD_POLYGON_INCLUSION, 0, 2, 0, 0)] * 2
    assert check_items(two, True) == (1, "Invalid vertex count (2)")
    short = square(home, CMD_POLYGON_INCLUSION, 0, 0, 10, 10)[:3]
    assert check_items(short, True) == (1, "Incorrect item count")
    mixed = square(home, CMD_POLYGON_INCLUSION, 0, 0, 10, 10)
    mixed[1] = FenceItem(CMD_POLYGON_EXCLUSION, 0, 4, mixed[1].x, mixed[1].y)
    assert check_items(mixed, True) == (1, "Received incorrect vertex type")
    circle = FenceItem(CMD_CIRCLE_EXCLUSION, 0, 0.0, 0, 0)
    assert check_items([circle], True) == (1, "Non-positive circle radius")
    ret = FenceItem(CMD_RETURN_POINT, 0, 0, 0, 0)
    assert check_items([ret, ret], True) == (1, "Multiple return points")
    assert check_items([FenceItem(16, 0, 0, 0, 0)], True)[0] == MAV.MAV_MISSION_UNSUPPORTED
    assert check_items([FenceItem(CMD_RETURN_POINT, 1, 0, 0, 0)], True)[0] == 2  # LOCAL_NED


def test_zones_and_breach_wording():
    fence = AutopilotFence(True, ARDUPILOT.default_home, 150.0)
    fence.store(site(fence.home))
    assert [zone.inclusion for zone in fence.zones] == [True, False]
    assert inside_polygon(0, 30, fence.zones[1].polygon)
    assert fence.breach(Vec3(0.0, 0.0, -10.0)).fences == 0
    assert fence.breach(Vec3(0, 30, -10)) == Breach(POLYGON, pytest.approx(10.0, abs=0.01))
    assert fence.breach(Vec3(0, 70, -10)).distance_m == pytest.approx(20.0, abs=0.01)
    fence.set_param("FENCE_ALT_MAX", 20)
    both = fence.breach(Vec3(0, 70, -25))
    assert both.fences == ALT_MAX | POLYGON
    assert both.names == "Max Alt and Polygon fences"
    assert Breach(POLYGON, 1.0).names == "Polygon fence"
    assert fence.breach(Vec3(0, 0, -20)).fences == ALT_MAX  # ArduPilot: at the ceiling
    px4 = AutopilotFence(False, PX4.default_home, 20.0)
    assert px4.breach(Vec3(0, 0, -20)).fences == 0  # PX4: above it only
    assert px4.breach(Vec3(0, 0, -20.5)).fences == ALT_MAX


def test_fence_parameters_per_flavour():
    ap = Vehicle(ARDUPILOT, VehicleConfig(fence_alt_max_m=120.0))
    table = {name: value for name, value, _ in parameter_table(ap, 1)}
    assert table["FENCE_ENABLE"] == 0 and table["FENCE_TYPE"] == 7
    assert table["FENCE_ACTION"] == 1 and table["FENCE_ALT_MAX"] == 120.0
    assert table["AVOID_ENABLE"] == 3 and table["FENCE_RADIUS"] == 1000.0
    assert set_parameter(ap, "FENCE_ALT_MAX", 60.0, MAV.MAV_PARAM_TYPE_REAL32)
    assert not set_parameter(ap, "FENCE_ALT_MAX", 5000.0, MAV.MAV_PARAM_TYPE_REAL32)
    assert not set_parameter(ap, "FENCE_ACTION", 1.5, MAV.MAV_PARAM_TYPE_INT8)
    assert not set_parameter(ap, "FENCE_RADIUS", 50.0, MAV.MAV_PARAM_TYPE_REAL32)  # the cylinder
    assert ap.autopilot_fence.params["FENCE_ALT_MAX"] == 60.0
    px4 = Vehicle(PX4, VehicleConfig(fence_alt_max_m=None))
    table = {name: value for name, value, _ in parameter_table(px4, 1)}
    assert table["GF_ACTION"] == 2 and table["GF_MAX_VER_DIST"] == 0
    three = struct.unpack("<f", struct.pack("<i", 3))[0]  # PX4: integers bit for bit
    assert set_parameter(px4, "GF_ACTION", three, MAV.MAV_PARAM_TYPE_INT32)
    assert px4.autopilot_fence.params["GF_ACTION"] == 3


# ---------------------------------------------------------------- ArduPilot


def test_ardupilot_refuses_position_targets_outside_an_enabled_fence():
    vehicle = airborne()
    fence_on(vehicle, FENCE_ENABLE=0)
    assert goto(vehicle, 0, 70, -10) == "accepted"  # disabled: taken
    assert vehicle.autopilot_fence.set_param("FENCE_ENABLE", 1)
    assert goto(vehicle, 0, 70, -10) == "rejected_fence"  # outside the inclusion
    assert goto(vehicle, 0, 30, -10) == "rejected_fence"  # in the exclusion, at any height
    assert goto(vehicle, 0, 30, -80) == "rejected_fence"
    assert goto(vehicle, 0, 0, -31) == "rejected_fence"  # above FENCE_ALT_MAX
    assert goto(vehicle, 0, 0, -30) == "accepted"  # at it
    assert goto(vehicle, 20, 10, -10) == "accepted"


def test_ardupilot_stops_at_the_fence_with_avoidance_and_breaches_without():
    """As the real ArduCopter SITL did (benchmarks/results/real_sitl_fence.json): 5 m/s east
    towards the exclusion stops FENCE_MARGIN (2 m) short of it with AVOID_ENABLE 3 (the SITL:
    1.98 m); with 0 it crosses, says "Polygon fence breached", goes RTL ("Manual recovery
    started"), and "Fence breach cleared" once RTL has brought it back out."""
    vehicle = airborne()
    fence_on(vehicle)
    run_vehicle(vehicle, lambda v: v.time_s > 25, 30, each_step=lambda v: velocity(v, 0, 5))
    assert 17.5 < vehicle.position.e < 18.0
    assert vehicle.mode.name == "GUIDED" and vehicle.counters["fence_breaches"] == 0
    assert vehicle.counters["fence_avoid_stops"] > 0
    assert texts(vehicle) == []
    assert vehicle.autopilot_fence.set_param("AVOID_ENABLE", 0)
    run_vehicle(vehicle, lambda v: v.mode.name == "RTL", 10, each_step=lambda v: velocity(v, 0, 5))
    assert texts(vehicle) == ["Polygon fence breached", "Manual recovery started"]
    assert 19.9 <= vehicle.position.e < 21.5  # the corners went through degE7 (~1 cm)
    assert vehicle.counters["failsafe_fence"] == 1
    run_vehicle(vehicle, lambda v: v.position.e < 19.0, 30)
    assert texts(vehicle) == ["Fence breach cleared"]
    run_vehicle(vehicle, lambda v: not v.armed, 120)  # RTL lands and disarms at home


@pytest.mark.parametrize(
    ("action", "mode", "said"),
    [
        (0, "GUIDED", ["Polygon fence breached"]),
        (2, "LAND", ["Polygon fence breached", "Manual recovery started"]),
        (4, "BRAKE", ["Polygon fence breached", "Manual recovery started"]),
    ],
)
def test_ardupilot_fence_action(action, mode, said):
    vehicle = airborne()
    fence_on(vehicle, AVOID_ENABLE=0, FENCE_ACTION=action)
    run_vehicle(
        vehicle,
        lambda v: v.counters["fence_breaches"] > 0,
        15,
        each_step=lambda v: velocity(v, 0, 5),
    )
    vehicle.step(0.02)
    assert vehicle.mode.name == mode
    assert texts(vehicle) == said


def test_ardupilot_ceiling_and_far_breaches():
    vehicle = airborne(alt_m=20.0)
    fence_on(vehicle, FENCE_ALT_MAX=15)  # enabled under the vehicle: an immediate breach
    vehicle.step(0.02)
    assert texts(vehicle) == ["Max Alt fence breached", "Manual recovery started"]
    assert vehicle.mode.name == "RTL"
    far = airborne()
    assert goto(far, 0, 200, -10) == "accepted"
    run_vehicle(far, lambda v: v.position.e > 170, 40)
    fence_on(far)  # 120 m outside the inclusion: ArduCopter gives up and lands
    far.step(0.02)
    assert far.mode.name == "LAND"
    assert texts(far)[0] == "Polygon fence breached"


def test_ardupilot_refuses_to_arm_inside_an_exclusion():
    vehicle = Vehicle(ARDUPILOT, VehicleConfig(ready_delay_s=1.0))
    run_vehicle(vehicle, lambda v: v.ready, max_s=5.0)
    home = vehicle.home
    vehicle.autopilot_fence.store(
        square(home, CMD_POLYGON_INCLUSION, -50, -50, 50, 50)
        + square(home, CMD_POLYGON_EXCLUSION, -5, -5, 5, 5)
    )
    vehicle.autopilot_fence.set_param("FENCE_ENABLE", 1)
    vehicle.drain_events()
    assert not vehicle.arm().accepted
    assert texts(vehicle) == ["PreArm: Vehicle breaching Polygon fence"]


# ---------------------------------------------------------------- PX4


@pytest.mark.parametrize(
    ("action", "mode", "said"),
    [
        (2, "AUTO.LOITER", "Failsafe activated due to geofence violation, triggering Hold"),
        (3, "AUTO.RTL", "Failsafe activated due to geofence violation, triggering Return"),
        (5, "AUTO.LAND", "Failsafe activated due to geofence violation, triggering Land"),
        (1, "OFFBOARD", "Failsafe warning triggered due to geofence violation"),
    ],
)
def test_px4_flies_to_a_target_outside_and_acts_by_gf_action(action, mode, said):
    """PX4 takes the offboard target outside the fence (it does not check setpoints) and acts
    when the vehicle itself crosses."""
    vehicle = airborne(PX4)
    fence_on(vehicle, GF_ACTION=action)
    assert goto(vehicle, 0, 70, -10) == "accepted"
    run_vehicle(
        vehicle,
        lambda v: v.counters["fence_breaches"] > 0,
        20,
        each_step=lambda v: goto(v, 0, 70, -10),
    )
    vehicle.step(0.02)
    assert vehicle.mode.name == mode
    assert 19.9 <= vehicle.position.e < 22.0  # it crossed into the exclusion first
    assert texts(vehicle) == [said]


def test_px4_terminate_and_none():
    vehicle = airborne(PX4)
    fence_on(vehicle, GF_ACTION=4)
    run_vehicle(vehicle, lambda v: not v.armed, 20, each_step=lambda v: goto(v, 0, 70, -10))
    assert texts(vehicle) == ["Failsafe activated due to geofence violation, triggering Terminate"]
    run_vehicle(vehicle, lambda v: v.landed, 10)  # it falls
    quiet = airborne(PX4)
    fence_on(quiet, GF_ACTION=0)
    run_vehicle(quiet, lambda v: v.position.e > 45, 20, each_step=lambda v: goto(v, 0, 70, -10))
    assert quiet.mode.name == "OFFBOARD" and texts(quiet) == []


# ---------------------------------------------------------------- mission protocol, manual clock


class FakeLink:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def send(self, message: Any) -> None:
        self.sent.append(message)

    def types(self) -> list[str]:
        return [m.get_type() for m in self.sent]


def _server(ardupilot: bool = True):
    said: list[str] = []
    fence = AutopilotFence(ardupilot, ARDUPILOT.default_home, 100.0)
    enc = mavlink.MAVLink(None, 1, 1)
    server = FenceMissionServer(
        fence, ardupilot, 70, enc, lambda _s, text: said.append(text), Counter()
    )
    gcs = mavlink.MAVLink(None, 255, 190)
    return server, fence, gcs, said


def _from_gcs(gcs: mavlink.MAVLink, message: Any) -> Any:
    """A message as the mock receives it (packed and parsed, with its header)."""
    return mavlink.MAVLink(None, 1, 1).decode(bytearray(message.pack(gcs)))


def test_the_request_is_repeated_and_an_idle_upload_cancelled():
    server, fence, gcs, said = _server()
    link = FakeLink()
    server.handle(link, _from_gcs(gcs, gcs.mission_count_encode(1, 1, 8, FENCE)), 0.0)
    assert link.types() == ["MISSION_REQUEST"] and link.sent[0].seq == 0
    server.tick(0.5)
    assert len(link.sent) == 1
    server.tick(1.1)
    assert link.types() == ["MISSION_REQUEST"] * 2
    assert server.stats["fence_requests_repeated"] == 1
    for t in (2.2, 3.3, 4.4, 5.5, 6.6, 7.7):
        server.tick(t)
    server.tick(8.1)
    assert link.sent[-1].get_type() == "MISSION_ACK"
    assert link.sent[-1].type == MAV.MAV_MISSION_OPERATION_CANCELLED
    assert said == ["Fence upload timeout"] and not server.receiving and fence.items == ()


def test_an_item_out_of_sequence_and_other_mission_types():
    server, fence, gcs, _ = _server()
    link = FakeLink()
    items = site(fence.home)
    server.handle(link, _from_gcs(gcs, gcs.mission_count_encode(1, 1, len(items), FENCE)), 0.0)

    def item(seq: int) -> Any:
        i = items[seq]
        return gcs.mission_item_int_encode(
            1, 1, seq, 0, i.command, 0, 1, i.param1, 0, 0, 0, i.x, i.y, 0, FENCE
        )

    server.handle(link, _from_gcs(gcs, item(0)), 0.1)
    server.handle(link, _from_gcs(gcs, item(0)), 0.2)  # again: ArduPilot says so, goes on
    assert link.sent[-1].get_type() == "MISSION_ACK"
    assert link.sent[-1].type == MAV.MAV_MISSION_INVALID_SEQUENCE
    for seq in range(1, len(items)):
        server.handle(link, _from_gcs(gcs, item(seq)), 0.3)
    assert link.sent[-1].type == MAV.MAV_MISSION_ACCEPTED
    assert fence.items == tuple(items)
    server.handle(link, _from_gcs(gcs, gcs.mission_request_list_encode(1, 1, 0)), 1.0)
    assert link.sent[-1].get_type() == "MISSION_ACK"
    assert link.sent[-1].type == MAV.MAV_MISSION_UNSUPPORTED
    assert link.sent[-1].mission_type == 0
    server.handle(link, _from_gcs(gcs, gcs.mission_clear_all_encode(1, 1, FENCE)), 1.0)
    assert link.sent[-1].type == MAV.MAV_MISSION_ACCEPTED and fence.items == ()


# ---------------------------------------------------------------- over the wire


def upload(client: MavClient, items: list[FenceItem], request: str) -> Any:
    client.mark()
    client.mav.mission_count_send(1, 1, len(items), FENCE)
    while True:
        message = client.wait((request, "MISSION_ACK"), timeout_s=3.0)
        if message.get_type() == "MISSION_ACK":
            return message
        i = items[message.seq]
        client.mav.mission_item_int_send(
            1, 1, message.seq, i.frame, i.command, 0, 1, i.param1, 0, 0, 0, i.x, i.y, 0, FENCE
        )


def download(client: MavClient) -> list[Any]:
    client.mark()
    client.mav.mission_request_list_send(1, 1, FENCE)
    count = client.wait("MISSION_COUNT").count
    got = []
    for seq in range(count):
        client.mav.mission_request_int_send(1, 1, seq, FENCE)
        got.append(client.wait("MISSION_ITEM_INT", lambda m, seq=seq: m.seq == seq))
    client.mav.mission_ack_send(1, 1, MAV.MAV_MISSION_ACCEPTED, FENCE)
    return got


@pytest.mark.parametrize(
    ("flavour", "request_type", "frame_back"),
    [("ardupilot", "MISSION_REQUEST", 0), ("px4", "MISSION_REQUEST_INT", 6)],
)
def test_upload_download_and_refusals_over_the_wire(
    start_mock, connect, flavour, request_type, frame_back
):
    mock = start_mock(flavour)
    client = connect(mock)
    items = [FenceItem(i.command, 6, i.param1, i.x, i.y) for i in site(mock.vehicle.home)]
    ack = upload(client, items, request_type)
    assert (ack.type, ack.mission_type) == (MAV.MAV_MISSION_ACCEPTED, FENCE)
    back = download(client)
    assert [(m.command, m.param1, m.x, m.y) for m in back] == [
        (i.command, i.param1, i.x, i.y) for i in items
    ]
    assert {m.frame for m in back} == {frame_back}  # ArduPilot: always MAV_FRAME_GLOBAL
    assert mock.stats["fence_uploads"] == 1 and mock.stats["fence_downloads"] == 1
    too_many = upload(client, items * 40, request_type)
    assert too_many.type == MAV.MAV_MISSION_NO_SPACE
    bad = [FenceItem(CMD_POLYGON_INCLUSION, 0, 2, i.x, i.y) for i in items[:2]]
    assert upload(client, bad, request_type).type == MAV.MAV_MISSION_ERROR
    client.pump_for(lambda: len(client.statustexts) >= 3 or flavour == "px4", 2.0, "texts")
    if flavour == "ardupilot":
        assert client.statustexts[-3:] == [
            "Only 70 items are supported",
            "Invalid vertex count (2)",
            "Fence validation failed",
        ]
    assert len(download(client)) == len(items)  # the refused uploads left the fence as it was
    # PARAM_SET of a fence parameter: taken and echoed.
    name = b"FENCE_ALT_MAX" if flavour == "ardupilot" else b"GF_MAX_VER_DIST"
    client.mav.param_set_send(1, 1, name, 55.0, MAV.MAV_PARAM_TYPE_REAL32)
    echo = client.wait("PARAM_VALUE", lambda m: m.param_id == name.decode())
    assert echo.param_value == 55.0
    assert mock.stats["param_sets"] == 1


@pytest.mark.slow
def test_ardupilot_breach_over_the_wire_goes_rtl(start_mock, connect):
    mock = start_mock("ardupilot", accel_v_mps2=5.0, max_speed_up_mps=5.0)
    client = connect(mock)
    assert upload(client, site(mock.vehicle.home), "MISSION_REQUEST").type == 0
    for name, value in (("FENCE_TYPE", 5), ("FENCE_ENABLE", 1), ("AVOID_ENABLE", 0)):
        client.mav.param_set_send(1, 1, name.encode(), value, MAV.MAV_PARAM_TYPE_INT8)
        assert client.wait("PARAM_VALUE", lambda m, n=name: m.param_id == n).param_value == value
    client.set_message_interval("LOCAL_POSITION_NED", 10.0)
    client.wait("STATUSTEXT", lambda m: "using GPS" in m.text, timeout_s=10.0)
    assert client.command(MAV.MAV_CMD_DO_SET_MODE, 1, GUIDED).result == 0
    assert client.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    assert client.command(MAV.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 5).result == 0
    client.wait("LOCAL_POSITION_NED", lambda m: m.z < -4.5, timeout_s=15.0)
    # A position target outside: ignored. A velocity towards the exclusion: crosses it.
    client.mav.set_position_target_local_ned_send(
        0, 1, 1, FRAME_LOCAL_NED, POSITION_ONLY_MASK, 0, 80, -5, 0, 0, 0, 0, 0, 0, 0, 0
    )
    client.every(
        0.2,
        lambda: client.mav.set_position_target_local_ned_send(
            0, 1, 1, FRAME_LOCAL_NED, VELOCITY_ONLY_MASK, 0, 0, 0, 0, 8, 0, 0, 0, 0, 0, 0
        ),
    )
    text = client.wait("STATUSTEXT", lambda m: "fence" in m.text, timeout_s=10.0)
    assert text.text == "Polygon fence breached"
    assert text.severity == MAV.MAV_SEVERITY_NOTICE
    client.wait("HEARTBEAT", lambda m: m.custom_mode == 6, timeout_s=2.0)  # RTL
    assert mock.stats["setpoints_rejected_fence"] == 1
    assert mock.stats["failsafe_fence"] == 1


@pytest.mark.slow
def test_px4_breach_over_the_wire_holds(start_mock, connect):
    mock = start_mock("px4", offboard_stream_min_s=0.3, accel_v_mps2=5.0, max_speed_up_mps=5.0)
    client = connect(mock)
    assert upload(client, site(mock.vehicle.home), "MISSION_REQUEST_INT").type == 0
    target = [(0.0, 0.0, -5.0)]

    def stream() -> None:
        client.mav.set_position_target_local_ned_send(
            0, 1, 1, FRAME_LOCAL_NED, POSITION_ONLY_MASK, *target[0], 0, 0, 0, 0, 0, 0, 0, 0
        )

    client.every(0.1, stream)
    client.wait("STATUSTEXT", lambda m: m.text == "Ready for takeoff!", timeout_s=5.0)
    deadline = time.monotonic() + 5.0
    while client.command(MAV.MAV_CMD_DO_SET_MODE, 1, 6, 0).result != 0:
        assert time.monotonic() < deadline, "OFFBOARD never accepted"
        end = time.monotonic() + 0.3
        client.pump_for(lambda end=end: time.monotonic() > end, 1.0, "the stream")
    assert client.command(MAV.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    client.wait("LOCAL_POSITION_NED", lambda m: m.z < -4.5, timeout_s=15.0)
    target[0] = (0.0, 80.0, -5.0)  # a setpoint forced outside the inclusion
    text = client.wait("STATUSTEXT", lambda m: "geofence" in m.text, timeout_s=15.0)
    # 61 characters: two STATUSTEXT chunks (id, chunk_seq), as MAVLink 2 sends a long text.
    rest = client.wait("STATUSTEXT", lambda m: m.id == text.id and m.chunk_seq == 1)
    assert text.text + rest.text == "Failsafe activated due to geofence violation, triggering Hold"
    assert text.severity == MAV.MAV_SEVERITY_CRITICAL
    hold = px4_custom_mode(4, 3)
    client.wait("HEARTBEAT", lambda m: m.custom_mode == hold, timeout_s=2.0)
    # Breached at the exclusion's edge (e = 20 m), then braked to a stop in it: Hold holds
    # where braking ends, as PX4 does (no return to the fence).
    assert 19.9 <= mock.state().position_ned_m.e < 45.0
    assert mock.stats["failsafe_fence"] == 1
