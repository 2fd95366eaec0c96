"""Unit tests of the vehicle state machine and kinematics, in simulated time (no sockets)."""

from __future__ import annotations

import math

import pytest

from sitl_mock.flavours import ARDUPILOT, PX4, MavResult, Severity
from sitl_mock.geo import GeoPoint, ned_to_global
from sitl_mock.vehicle import (
    FRAME_GLOBAL_INT,
    FRAME_GLOBAL_RELATIVE_ALT_INT,
    FRAME_LOCAL_NED,
    FRAME_LOCAL_OFFSET_NED,
    LANDED_IN_AIR,
    LANDED_ON_GROUND,
    LANDED_TAKEOFF,
    POSITION_ONLY_MASK,
    Vec3,
    Vehicle,
    VehicleConfig,
)
from tests.sitl_mock.helpers import run_vehicle

NAN = float("nan")
VELOCITY_ONLY_MASK = 0b110111000111  # positions, accelerations, yaw and yaw rate ignored


def ready_vehicle(flavour=ARDUPILOT, **config) -> Vehicle:
    config.setdefault("ready_delay_s", 1.0)
    vehicle = Vehicle(flavour, VehicleConfig(**config))
    run_vehicle(vehicle, lambda v: v.ready, max_s=5.0)
    vehicle.drain_events()
    return vehicle


def ardupilot_airborne(alt_m: float = 10.0, **config) -> Vehicle:
    """ArduPilot in GUIDED, armed, takeoff to ``alt_m`` finished."""
    vehicle = ready_vehicle(ARDUPILOT, **config)
    assert vehicle.set_mode_by_name("GUIDED").accepted
    assert vehicle.arm().accepted
    assert vehicle.takeoff(alt_m).accepted
    run_vehicle(vehicle, lambda v: v.landed_state == LANDED_IN_AIR, max_s=30.0)
    return vehicle


def goto_local(vehicle: Vehicle, n: float, e: float, d: float, mask: int = POSITION_ONLY_MASK):
    return vehicle.set_position_target_local(FRAME_LOCAL_NED, mask, n, e, d, 0, 0, 0, 0)


def close_to(vehicle: Vehicle, point: tuple[float, float, float], tol_m: float = 1.0) -> bool:
    return math.dist(vehicle.position, point) < tol_m


# ---------------------------------------------------------------- start-up, arming, modes


def test_ardupilot_start_up_as_arducopter_sitl_goes_through_it():
    """Origin ~19 s, pre-arm ~22 s, GPS use ~40 s; GUIDED granted on the ground before any of it
    (undone by the RC mode switch's first read at ~2.2 s); arming in STABILIZE once the pre-arm
    checks pass, in GUIDED only once the EKF uses GPS."""
    vehicle = Vehicle(ARDUPILOT, VehicleConfig())
    outcome = vehicle.arm()
    assert outcome.result is MavResult.FAILED
    assert [e.text for e in vehicle.drain_events()] == ["PreArm: AHRS: waiting for home"]
    assert vehicle.set_mode_by_name("GUIDED").accepted  # disarmed: no position needed
    run_vehicle(vehicle, lambda v: v.mode.name == "STABILIZE", max_s=3.0)
    assert 2.1 < vehicle.time_s < 2.3  # the mode switch's first read
    assert vehicle.ekf_flags & 128  # constant-position mode: no GPS yet
    run_vehicle(vehicle, lambda v: v.origin_set, max_s=20.0)
    assert 18.9 < vehicle.time_s < 19.1
    assert [e.text for e in vehicle.drain_events()] == ["EKF3 IMU0 origin set"]
    run_vehicle(vehicle, lambda v: v.prearm_ok, max_s=23.0)
    assert vehicle.set_mode_by_name("GUIDED").accepted
    outcome = vehicle.arm()
    assert outcome.result is MavResult.FAILED
    assert [e.text for e in vehicle.drain_events()] == ["Arm: Need Position Estimate"]
    vehicle.rc_mode_switch("STABILIZE")  # the pilot
    assert vehicle.arm().accepted  # STABILIZE needs no position
    assert vehicle.counters["arms_in_STABILIZE"] == 1
    assert vehicle.takeoff(10.0).result is MavResult.FAILED  # no position estimate yet
    assert vehicle.disarm().accepted
    run_vehicle(vehicle, lambda v: v.ready, max_s=41.0)
    assert 39.9 < vehicle.time_s < 40.1
    assert "EKF3 IMU0 is using GPS" in [e.text for e in vehicle.drain_events()]
    assert vehicle.ekf_flags == 831
    assert vehicle.arm().accepted
    assert vehicle.takeoff(10.0).result is MavResult.FAILED  # STABILIZE: no take-off
    vehicle.rc_mode_switch("ALT_HOLD")
    assert vehicle.takeoff(10.0).result is MavResult.FAILED  # ALT_HOLD does not navigate
    assert vehicle.set_mode_by_name("GUIDED").accepted
    assert vehicle.takeoff(10.0).accepted


