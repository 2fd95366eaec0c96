"""The take-off sequence against the strict mock: the rules a real ArduCopter and PX4 enforce.

The ArduPilot mock here runs ArduCopter SITL's start-up in miniature (EKF origin, pre-arm checks,
GPS use and the RC mode switch's first read, in that order, scaled down from ~19/22/40/2.2 s):
GUIDED is granted on the ground before the position estimate and then undone by the mode switch,
arming in STABILIZE passes before arming in GUIDED does, and NAV_TAKEOFF is refused outside GUIDED.
A service that does not wait for the estimate and confirm GUIDED in HEARTBEAT arms in the wrong
mode and never leaves the ground.
"""

from __future__ import annotations

import math
import time

import pytest

from service.link_takeoff import ekf_position_ok
from service.vehicle_link import mavlink
from tests.helpers import tcp_url, wait_for
from tests.service.conftest import AREA, FAST_VEHICLE

STRICT_ARDUPILOT = {
    "mode_switch_read_s": 1.2,
    "origin_delay_s": 0.8,
    "prearm_delay_s": 1.5,
    "ready_delay_s": 3.0,
    **FAST_VEHICLE,
}


@pytest.mark.slow
def test_ardupilot_takes_off_only_in_guided_after_the_position_estimate(start_mock, open_link):
    mock = start_mock("ardupilot", **STRICT_ARDUPILOT)
    link = open_link(tcp_url(mock))
    future = link.arm_and_takeoff(timeout_s=40.0)
    future.result(timeout=45.0)
    stats = mock.stats
    assert stats.get("arms", 0) >= 1
    assert stats.get("arms", 0) == stats.get("arms_in_GUIDED", 0)  # never in another mode
    assert mock.state().alt_m >= 0.9 * AREA.z_min_m - 0.5
    state = link.state()
    assert state.takeoff == "airborne"
    assert any("using GPS" in text for text in state.status_texts)
    assert link._fallback_streams_sent is False  # no positions for 0.8 s is no reason


@pytest.mark.slow
def test_a_mode_switch_during_the_climb_restarts_the_sequence_and_flies_on(start_mock, open_link):
    mock = start_mock("ardupilot", max_speed_up_mps=1.0, accel_v_mps2=2.0)
    link = open_link(tcp_url(mock))
    future = link.arm_and_takeoff(timeout_s=40.0)
    wait_for(lambda: mock.state().alt_m > 1.5, 20.0, message="climbing")
    mock.with_vehicle(lambda vehicle: vehicle.rc_mode_switch("LOITER"))
    future.result(timeout=40.0)
    state = link.state()
    assert state.takeoff_attempts == 2
    assert "left GUIDED" in (state.takeoff_last_refusal or "")
    assert mock.stats["arms"] == 1  # the second attempt took the flying vehicle over
    target = (30.0, 30.0, 12.0)
    link.set_target(target)
    wait_for(lambda: mock.state().mode == "GUIDED", 10.0, message="GUIDED asked for again")
    wait_for(
        lambda: math.dist(link.state().position_m or (0, 0, 0), target) < 1.0,
        40.0,
        message="flown to the target",
    )


@pytest.mark.slow
@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_a_failsafe_during_the_climb_ends_the_take_off_without_arming_again(
    start_mock, open_link, flavour
):
    """A real PX4 SITL landed by its own failsafe during the climb ("Failsafe activated",
    AUTO.LAND) was asked to arm again every 10 s: a take-off the autopilot's failsafe ended is
    its, not retried, and the vehicle is the autopilot's."""
    mock = start_mock(flavour, max_speed_up_mps=1.0, accel_v_mps2=2.0)
    link = open_link(tcp_url(mock))
    future = link.arm_and_takeoff(timeout_s=60.0)
    wait_for(lambda: mock.state().alt_m > 1.5, 20.0, message="climbing")
    mock.with_vehicle(lambda vehicle: vehicle.set_battery_remaining(5.0))  # under its failsafe
    with pytest.raises(RuntimeError, match="failsafe acted during the take-off"):
        future.result(timeout=30.0)
    state = link.state()
    assert state.control == "autopilot" and state.takeoff.startswith("failed")
    arms = mock.stats["arms"]
    assert arms == 1
    deadline = time.monotonic() + 3.0
    while time.monotonic() < deadline:  # watching that nothing is asked: no condition to await
        time.sleep(0.1)
    assert mock.stats["arms"] == arms and not link.state().streaming


@pytest.mark.slow
def test_refusals_are_retried_with_the_vehicles_words_until_it_arms(start_mock, open_link):
    mock = start_mock("ardupilot", **FAST_VEHICLE)
    refusal = "PreArm: Battery below minimum arming voltage"
    mock.with_vehicle(lambda vehicle: setattr(vehicle, "_arming_refusal", lambda: refusal))
    link = open_link(tcp_url(mock))
    future = link.arm_and_takeoff(timeout_s=60.0)
    state = wait_for(
        lambda: (s := link.state()).takeoff_attempts >= 2 and s.takeoff_last_refusal and s,
        30.0,
        message="a refused attempt and a second one",
    )
    assert state.takeoff == "running"
    assert "arming refused (FAILED)" in state.takeoff_last_refusal
    assert refusal in state.takeoff_last_refusal
    assert f"CRITICAL: {refusal}" in state.status_texts
    mock.with_vehicle(lambda vehicle: vars(vehicle).pop("_arming_refusal"))  # the battery is fine
    future.result(timeout=40.0)
    assert link.state().takeoff == "airborne"
    assert mock.stats["arms"] == 1


def test_the_sequence_gives_up_at_its_timeout_naming_the_last_refusal(start_mock, open_link):
    mock = start_mock("ardupilot")
    refusal = "PreArm: Compass not calibrated"
    mock.with_vehicle(lambda vehicle: setattr(vehicle, "_arming_refusal", lambda: refusal))
    link = open_link(tcp_url(mock))
    future = link.arm_and_takeoff(timeout_s=4.0)
    error = future.exception(timeout=10.0)
    assert isinstance(error, TimeoutError)
    assert "last refusal: arming refused" in str(error) and refusal in str(error)
    assert link.state().takeoff.startswith("failed: not airborne after 4 s")
    assert mock.stats.get("arms", 0) == 0


@pytest.mark.slow
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_vehicle_already_flying_is_taken_over_without_arming(start_mock, open_link, flavour):
    mock = start_mock(flavour, **FAST_VEHICLE)
    first = open_link(tcp_url(mock))
    first.arm_and_takeoff().result(timeout=30.0)
    first.set_target((10.0, 20.0, 10.0))
    wait_for(lambda: first.state().streaming, 5.0, message="streaming")
    first.close()  # the service restarts: a new link, the vehicle still in the air
    second = open_link(tcp_url(mock))
    second.arm_and_takeoff().result(timeout=30.0)
    assert mock.stats["arms"] == 1
    assert second.state().takeoff_attempts == 1


@pytest.mark.slow
def test_px4_takes_off_where_it_stands_not_at_latitude_zero(start_mock, open_link):
    mock = start_mock("px4", **FAST_VEHICLE)
    link = open_link(tcp_url(mock))
    started = time.monotonic()
    link.arm_and_takeoff(timeout_s=30.0).result(timeout=35.0)
    assert time.monotonic() - started < 20.0
    assert mock.stats.get("takeoffs_not_flown", 0) == 0
    ned = mock.state().position_ned_m
    assert math.hypot(ned.n, ned.e) < 1.0  # straight up, not off towards 0/0


def test_ekf_flags_as_arducopter_reads_them():
    healthy = 831  # what a healthy ArduCopter SITL reports
    assert ekf_position_ok(healthy)
    no_gps = (
        mavlink.EKF_ATTITUDE
        | mavlink.EKF_VELOCITY_VERT
        | mavlink.EKF_POS_VERT_ABS
        | mavlink.EKF_CONST_POS_MODE
    )
    assert not ekf_position_ok(no_gps)
    assert not ekf_position_ok(no_gps | mavlink.EKF_PRED_POS_HORIZ_ABS)  # still const-pos
    assert ekf_position_ok(mavlink.EKF_PRED_POS_HORIZ_ABS)  # disarmed: the prediction suffices
