"""``benchmarks/real_px4_sitl.py``'s tap on the service's link, on synthetic datagrams (no SITL,
no packet socket): what it counts as the service's setpoints and commands, and PX4's answers."""

from __future__ import annotations

import importlib.util
import os
import struct
import sys
import threading
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def px4():
    spec = importlib.util.spec_from_file_location(
        "real_px4_sitl", ROOT / "benchmarks" / "real_px4_sitl.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[spec.name]


def _packet(src_port: int, dst_port: int, payload: bytes) -> bytes:
    """An Ethernet-framed IPv4/UDP packet as a packet socket on ``lo`` delivers it."""
    udp = struct.pack("!HHHH", src_port, dst_port, 8 + len(payload), 0) + payload
    ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, 0, 64, 17, 0, bytes(4), bytes(4))
    return bytes(14) + ip + udp


def _tap(px4):
    """A Tap without its socket and thread (only the parsing)."""
    tap = object.__new__(px4.Tap)
    tap.t0 = 0.0
    tap.port = px4.SERVICE_PORT
    tap.lock = threading.Lock()
    tap.from_service = mavlink.MAVLink(None)
    tap.from_service.robust_parsing = True
    tap.from_vehicle = mavlink.MAVLink(None)
    tap.from_vehicle.robust_parsing = True
    tap.datagrams = {"from_service": 0, "to_service": 0}
    tap.sent_types, tap.sent, tap.setpoint_times = {}, [], []
    tap.commands, tap.info_commands, tap.acks = [], {}, []
    tap.params_set, tap.fence_items, tap.mission, tap.homes = [], {}, [], []
    tap.parse_errors = tap.packets = 0
    return tap


def _pack(system: int, component: int, *messages) -> bytes:
    mav = mavlink.MAVLink(None, system, component)
    return b"".join(m.pack(mav) for m in messages)


def test_the_tap_times_what_the_service_sends_and_what_px4_answers(px4) -> None:
    tap = _tap(px4)
    setpoint = mavlink.MAVLink_set_position_target_local_ned_message(
        0, 1, 1, 1, 3576, 1.0, 2.0, -25.0, 0, 0, 0, 0, 0, 0, 0, 0
    )
    rtl = mavlink.MAVLink_command_long_message(1, 1, 20, 0, 0, 0, 0, 0, 0, 0, 0)
    interval = mavlink.MAVLink_command_long_message(1, 1, 511, 0, 33, 1e5, 0, 0, 0, 0, 0)
    tap._packet(1.0, _packet(14540, 14580, _pack(255, 191, setpoint, setpoint)))
    tap._packet(2.0, _packet(14540, 14580, _pack(255, 191, interval, rtl)))
    ack = mavlink.MAVLink_command_ack_message(20, 0, 0, 0, 255, 191)
    position = mavlink.MAVLink_local_position_ned_message(0, 1, 2, 3, 0, 0, 0)
    tap._packet(2.1, _packet(14580, 14540, _pack(1, 1, position, ack)))
    # Another system's ACK on the same datagram stream is not PX4's.
    tap._packet(2.2, _packet(14580, 14540, _pack(7, 1, ack)))
    assert tap.setpoint_times == [1.0, 1.0]
    assert [c["command"] for c in tap.commands] == ["MAV_CMD_NAV_RETURN_TO_LAUNCH"]
    assert tap.info_commands == {"MAV_CMD_SET_MESSAGE_INTERVAL": 1}
    assert [(a["command"], a["result"]) for a in tap.acks] == [("MAV_CMD_NAV_RETURN_TO_LAUNCH", 0)]
    assert tap.setpoints_after(1.0) == 0
    assert tap.commands_after(1.5) == tap.commands
    assert tap.commands_after(1.5, but="MAV_CMD_NAV_RETURN_TO_LAUNCH") == []
    assert tap.types_after(1.5) == {"COMMAND_LONG": 2}


def test_frames_splits_a_datagram_of_several_messages(px4) -> None:
    ack = mavlink.MAVLink_command_ack_message(20, 0, 0, 0, 255, 191)
    heartbeat = mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3)
    data = _pack(1, 1, heartbeat, ack, heartbeat)
    ids = [msgid for msgid, *_ in px4._frames(data)]
    assert ids == [0, 77, 0]
    assert b"".join(frame for *_, frame in px4._frames(data)) == data


def test_the_packet_filter_jumps_stay_inside_the_program(px4) -> None:
    program = px4._bpf_udp_port(14540)
    code = [struct.unpack("HBBI", program[i : i + 8]) for i in range(0, len(program), 8)]
    for i, (op, jt, jf, _k) in enumerate(code):
        if op & 0x07 == 0x05:  # BPF_JMP
            assert i + 1 + jt < len(code) and i + 1 + jf < len(code)
    assert code[-2][0] == code[-1][0] == 0x06  # ends with accept, drop
    assert code[-1][3] == 0