def test_ardupilot_refuses_guided_when_armed_without_a_position_and_takeoff_when_disarmed():
    vehicle = Vehicle(ARDUPILOT, VehicleConfig())
    run_vehicle(vehicle, lambda v: v.prearm_ok, max_s=23.0)
    assert vehicle.arm().accepted  # STABILIZE
    outcome = vehicle.set_mode_by_name("GUIDED")
    assert outcome.result is MavResult.FAILED
    assert "requires position" in outcome.reason
    assert vehicle.disarm().accepted
    run_vehicle(vehicle, lambda v: v.ready, max_s=41.0)
    assert vehicle.set_mode_by_name("GUIDED").accepted
    assert vehicle.takeoff(10.0).result is MavResult.FAILED  # disarmed


def test_ardupilot_disarms_10_s_after_arming_without_taking_off():
    vehicle = Vehicle(ARDUPILOT, VehicleConfig(ready_delay_s=1.0))
    run_vehicle(vehicle, lambda v: v.ready, max_s=2.0)
    assert vehicle.set_mode_by_name("GUIDED").accepted
    assert vehicle.arm().accepted
    armed_at = vehicle.time_s
    run_vehicle(vehicle, lambda v: not v.armed, max_s=12.0)
    assert 9.9 < vehicle.time_s - armed_at < 10.1
    assert vehicle.takeoff(10.0).result is MavResult.FAILED


def test_px4_takes_off_at_a_near_position_and_not_at_a_far_one():
    vehicle = Vehicle(PX4, VehicleConfig(ready_delay_s=1.0))
    run_vehicle(vehicle, lambda v: v.ready, max_s=2.0)
    home = vehicle.home
    assert vehicle.arm().accepted
    # Latitude/longitude 0/0, as a client that writes 0 for "unused": accepted, never flown.
    assert vehicle.takeoff(home.alt_amsl_m + 10.0, 0.0, 0.0).accepted
    assert vehicle.mode.name == "AUTO.TAKEOFF"
    run_vehicle(vehicle, lambda v: not v.armed, max_s=12.0)
    assert vehicle.alt_m == 0.0 and vehicle.counters["takeoffs_not_flown"] == 1
    assert "Disarmed by auto preflight disarming" in [e.text for e in vehicle.drain_events()]
    # NaN: where it stands.
    assert vehicle.arm().accepted
    assert vehicle.takeoff(home.alt_amsl_m + 10.0, NAN, NAN).accepted
    run_vehicle(vehicle, lambda v: v.mode.name == "AUTO.LOITER", max_s=30.0)
    assert close_to(vehicle, (0.0, 0.0, -10.0), 0.5)
    # A near take-off position: up, then there.
    vehicle2 = Vehicle(PX4, VehicleConfig(ready_delay_s=1.0))
    run_vehicle(vehicle2, lambda v: v.ready, max_s=2.0)
    there = ned_to_global(home, 30.0, -20.0, 0.0)
    assert vehicle2.arm().accepted
    assert vehicle2.takeoff(home.alt_amsl_m + 8.0, there.lat_deg, there.lon_deg).accepted
    run_vehicle(vehicle2, lambda v: close_to(v, (30.0, -20.0, -8.0)), max_s=40.0)


def test_px4_refuses_arming_before_ready_with_temporarily_rejected():
    vehicle = Vehicle(PX4, VehicleConfig(ready_delay_s=5.0))
    assert vehicle.arm().result is MavResult.TEMPORARILY_REJECTED
    events = vehicle.drain_events()
    assert events and events[0].severity is Severity.CRITICAL


def test_ardupilot_will_not_arm_in_rtl_or_land_mode():
    vehicle = ready_vehicle()
    assert vehicle.set_mode_by_name("LAND").accepted
    assert vehicle.arm().result is MavResult.FAILED
    assert vehicle.drain_events()[-1].text == "Arm: Mode not armable"
    assert vehicle.arm(force=True).accepted


def test_unknown_mode_number_is_refused():
    vehicle = ready_vehicle()
    assert vehicle.set_mode(3).result is MavResult.FAILED  # AUTO: no mission support
    assert vehicle.mode.name == "STABILIZE"


def test_armed_on_the_ground_without_takeoff_disarms_after_the_delay():
    vehicle = ready_vehicle(auto_disarm_s=3.0)
    vehicle.set_mode_by_name("GUIDED")
    assert vehicle.arm().accepted
    elapsed = run_vehicle(vehicle, lambda v: not v.armed, max_s=10.0)
    assert 2.9 < elapsed < 3.1
    assert vehicle.counters["auto_disarms"] == 1


def test_disarm_in_the_air_is_refused_unless_forced_and_then_it_falls():
    vehicle = ardupilot_airborne(10.0)
    assert vehicle.disarm().result is MavResult.FAILED
    assert vehicle.armed
    assert vehicle.disarm(force=True).accepted
    elapsed = run_vehicle(vehicle, lambda v: v.landed, max_s=5.0)
    assert elapsed < 2.0  # free fall from 10 m takes ~1.4 s


# ---------------------------------------------------------------- takeoff


def test_ardupilot_takeoff_climbs_within_the_vertical_speed_limit():
    vehicle = ready_vehicle(max_speed_up_mps=3.0)
    vehicle.set_mode_by_name("GUIDED")
    vehicle.arm()
    assert vehicle.takeoff(20.0).accepted
    states = []
    run_vehicle(
        vehicle,
        lambda v: v.landed_state == LANDED_IN_AIR,
        max_s=30.0,
        each_step=lambda v: states.append((v.landed_state, -v.velocity.d)),
    )
    assert states[0][0] == LANDED_TAKEOFF
    assert max(climb for _, climb in states) <= 3.0 + 1e-9
    assert vehicle.alt_m == pytest.approx(20.0, abs=0.3)


def test_ardupilot_takeoff_needs_armed_guided_and_an_altitude():
    vehicle = ready_vehicle()
    assert vehicle.takeoff(10.0).result is MavResult.FAILED  # disarmed
    vehicle.set_mode_by_name("GUIDED")
    vehicle.arm()
    assert vehicle.takeoff(NAN).result is MavResult.FAILED
    assert vehicle.takeoff(0.0).result is MavResult.FAILED
    assert vehicle.takeoff(5.0).accepted


def test_ardupilot_position_target_while_takeoff_is_on_the_ground_cancels_it():
    vehicle = ready_vehicle(auto_disarm_s=5.0)
    vehicle.set_mode_by_name("GUIDED")
    vehicle.arm()
    vehicle.takeoff(10.0)
    vehicle.step(0.1)  # still spooling up
    assert goto_local(vehicle, 20, 0, -10) == "cancelled_takeoff"
    run_vehicle(vehicle, lambda v: not v.armed, max_s=10.0)  # stays down, then auto-disarms
    assert vehicle.alt_m == 0.0
    assert vehicle.counters["takeoffs_cancelled"] == 1
    assert vehicle.counters["liftoffs"] == 0


def test_ardupilot_position_target_once_airborne_replaces_the_takeoff():
    vehicle = ready_vehicle()
    vehicle.set_mode_by_name("GUIDED")
    vehicle.arm()
    vehicle.takeoff(10.0)
    run_vehicle(vehicle, lambda v: v.alt_m > 2.0, max_s=10.0)
    assert goto_local(vehicle, 15, 0, -5) == "accepted"
    run_vehicle(vehicle, lambda v: close_to(v, (15, 0, -5), 0.3), max_s=30.0)


def test_px4_takeoff_uses_amsl_altitude_and_switches_to_hold_when_done():
    home = GeoPoint(47.0, 8.0, 500.0)
    vehicle = ready_vehicle(PX4, home=home)
    assert vehicle.arm().accepted
    assert vehicle.takeoff(508.0).accepted  # param7 is AMSL on PX4: 8 m above home
    assert vehicle.mode.name == "AUTO.TAKEOFF"
    run_vehicle(vehicle, lambda v: v.mode.name == "AUTO.LOITER", max_s=20.0)
    run_vehicle(vehicle, lambda v: close_to(v, (0, 0, -8), 0.1), max_s=10.0)


def test_px4_takeoff_without_altitude_uses_the_default():
    vehicle = ready_vehicle(PX4, takeoff_alt_m=4.0)
    vehicle.arm()
    assert vehicle.takeoff(NAN).accepted
    run_vehicle(vehicle, lambda v: v.mode.name == "AUTO.LOITER", max_s=20.0)
    assert vehicle.alt_m == pytest.approx(4.0, abs=0.3)


# ---------------------------------------------------------------- position control


def test_flies_60_m_in_about_11_s_and_holds_within_a_metre():
    vehicle = ardupilot_airborne(10.0)
    assert goto_local(vehicle, 60, 0, -10) == "accepted"
    speeds = []
    elapsed = run_vehicle(
        vehicle,
        lambda v: close_to(v, (60, 0, -10), 1.0),
        max_s=30.0,
        each_step=lambda v: speeds.append(math.hypot(v.velocity.n, v.velocity.e)),
    )
    assert 8.0 < elapsed < 13.0
    assert max(speeds) <= 10.0 + 1e-9
    for _ in range(500):  # 10 s of holding
        vehicle.step(0.02)
        assert close_to(vehicle, (60, 0, -10), 1.0)
    assert close_to(vehicle, (60, 0, -10), 0.05)


def test_speed_and_acceleration_limits_hold_on_a_long_diagonal_leg():
    vehicle = ardupilot_airborne(10.0, max_speed_h_mps=7.0, accel_h_mps2=2.0)
    goto_local(vehicle, 300, -200, -40)
    samples = []
    run_vehicle(
        vehicle,
        lambda v: close_to(v, (300, -200, -40), 0.5),
        max_s=120.0,
        each_step=lambda v: samples.append((v.velocity, v.acceleration)),
    )
    assert max(math.hypot(v.n, v.e) for v, _ in samples) <= 7.0 + 1e-9
    assert max(-v.d for v, _ in samples) <= 3.0 + 1e-9
    assert max(math.hypot(a.n, a.e) for _, a in samples) <= 2.0 + 1e-6
    assert max(math.hypot(v.n, v.e) for v, _ in samples) > 6.9  # it did reach cruise speed


def test_setpoints_outside_guided_are_ignored_on_ardupilot():
    vehicle = ready_vehicle()
    vehicle.set_mode_by_name("LOITER")
    assert goto_local(vehicle, 10, 0, -10) == "ignored_mode"
    assert vehicle.counters["setpoints_ignored_mode"] == 1


def test_guided_holds_the_last_target_when_setpoints_stop_on_ardupilot():
    vehicle = ardupilot_airborne(10.0)
    goto_local(vehicle, 20, 5, -12)
    run_vehicle(vehicle, lambda v: v.time_s > 60.0, max_s=70.0)
    assert vehicle.mode.name == "GUIDED"
    assert close_to(vehicle, (20, 5, -12), 0.1)


