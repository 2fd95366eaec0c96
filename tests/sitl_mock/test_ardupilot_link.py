"""The ArduPilot flavour over TCP, driven with raw pymavlink as a client drives ArduCopter SITL."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tests.sitl_mock.helpers import MavClient

GUIDED = 4
POSITION_ONLY = 3576


def test_heartbeat_identifies_an_ardupilot_quadrotor_in_stabilize(start_mock, connect):
    mock = start_mock("ardupilot")
    client = connect(mock)
    heartbeat = client.wait("HEARTBEAT")
    assert heartbeat.get_header().srcSystem == 1
    assert heartbeat.get_header().srcComponent == 1
    assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert heartbeat.type == mavlink.MAV_TYPE_QUADROTOR
    assert heartbeat.custom_mode == 0  # STABILIZE
    assert heartbeat.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert heartbeat._msgbuf[0] == 0xFD  # MAVLink 2


def test_no_telemetry_until_asked_then_set_message_interval_and_data_streams(start_mock, connect):
    mock = start_mock("ardupilot")
    client = connect(mock)
    client.wait("HEARTBEAT")
    client.wait("HEARTBEAT")  # a second later: still nothing but heartbeats
    types = {m.get_type() for m in client.received}
    assert types <= {"HEARTBEAT", "STATUSTEXT", "HOME_POSITION"}, types

    ack = client.set_message_interval("GLOBAL_POSITION_INT", 10.0)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    stamps_ms = [client.wait("GLOBAL_POSITION_INT").time_boot_ms for _ in range(6)]
    assert 80 <= (stamps_ms[-1] - stamps_ms[0]) / 5 <= 140  # ~10 Hz

    client.mav.request_data_stream_send(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 5, 1)
    client.wait("ATTITUDE")
    ack = client.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 99999, 1e5)
    assert ack.result == mavlink.MAV_RESULT_DENIED  # no such message: DENIED, as ArduCopter
    assert any("99999" in text for text in client.statustexts)  # said before the ACK


def test_request_message_and_autopilot_version(start_mock, connect):
    mock = start_mock("ardupilot")
    client = connect(mock)
    ack = client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    version = client.wait("AUTOPILOT_VERSION")
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    client.pump_for(lambda: mock.state().ready, 5.0, "ready")
    ack = client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    home = client.wait("HOME_POSITION")
    assert home.latitude == round(mock.vehicle.home.lat_deg * 1e7)
    ack = client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 12345)
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED


def test_unsupported_command_gets_unsupported(start_mock, connect):
    mock = start_mock("ardupilot")
    client = connect(mock)
    ack = client.command(mavlink.MAV_CMD_DO_SET_SERVO, 9, 1500)
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    assert ack.target_system == 255 and ack.target_component == 190
    assert mock.stats["commands_unsupported"] == 1


def test_parameters_can_be_read(start_mock, connect):
    mock = start_mock("ardupilot", max_speed_h_mps=8.0)
    client = connect(mock)
    client.mav.param_request_read_send(1, 1, b"WPNAV_SPEED", -1)
    value = client.wait("PARAM_VALUE")
    assert value.param_id == "WPNAV_SPEED"
    assert value.param_value == pytest.approx(800.0)
    client.mav.param_request_list_send(1, 1)
    values = [client.wait("PARAM_VALUE")]
    while len(values) < values[0].param_count:
        values.append(client.wait("PARAM_VALUE"))
    assert {"RTL_ALT", "FENCE_RADIUS", "DISARM_DELAY"} <= {v.param_id for v in values}
    # The table is read-only: a PARAM_SET is answered with the value the vehicle keeps.
    client.mav.param_set_send(1, 1, b"WPNAV_SPEED", 2000.0, mavlink.MAV_PARAM_TYPE_REAL32)
    value = client.wait("PARAM_VALUE", lambda m: m.param_id == "WPNAV_SPEED")
    assert value.param_value == pytest.approx(800.0)


def fly_guided_takeoff(client: MavClient, mock, alt_m: float) -> None:
    """What a careful client does with ArduCopter: wait for the EKF, GUIDED, arm, takeoff."""
    for name in ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "POSITION_TARGET_LOCAL_NED"):
        assert client.set_message_interval(name, 10.0).result == mavlink.MAV_RESULT_ACCEPTED
    client.set_message_interval("EXTENDED_SYS_STATE", 5.0)
    # Arming is refused until the pre-arm checks pass, and in GUIDED until the EKF uses GPS.
    ack = client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert ack.result == mavlink.MAV_RESULT_FAILED
    assert any(text.startswith("PreArm:") for text in client.statustexts)
    client.wait("STATUSTEXT", lambda m: "using GPS" in m.text, timeout_s=10.0)
    ack = client.command(mavlink.MAV_CMD_DO_SET_MODE, 1, GUIDED)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    client.wait("HEARTBEAT", lambda m: m.custom_mode == GUIDED)
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    assert client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt_m).result == 0
    client.wait(
        "GLOBAL_POSITION_INT", lambda m: m.relative_alt > (alt_m - 0.5) * 1000, timeout_s=15.0
    )


@pytest.mark.slow
def test_guided_arm_takeoff_and_fly_to_a_local_ned_setpoint(start_mock, connect):
    mock = start_mock("ardupilot", ready_delay_s=1.0, accel_h_mps2=5.0, accel_v_mps2=4.0)
    client = connect(mock)
    client.wait("HEARTBEAT")
    fly_guided_takeoff(client, mock, alt_m=3.0)

    target = (15.0, -8.0, -6.0)
    client.every(
        0.2,
        lambda: client.mav.set_position_target_local_ned_send(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY, *target, 0, 0, 0, 0, 0, 0, 0, 0
        ),
    )
    position = client.wait(
        "LOCAL_POSITION_NED",
        lambda m: math.dist((m.x, m.y, m.z), target) < 1.0,
        timeout_s=20.0,
    )
    assert math.dist((position.x, position.y, position.z), target) < 1.0
    echo = client.wait("POSITION_TARGET_LOCAL_NED")
    assert (echo.x, echo.y, echo.z) == pytest.approx(target)
    assert echo.type_mask == POSITION_ONLY
    assert echo.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED
    heartbeat = client.wait("HEARTBEAT")
    assert heartbeat.custom_mode == GUIDED
    assert heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    state = client.wait("EXTENDED_SYS_STATE")
    assert state.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
    # Disarming in flight is refused; landing works and ends disarmed.
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0).result == 4
    client.clear_tasks()
    assert client.command(mavlink.MAV_CMD_NAV_LAND).result == 0
    assert client.wait("HEARTBEAT").custom_mode == 9  # LAND
    assert mock.stats["setpoints_accepted"] >= 5
    assert mock.stats["signing_rejected"] == 0


def test_setpoint_while_takeoff_is_on_the_ground_leaves_the_vehicle_down(start_mock, connect):
    mock = start_mock("ardupilot", auto_disarm_s=2.0)
    client = connect(mock)
    client.wait("STATUSTEXT", lambda m: "using GPS" in m.text)
    assert client.command(mavlink.MAV_CMD_DO_SET_MODE, 1, GUIDED).result == 0
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    assert client.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10).result == 0
    # Too early: the client streams setpoints right after the takeoff command.
    client.mav.set_position_target_local_ned_send(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY, 10, 0, -10, 0, 0, 0, 0, 0, 0, 0, 0
    )
    client.pump_for(lambda: not mock.state().armed, 6.0, "auto-disarm")
    assert mock.state().alt_m == 0.0
    assert mock.stats["takeoffs_cancelled"] == 1


def test_command_int_and_set_mode_message(start_mock, connect):
    mock = start_mock("ardupilot")
    client = connect(mock)
    client.wait("STATUSTEXT", lambda m: "using GPS" in m.text)
    client.mav.set_mode_send(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED)
    ack = client.wait("COMMAND_ACK", lambda m: m.command == mavlink.MAVLINK_MSG_ID_SET_MODE)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    client.mav.command_int_send(
        1, 1, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0,
        0, 0, 6.0,
    )  # fmt: skip
    ack = client.wait("COMMAND_ACK", lambda m: m.command == mavlink.MAV_CMD_NAV_TAKEOFF)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert mock.state().landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF
