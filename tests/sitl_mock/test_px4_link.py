"""The PX4 flavour over the wire: default streams, OFFBOARD rules and failsafe (raw pymavlink),
and a whole flight driven by the native MAVSDK binding (mavsdk >= 4, no mavsdk_server process)."""

from __future__ import annotations

import asyncio
import math
import struct
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl_mock.flavours import px4_custom_mode
from tests.sitl_mock.helpers import MavClient

OFFBOARD = px4_custom_mode(6)
AUTO_LOITER = px4_custom_mode(4, 3)
POSITION_ONLY = 3576


def send_target(client: MavClient, target: tuple[float, float, float]) -> None:
    client.mav.set_position_target_local_ned_send(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY, *target, 0, 0, 0, 0, 0, 0, 0, 0
    )


def test_px4_streams_telemetry_by_default_and_reports_its_modes(start_mock, connect):
    mock = start_mock("px4")
    client = connect(mock)
    heartbeat = client.wait("HEARTBEAT")
    assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert heartbeat.custom_mode == AUTO_LOITER == 4 << 16 | 3 << 24
    client.wait("GLOBAL_POSITION_INT")
    client.wait("LOCAL_POSITION_NED")
    client.wait("ATTITUDE")
    client.wait("EXTENDED_SYS_STATE")
    status = client.wait("SYS_STATUS")
    assert status.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK
    battery = client.wait("BATTERY_STATUS")
    assert 0 < battery.battery_remaining <= 100
    # PX4 sends integer parameters bit-for-bit in the float field.
    client.mav.param_request_read_send(1, 1, b"MAV_SYS_ID", -1)
    value = client.wait("PARAM_VALUE", lambda m: m.param_id == "MAV_SYS_ID")
    assert value.param_type == mavlink.MAV_PARAM_TYPE_INT32
    assert struct.unpack("<i", struct.pack("<f", value.param_value))[0] == 1
    # PX4 ignores the old REQUEST_DATA_STREAM.
    client.mav.request_data_stream_send(1, 1, mavlink.MAV_DATA_STREAM_ALL, 0, 0)
    client.wait("ATTITUDE")


@pytest.mark.slow
def test_px4_offboard_switch_needs_a_running_stream_and_fails_safe_when_it_stops(
    start_mock, connect
):
    mock = start_mock(
        "px4",
        speedup=1.0,
        offboard_stream_min_s=0.5,
        offboard_timeout_s=0.5,
        accel_v_mps2=5.0,
    )
    client = connect(mock)
    client.wait("STATUSTEXT", lambda m: m.text == "Ready for takeoff!")
    # Switching before any setpoint streams is refused, with a reason.
    ack = client.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0)
    assert ack.result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert any("Offboard" in text for text in client.statustexts)

    target = (6.0, -3.0, -4.0)
    last_sent = [0.0]

    def stream() -> None:
        send_target(client, target)
        last_sent[0] = time.monotonic()

    client.every(0.1, stream)
    deadline = time.monotonic() + 5.0
    while client.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0).result != 0:
        assert time.monotonic() < deadline, "OFFBOARD never accepted"
        sent = mock.stats.get("setpoints_buffered", 0)
        client.pump_for(lambda s=sent: mock.stats["setpoints_buffered"] >= s + 3, 2.0, "stream")
    assert client.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    client.wait(
        "LOCAL_POSITION_NED",
        lambda m: math.dist((m.x, m.y, m.z), target) < 0.5,
        timeout_s=15.0,
    )
    assert client.wait("HEARTBEAT").custom_mode == OFFBOARD

    client.clear_tasks()  # the setpoint stream stops
    text = client.wait("STATUSTEXT", lambda m: "offboard" in m.text.lower(), timeout_s=3.0)
    # The failsafe waits the 0.5 s timeout after the last setpoint the mock received, which
    # was sent no earlier than the last send recorded here; the mock steps its clock at 50 Hz
    # and a loaded machine delays both sides, hence the margin (the behaviour: not at once).
    assert time.monotonic() - last_sent[0] >= 0.35
    assert text.severity == mavlink.MAV_SEVERITY_CRITICAL
    assert client.wait("HEARTBEAT").custom_mode == AUTO_LOITER
    assert mock.stats["failsafe_offboard"] == 1
    assert math.dist(mock.state().position_ned_m, target) < 1.0  # holding, not falling