def test_ardupilot_reentering_guided_holds_instead_of_resuming_the_old_target():
    vehicle = ardupilot_airborne(10.0)
    goto_local(vehicle, 80, 0, -10)
    run_vehicle(vehicle, lambda v: v.position.n > 20.0, max_s=20.0)
    assert vehicle.set_mode_by_name("LOITER").accepted
    assert vehicle.set_mode_by_name("GUIDED").accepted
    run_vehicle(vehicle, lambda v: v.time_s > 0 and math.hypot(*v.velocity[:2]) < 0.01, 20.0)
    for _ in range(250):
        vehicle.step(0.02)
    # It braked to a stop (10 m/s at 2.5 m/s² takes 20 m) and held there; it did not go on.
    assert vehicle.position.n == pytest.approx(40.0, abs=1.5)
    assert vehicle.velocity.n == pytest.approx(0.0, abs=1e-3)


def test_velocity_setpoint_is_followed_then_stops_after_3_s_on_ardupilot():
    vehicle = ardupilot_airborne(10.0)
    outcome = vehicle.set_position_target_local(
        FRAME_LOCAL_NED, VELOCITY_ONLY_MASK, 0, 0, 0, 2.0, 0.0, 0.0, 0
    )
    assert outcome == "accepted"
    sent_s = vehicle.time_s
    run_vehicle(vehicle, lambda v: v.time_s - sent_s > 2.9, max_s=3.0)
    assert vehicle.velocity.n == pytest.approx(2.0, abs=1e-6)
    run_vehicle(vehicle, lambda v: abs(v.velocity.n) < 0.01 and v.time_s - sent_s > 3.5, 10.0)
    stopped_at = vehicle.position
    for _ in range(100):
        vehicle.step(0.02)
    assert close_to(vehicle, stopped_at, 0.05)


def test_local_offset_frame_is_relative_to_the_current_position():
    vehicle = ardupilot_airborne(10.0)
    start = vehicle.position
    vehicle.set_position_target_local(
        FRAME_LOCAL_OFFSET_NED, POSITION_ONLY_MASK, 5, -5, 0, 0, 0, 0, 0
    )
    run_vehicle(vehicle, lambda v: close_to(v, (start.n + 5, start.e - 5, start.d), 0.1), 20.0)


def test_global_setpoints_in_amsl_and_relative_frames():
    home = GeoPoint(-35.0, 149.0, 600.0)
    vehicle = ardupilot_airborne(10.0, home=home)
    target = ned_to_global(home, 30.0, -20.0, -15.0)
    outcome = vehicle.set_position_target_global(
        FRAME_GLOBAL_INT, POSITION_ONLY_MASK, target.lat_deg, target.lon_deg, 615.0, 0, 0, 0, 0
    )
    assert outcome == "accepted"
    run_vehicle(vehicle, lambda v: close_to(v, (30, -20, -15), 0.1), max_s=30.0)
    vehicle.set_position_target_global(
        FRAME_GLOBAL_RELATIVE_ALT_INT,
        POSITION_ONLY_MASK,
        home.lat_deg,
        home.lon_deg,
        8.0,
        0,
        0,
        0,
        0,
    )
    run_vehicle(vehicle, lambda v: close_to(v, (0, 0, -8), 0.1), max_s=30.0)


@pytest.mark.parametrize(
    ("values", "mask", "expected"),
    [
        ((NAN, 0.0, -10.0), POSITION_ONLY_MASK, "rejected_invalid"),
        ((0.0, math.inf, -10.0), POSITION_ONLY_MASK, "rejected_invalid"),
        ((5.0, 5.0, -10.0), POSITION_ONLY_MASK | 1, "unsupported"),  # x ignored, y and z not
        ((5.0, 5.0, -10.0), 0b110111111111, "unsupported"),  # nothing but accelerations
        ((NAN, NAN, NAN), VELOCITY_ONLY_MASK, "accepted"),  # ignored fields may be NaN
    ],
)
def test_bad_setpoints_are_rejected_and_counted(values, mask, expected):
    vehicle = ardupilot_airborne(10.0)
    outcome = vehicle.set_position_target_local(FRAME_LOCAL_NED, mask, *values, 0, 0, 0, 0)
    assert outcome == expected
    assert vehicle.counters[f"setpoints_{expected}"] == 1
    if expected != "accepted":
        for _ in range(250):
            vehicle.step(0.02)
        assert close_to(vehicle, (0, 0, -10), 0.05)  # still holding the takeoff point


