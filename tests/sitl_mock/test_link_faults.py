"""What real links do to the mock: garbage bytes, spoofed or unsigned packets, several ground
stations at once, UDP peers. It must count and ignore what it cannot use, and never stop."""

from __future__ import annotations

import math
import socket
import struct

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tests.helpers import wait_for
from tests.sitl_mock.helpers import MavClient

KEY = bytes(range(32))
WRONG_KEY = bytes([7] * 32)
GUIDED = 4
POSITION_ONLY = 3576


def wait_heartbeats(client: MavClient, count: int) -> None:
    """Let ``count`` of the mock's heartbeats go by (the mock's own 1 Hz clock)."""
    for _ in range(count):
        client.wait("HEARTBEAT", lambda m: m.get_header().srcSystem == 1)


def no_ack_since_mark(client: MavClient) -> bool:
    return not any(m.get_type() == "COMMAND_ACK" for m in client.received[client._cursor :])


def send_local_target(client: MavClient, target: tuple[float, float, float]) -> None:
    client.mav.set_position_target_local_ned_send(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY, *target, 0, 0, 0, 0, 0, 0, 0, 0
    )


def v2_frame(message_id: int, payload: bytes, crc: int = 0x1234, incompat: int = 0) -> bytes:
    header = struct.pack(
        "<BBBBBBBHB", 0xFD, len(payload), incompat, 0, 0, 255, 190, message_id & 0xFFFF,
        message_id >> 16,
    )  # fmt: skip
    return header + payload + struct.pack("<H", crc)


def test_malformed_and_unknown_input_is_counted_and_never_stops_the_mock(start_mock, connect):
    mock = start_mock("ardupilot")
    client = connect(mock)
    client.wait("HEARTBEAT")
    valid = mavlink.MAVLink(None, 255, 190).command_long_encode(
        1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
    )
    packed = bytearray(valid.pack(mavlink.MAVLink(None, 255, 190)))
    bad_crc = bytes(packed[:-1] + bytes([packed[-1] ^ 0xFF]))
    client.send_raw(v2_frame(60000, b"\x01\x02\x03"))  # a message id nobody knows
    client.send_raw(bad_crc)
    client.send_raw(v2_frame(mavlink.MAVLINK_MSG_ID_HEARTBEAT, b"\x00" * 9, incompat=0x80))
    client.send_raw(b"\x00\x01 not mavlink at all \xff\xfe" * 40)
    client.send_raw(bytes(range(256)) * 4)
    # Line noise can start a bogus frame that swallows what follows until its CRC fails, as
    # on a real parser; quiet bytes after the noise let it resynchronise.
    client.send_raw(bytes(300))
    # A well-formed setpoint full of NaN, in GUIDED, is counted and ignored.
    client.mav.set_position_target_local_ned_send(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY, *[math.nan] * 3, 0, 0, 0, 0, 0, 0, 0, 0
    )
    # The mock keeps answering: a valid command after all that gets its ACK.
    wait_for(lambda: mock.state().ready, message="ready")
    ack = client.command(mavlink.MAV_CMD_DO_SET_MODE, 1, GUIDED, timeout_s=5.0)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    client.mav.set_position_target_local_ned_send(
        0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, POSITION_ONLY, math.nan, 0, -5, 0, 0, 0, 0, 0, 0, 0, 0
    )
    client.pump_for(lambda: mock.stats["setpoints_rejected_invalid"] >= 1, 3.0, "NaN rejection")
    stats = mock.stats
    assert stats["bad_data"] >= 3
    assert stats["unknown_messages"] == 1
    assert stats["handler_errors"] == 0
    assert stats.get("loop_errors", 0) == 0
    assert not mock.state().armed  # the corrupted arm command did nothing
    assert mock.state().position_ned_m == (0.0, 0.0, 0.0)


def test_abrupt_disconnects_do_not_disturb_other_clients(start_mock, connect):
    mock = start_mock("px4")
    steady = connect(mock)
    for _ in range(5):
        rude = socket.create_connection(("127.0.0.1", mock.port))
        rude.sendall(b"\xfd\x20\x00")  # half a header, then gone
        rude.close()
    wait_heartbeats(steady, 2)
    wait_for(lambda: mock.stats["links_open"] == 1, message="rude clients dropped")
    assert mock.stats["clients_total"] == 6


@pytest.mark.slow
def test_signing_ignores_unsigned_and_wrongly_signed_commands_and_setpoints(start_mock, connect):
    mock = start_mock("ardupilot", signing_key=KEY, ready_delay_s=0.2, accel_v_mps2=4.0)
    good = connect(mock, signing_key=KEY, system_id=255)
    wrong = connect(mock, signing_key=WRONG_KEY, system_id=250)
    unsigned = connect(mock, system_id=251)
    heartbeat = good.wait("HEARTBEAT")
    assert heartbeat.get_header().incompat_flags & mavlink.MAVLINK_IFLAG_SIGNED
    good.wait("STATUSTEXT", lambda m: "using GPS" in m.text)

    commands_before = mock.stats["commands"]
    unsigned.mark()
    for client in (wrong, unsigned):
        client.heartbeat()
        client.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, GUIDED, 0, 0, 0, 0, 0)
        client.mav.command_long_send(
            1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0
        )
    # The wrong-key client cannot even read the vehicle (its packets are signed with KEY):
    # time passes on the unsigned client, which reads without checking.
    wait_heartbeats(unsigned, 2)
    assert no_ack_since_mark(unsigned)
    assert mock.stats["commands"] == commands_before
    assert mock.state().mode == "STABILIZE" and not mock.state().armed
    assert mock.stats["signing_rejected"] >= 4
    assert mock.stats["gcs_heartbeats"] >= 4  # unsigned HEARTBEATs are still let through

    # The right key flies it.
    assert good.command(mavlink.MAV_CMD_DO_SET_MODE, 1, GUIDED).result == 0
    assert good.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    assert good.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.5).result == 0
    wait_for(lambda: mock.state().landed_state == 2, timeout_s=10.0, message="airborne")
    hover = mock.state().position_ned_m

    # A wrong key moves nothing: a stream of far setpoints is ignored and counted.
    rejected_before = mock.stats["signing_rejected"]
    for client in (wrong, unsigned):
        client.every(0.1, lambda c=client: send_local_target(c, (50.0, 50.0, -20.0)))
    wrong.pump_for(lambda: mock.stats["signing_rejected"] >= rejected_before + 10, 5.0, "spoofs")
    unsigned.pump_for(lambda: mock.stats["signing_rejected"] >= rejected_before + 20, 5.0, "more")
    assert math.dist(mock.state().position_ned_m, hover) < 0.3
    assert mock.stats["setpoints_received"] == 0
    # ... while the same setpoint with the right key is obeyed.
    send_local_target(good, (5.0, 0.0, -2.5))
    good.pump_for(lambda: mock.stats["setpoints_accepted"] == 1, 3.0, "signed setpoint")


def test_several_clients_each_with_their_own_streams(start_mock, connect, monkeypatch):
    from pymavlink import mavutil

    # mavutil switches itself (process-wide) to MAVLink 2 when it hears one: undo that after.
    monkeypatch.delenv("MAVLINK20", raising=False)
    monkeypatch.setattr(mavutil, "mavlink", mavutil.mavlink)
    monkeypatch.setattr(mavutil, "current_dialect", mavutil.current_dialect)
    mock = start_mock("ardupilot", ready_delay_s=5.0)
    service = connect(mock, system_id=1, component_id=191)  # a companion on the vehicle
    gcs_a = connect(mock, system_id=255)
    gcs_b = mavutil.mavlink_connection(f"tcp:127.0.0.1:{mock.port}", source_system=254)
    try:
        assert gcs_b.wait_heartbeat(timeout=5).autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        wait_for(lambda: mock.stats["links_open"] == 3, message="three clients")

        assert service.set_message_interval("ATTITUDE", 20.0).result == 0
        service.wait("ATTITUDE")
        # The others did not ask: ArduPilot streams per link.
        ack = gcs_a.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == mavlink.MAV_RESULT_FAILED  # not ready yet
        # Every ground station sees why, only the sender gets the ACK.
        refusal = "PreArm: AHRS: waiting for home"
        service.wait("STATUSTEXT", lambda m: m.text == refusal)
        text = gcs_b.recv_match(type="STATUSTEXT", blocking=True, timeout=5)
        assert text is not None and text.text == refusal
        wait_heartbeats(gcs_a, 1)
        assert not any(m.get_type() == "ATTITUDE" for m in gcs_a.received)
        assert not any(m.get_type() == "COMMAND_ACK" and m.command == 400 for m in service.received)
        gcs_a.close()
        wait_for(lambda: mock.stats["links_open"] == 2, message="one client gone")
        service.wait("ATTITUDE")
    finally:
        gcs_b.close()


def test_udp_bind_answers_each_sender(start_mock, connect):
    mock = start_mock("px4", listen="udp:127.0.0.1:0")
    client = connect(mock)
    client.heartbeat()  # a UDP autopilot only knows a client once it hears from it
    heartbeat = client.wait("HEARTBEAT")
    assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_PX4
    client.wait("SYS_STATUS")  # PX4 streams by default
    ack = client.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    other = connect(mock)
    other.heartbeat()
    other.wait("HEARTBEAT")
    wait_for(lambda: mock.stats["links_open"] == 2, message="two UDP peers")


def test_udpout_sends_to_a_listening_client_like_px4_sitl(start_mock):
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    mock = start_mock("px4", listen=f"udpout:127.0.0.1:{port}")
    client = MavClient(("127.0.0.1", mock.port), kind="udp", sock=listener)
    try:
        assert client.wait("HEARTBEAT").autopilot == mavlink.MAV_AUTOPILOT_PX4
        ack = client.command(mavlink.MAV_CMD_DO_SET_SERVO, 1, 1500)
        assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED
    finally:
        client.close()