# ---------------------------------------------------------------- MAVSDK


async def _first(stream, predicate, timeout_s: float):
    async def _scan():
        async for item in stream:
            if predicate(item):
                return item
        raise AssertionError("stream ended")

    return await asyncio.wait_for(_scan(), timeout_s)


async def _fly_with_mavsdk(url: str) -> None:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard import OffboardAsync, OffboardError, PositionNedYaw
    from mavsdk.asyncio.plugins.telemetry import FlightMode, TelemetryAsync

    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as sdk:
        await sdk.add_any_connection(url)
        drone = await sdk.first_autopilot(timeout_s=10.0)
        assert drone is not None, "MAVSDK found no autopilot"
        telemetry = TelemetryAsync(drone)
        action = ActionAsync(drone)
        offboard = OffboardAsync(drone)

        await _first(
            telemetry.subscribe_health(),
            lambda h: h.is_global_position_ok and h.is_home_position_ok and h.is_armable,
            timeout_s=10.0,
        )
        await action.arm()
        await action.takeoff()  # PX4: AUTO.TAKEOFF to its default altitude
        await _first(telemetry.subscribe_in_air(), bool, timeout_s=10.0)
        # PX4 goes AUTO.TAKEOFF -> AUTO.LOITER ("Hold") at the takeoff altitude.
        await _first(
            telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.HOLD, timeout_s=15.0
        )
        position = await telemetry.position()
        assert position.relative_altitude_m == pytest.approx(2.5, abs=0.3)

        target = PositionNedYaw(6.0, 3.0, -3.5, 0.0)
        await offboard.set_position_ned(target)  # MAVSDK now streams it at 20 Hz
        for _ in range(50):  # PX4 wants the stream running before the switch
            try:
                await offboard.start()
                break
            except OffboardError:
                await asyncio.sleep(0.1)
        else:
            raise AssertionError("offboard never started")
        await _first(
            telemetry.subscribe_flight_mode(), lambda m: m == FlightMode.OFFBOARD, timeout_s=3.0
        )
        reached = await _first(
            telemetry.subscribe_position_velocity_ned(),
            lambda pv: (
                math.dist(
                    (pv.position.north_m, pv.position.east_m, pv.position.down_m), (6.0, 3.0, -3.5)
                )
                < 0.5
            ),
            timeout_s=15.0,
        )
        assert reached.position.down_m == pytest.approx(-3.5, abs=0.5)

        await action.land()
        await _first(telemetry.subscribe_in_air(), lambda in_air: not in_air, timeout_s=20.0)


@pytest.mark.slow
def test_mavsdk_native_binding_flies_the_px4_flavour(start_mock, request):
    pytest.importorskip("mavsdk.asyncio", reason="the native MAVSDK binding (mavsdk>=4) is needed")
    from mavsdk.logging import log_subscribe, log_unsubscribe

    # MAVSDK's log callback is process-wide: this test's filter must not outlive it.
    log_subscribe(lambda level, message, file, line: level < 2)  # keep warnings and errors
    request.addfinalizer(log_unsubscribe)
    mock = start_mock(
        "px4",
        ready_delay_s=0.5,
        offboard_stream_min_s=0.5,
        accel_h_mps2=5.0,
        accel_v_mps2=5.0,
        land_speed_mps=2.0,
        takeoff_alt_m=2.5,
    )
    asyncio.run(asyncio.wait_for(_fly_with_mavsdk(f"tcpout://127.0.0.1:{mock.port}"), 60.0))
    stats = mock.stats
    assert stats["setpoints_accepted"] > 10
    assert stats["failsafe_offboard"] == 0
    assert stats["handler_errors"] == 0
    state = mock.state()
    assert state.landed and state.mode == "AUTO.LAND"
    assert math.hypot(state.position_ned_m.n - 6.0, state.position_ned_m.e - 3.0) < 1.0