def test_unknown_frame_is_rejected():
    vehicle = ardupilot_airborne(10.0)
    outcome = vehicle.set_position_target_local(12, POSITION_ONLY_MASK, 1, 1, -10, 0, 0, 0, 0)
    assert outcome == "rejected_frame"


# ---------------------------------------------------------------- geofence


def test_setpoint_outside_the_fence_is_rejected_and_nothing_moves():
    vehicle = ardupilot_airborne(10.0, fence_radius_m=100.0, fence_alt_max_m=50.0)
    assert goto_local(vehicle, 150, 0, -10) == "rejected_fence"
    assert goto_local(vehicle, 10, 0, -60) == "rejected_fence"
    for _ in range(200):
        vehicle.step(0.02)
    assert close_to(vehicle, (0, 0, -10), 0.05)
    assert vehicle.counters["setpoints_rejected_fence"] == 2


def test_setpoint_outside_the_fence_is_clamped_with_fence_action_clamp():
    vehicle = ardupilot_airborne(10.0, fence_radius_m=50.0, fence_action="clamp")
    assert goto_local(vehicle, 0, 80, -10) == "accepted"
    run_vehicle(vehicle, lambda v: close_to(v, (0, 50, -10), 0.1), max_s=30.0)
    assert vehicle.counters["setpoints_clamped_fence"] == 1


def test_velocity_setpoint_is_held_at_the_fence():
    vehicle = ardupilot_airborne(10.0, fence_radius_m=40.0)
    vehicle.set_position_target_local(FRAME_LOCAL_NED, VELOCITY_ONLY_MASK, 0, 0, 0, 5, 0, 0, 0)

    def keep_pushing(v: Vehicle) -> None:
        v.set_position_target_local(FRAME_LOCAL_NED, VELOCITY_ONLY_MASK, 0, 0, 0, 5, 0, 0, 0)

    run_vehicle(vehicle, lambda v: v.time_s > 40.0, max_s=60.0, each_step=keep_pushing)
    assert math.hypot(vehicle.position.n, vehicle.position.e) == pytest.approx(40.0, abs=1e-6)
    assert vehicle.counters["fence_holds"] >= 1


# ---------------------------------------------------------------- PX4 offboard


def stream_setpoints(vehicle: Vehicle, target: tuple[float, float, float], rate_hz: float):
    """An each_step callback sending ``target`` at ``rate_hz``."""
    state = {"next": vehicle.time_s}

    def _send(v: Vehicle) -> None:
        if v.time_s + 1e-9 >= state["next"]:
            goto_local(v, *target)
            state["next"] += 1.0 / rate_hz

    return _send


def test_px4_offboard_needs_a_setpoint_stream_above_2_hz_first():
    vehicle = ready_vehicle(PX4)
    assert vehicle.set_mode_by_name("OFFBOARD").result is MavResult.TEMPORARILY_REJECTED
    goto_local(vehicle, 0, 0, -5)  # one setpoint is not a stream
    assert vehicle.set_mode_by_name("OFFBOARD").result is MavResult.TEMPORARILY_REJECTED
    slow = stream_setpoints(vehicle, (0, 0, -5), rate_hz=1.0)
    run_vehicle(vehicle, lambda v: v.time_s > 5.0, max_s=6.0, each_step=slow)
    assert vehicle.set_mode_by_name("OFFBOARD").result is MavResult.TEMPORARILY_REJECTED
    fast = stream_setpoints(vehicle, (0, 0, -5), rate_hz=10.0)
    start = vehicle.time_s
    run_vehicle(vehicle, lambda v: v.time_s - start > 1.05, max_s=2.0, each_step=fast)
    assert vehicle.set_mode_by_name("OFFBOARD").accepted
    assert vehicle.counters["setpoints_buffered"] > 10


def test_px4_offboard_takes_off_from_the_ground_and_reaches_the_setpoint():
    vehicle = ready_vehicle(PX4, offboard_stream_min_s=0.5)
    stream = stream_setpoints(vehicle, (10, 5, -6), rate_hz=10.0)
    run_vehicle(vehicle, lambda v: v.time_s > 2.0, max_s=3.0, each_step=stream)
    assert vehicle.set_mode_by_name("OFFBOARD").accepted
    assert vehicle.arm().accepted
    run_vehicle(vehicle, lambda v: close_to(v, (10, 5, -6), 0.2), max_s=30.0, each_step=stream)


def test_px4_offboard_failsafe_holds_when_setpoints_stop():
    vehicle = ready_vehicle(PX4, offboard_stream_min_s=0.5, offboard_timeout_s=1.0)
    stream = stream_setpoints(vehicle, (10, 0, -6), rate_hz=10.0)
    run_vehicle(vehicle, lambda v: v.time_s > 2.0, max_s=3.0, each_step=stream)
    vehicle.set_mode_by_name("OFFBOARD")
    vehicle.arm()
    run_vehicle(vehicle, lambda v: close_to(v, (10, 0, -6), 0.2), max_s=30.0, each_step=stream)
    vehicle.drain_events()
    last_setpoint_s = vehicle.time_s - 0.02
    elapsed = run_vehicle(vehicle, lambda v: v.mode.name != "OFFBOARD", max_s=5.0)
    assert vehicle.mode.name == "AUTO.LOITER"
    assert 0.9 < vehicle.time_s - last_setpoint_s < 1.2, elapsed
    assert vehicle.counters["failsafe_offboard"] == 1
    assert any("offboard" in e.text for e in vehicle.drain_events())
    for _ in range(250):
        vehicle.step(0.02)
    assert close_to(vehicle, (10, 0, -6), 0.3)  # holds where it was


# ---------------------------------------------------------------- failsafes, RTL, land


def test_gcs_heartbeat_loss_triggers_rtl_which_lands_at_home_and_disarms():
    vehicle = ardupilot_airborne(10.0, gcs_failsafe_s=5.0)
    goto_local(vehicle, 40, 30, -20)
    run_vehicle(
        vehicle,
        lambda v: close_to(v, (40, 30, -20), 0.5),
        max_s=30.0,
        each_step=lambda v: v.note_gcs_heartbeat(),  # a ground station at 50 Hz
    )
    vehicle.note_gcs_heartbeat()
    heartbeat_s = vehicle.time_s
    run_vehicle(vehicle, lambda v: v.mode.name == "RTL", max_s=10.0)
    assert 5.0 < vehicle.time_s - heartbeat_s < 5.1
    assert vehicle.gcs_failsafe_active
    assert vehicle.counters["failsafe_gcs"] == 1
    run_vehicle(vehicle, lambda v: not v.armed, max_s=120.0)
    assert math.hypot(vehicle.position.n, vehicle.position.e) < 1.0
    assert vehicle.landed and vehicle.alt_m == 0.0
    vehicle.drain_events()
    vehicle.note_gcs_heartbeat()
    assert not vehicle.gcs_failsafe_active
    assert vehicle.drain_events()[0].text == "GCS Failsafe Cleared"


def test_no_gcs_failsafe_without_a_ground_station_ever_seen_or_when_disabled():
    vehicle = ardupilot_airborne(10.0, gcs_failsafe_s=1.0)
    run_vehicle(vehicle, lambda v: v.time_s > 30.0, max_s=40.0)
    assert vehicle.mode.name == "GUIDED"
    quiet = ardupilot_airborne(10.0, gcs_failsafe_s=1.0, gcs_failsafe_action="none")
    quiet.note_gcs_heartbeat()
    run_vehicle(quiet, lambda v: v.time_s > 30.0, max_s=40.0)
    assert quiet.mode.name == "GUIDED"


def test_gcs_failsafe_land_action_on_px4():
    vehicle = ready_vehicle(PX4, gcs_failsafe_s=2.0, gcs_failsafe_action="land")
    vehicle.note_gcs_heartbeat()
    vehicle.arm()
    vehicle.takeoff(NAN)
    run_vehicle(vehicle, lambda v: v.mode.name == "AUTO.LAND", max_s=10.0)
    run_vehicle(vehicle, lambda v: not v.armed, max_s=30.0)
    assert vehicle.landed


def test_rtl_climbs_to_the_return_altitude_first():
    vehicle = ardupilot_airborne(5.0, rtl_alt_m=15.0)
    goto_local(vehicle, 30, 0, -5)
    run_vehicle(vehicle, lambda v: close_to(v, (30, 0, -5), 0.3), max_s=30.0)
    assert vehicle.return_to_launch().accepted
    track = []
    run_vehicle(
        vehicle, lambda v: v.landed, max_s=120.0, each_step=lambda v: track.append(v.position)
    )
    assert max(-p.d for p in track) == pytest.approx(15.0, abs=0.5)
    # It does not head home before it has climbed.
    climbing = [p for p in track if -p.d < 14.0 and p.n > 29.0]
    assert all(abs(p.n - 30) < 0.5 for p in climbing)


def test_land_descends_where_it_is_and_disarms():
    vehicle = ardupilot_airborne(8.0, land_speed_mps=1.0)
    assert vehicle.land().accepted
    run_vehicle(vehicle, lambda v: not v.armed, max_s=30.0)
    assert vehicle.landed and close_to(vehicle, (0, 0, 0), 0.05)


# ---------------------------------------------------------------- battery


def test_battery_drains_faster_in_flight_than_on_the_ground():
    vehicle = ready_vehicle(battery_capacity_mah=5000.0)
    start_pct = vehicle.battery_remaining_pct
    run_vehicle(vehicle, lambda v: v.time_s > 61.0, max_s=70.0)
    idle_drop = start_pct - vehicle.battery_remaining_pct
    flying = ardupilot_airborne(10.0, battery_capacity_mah=5000.0, gcs_failsafe_action="none")
    before = flying.battery_remaining_pct
    voltage_before = flying.battery_voltage_v
    start = flying.time_s
    run_vehicle(flying, lambda v: v.time_s - start > 60.0, max_s=70.0)
    flying_drop = before - flying.battery_remaining_pct
    # ~15 A for a minute is 250 mAh: 5 % of 5000 mAh.
    assert flying_drop == pytest.approx(5.0, rel=0.05)
    assert flying_drop > 10 * idle_drop > 0
    assert flying.battery_voltage_v < voltage_before


def test_battery_failsafe_lands():
    vehicle = ardupilot_airborne(10.0, battery_capacity_mah=300.0, battery_failsafe_pct=20.0)
    run_vehicle(vehicle, lambda v: v.mode.name == "LAND", max_s=120.0)
    assert vehicle.battery_remaining_pct <= 20.0
    assert vehicle.counters["failsafe_battery"] == 1
    run_vehicle(vehicle, lambda v: not v.armed, max_s=60.0)
    assert vehicle.arm().result is MavResult.FAILED  # too low to arm again


# ---------------------------------------------------------------- configuration


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("max_speed_h_mps", 0.0),
        ("accel_h_mps2", -1.0),
        ("ready_delay_s", NAN),
        ("fence_radius_m", -5.0),
        ("gcs_failsafe_action", "explode"),
        ("fence_action", "ignore"),
        ("battery_failsafe_pct", 100.0),
        ("home", GeoPoint(95.0, 0.0, 0.0)),
    ],
)
def test_config_validation_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        VehicleConfig(**{field: value}).validate()


def test_landed_state_on_the_ground_at_start():
    vehicle = Vehicle(PX4)
    assert vehicle.landed_state == LANDED_ON_GROUND
    assert vehicle.position == Vec3(0.0, 0.0, 0.0)
