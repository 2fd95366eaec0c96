"""What only the MAVSDK backend of the vehicle link (service.mavsdk_link) does: the connection
strings it takes, what it refuses (a signing key), MAVSDK's own log lines, and which system it
drives when MAVSDK discovers others. The contract both backends keep, against the sitl_mock
autopilot, is in ``test_link_contract.py``.

Every link a test starts is stopped at teardown (also on failure); every wait is on a condition
with a timeout, never a fixed sleep.
"""

from __future__ import annotations

import logging

import pytest

from service.mavsdk_link import MavsdkLink
from service.mavsdk_session import mavsdk_url, packets
from service.vehicle_link import LinkConfig, signing_key_from_passphrase
from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot
from tests.helpers import free_udp_port, wait_for


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("tcp:127.0.0.1:5760", "tcpout://127.0.0.1:5760"),
        ("tcpin:0.0.0.0:5760", "tcpin://0.0.0.0:5760"),
        ("udpin:0.0.0.0:14540", "udpin://0.0.0.0:14540"),
        ("udp:127.0.0.1:14550", "udpin://127.0.0.1:14550"),
        ("udpout:10.0.0.2:14555", "udpout://10.0.0.2:14555"),
        ("/dev/ttyUSB0", "serial:///dev/ttyUSB0:57600"),
        ("/dev/ttyACM0,921600", "serial:///dev/ttyACM0:921600"),
        ("udpin://0.0.0.0:14540", "udpin://0.0.0.0:14540"),
    ],
)
def test_pymavlink_connection_strings_become_mavsdk_urls(url, expected):
    assert mavsdk_url(url) == expected


@pytest.mark.parametrize("url", ["", "tcp:5760", "bogus:1.2.3.4:5", "udpin:host:port"])
def test_unusable_connection_strings_are_refused(url):
    with pytest.raises(ValueError, match="url"):
        MavsdkLink(LinkConfig(url))


def test_a_signing_key_is_refused_with_a_reason():
    config = LinkConfig("tcp:127.0.0.1:1", signing_key=signing_key_from_passphrase("tupa"))
    with pytest.raises(ValueError, match=r"signing_key.*mavsdk.*pymavlink"):
        MavsdkLink(config)


def test_mavsdk_log_lines_reach_the_mavsdk_logger_off_mavsdk_threads(open_link, caplog):
    caplog.set_level(logging.DEBUG, logger="mavsdk")
    open_link(f"tcp:127.0.0.1:{free_udp_port()}", "mavsdk", reconnect_min_s=0.05)
    # Every MAVSDK instance logs (its version, then the connection attempts).
    record = wait_for(
        lambda: next((r for r in caplog.records if r.name == "mavsdk"), None),
        10.0,
        message="a MAVSDK log line",
    )
    assert record.threadName == "mavsdk-log"  # not the MAVSDK thread that produced it
    assert ".cpp:" in record.getMessage()  # MAVSDK's source location comes along


def test_a_session_made_anew_drives_only_the_system_it_locked(start_mock, open_link):
    """The vehicle (system 1) falls silent and system 42 answers on its port: the sessions made
    anew after the loss find 42 but never drive it; system 1 back on the port is driven again."""
    first = start_mock("px4")
    port = first.port
    link = open_link(
        f"tcp:127.0.0.1:{port}",
        "mavsdk",
        heartbeat_timeout_s=1.0,
        reconnect_min_s=0.1,
        reconnect_max_s=0.3,
    )
    wait_for(lambda: (s := link.state()).link == "up" and s.position_m is not None, 15.0)
    link.set_target((30.0, 30.0, 10.0))
    wait_for(lambda: first.stats["setpoints_received"] >= 5, 10.0, message="setpoints")
    first.stop()
    other = MockAutopilot(
        f"tcp:127.0.0.1:{port}", "px4", VehicleConfig(ready_delay_s=0.3), system_id=42
    ).start()
    try:
        wait_for(lambda: other.stats["gcs_heartbeats"] >= 3, 15.0, message="MAVSDK at 42")
        reconnects = link.counters["reconnects"]
        driven: set[int | None] = set()

        def sessions_made_anew() -> bool:
            session = link._session
            driven.add(None if session is None else session.system_id)
            return link.counters["reconnects"] >= reconnects + 2

        wait_for(sessions_made_anew, 15.0, interval_s=0.01, message="sessions made anew")
        assert 42 not in driven  # no plugins (telemetry, offboard, action) for system 42
        state = link.state()
        assert state.link == "link_lost" and state.system_id == 1 and not state.streaming
        assert other.stats["setpoints_received"] == 0 and other.stats["not_for_us"] == 0
        assert other.state().mode == "AUTO.LOITER" and not other.state().armed
    finally:
        other.stop()
    back = start_mock("px4", listen=f"tcp:127.0.0.1:{port}")
    wait_for(lambda: back.stats["setpoints_received"] >= 5, 20.0, message="setpoints again")
    assert link.state().system_id == 1


def test_packets_are_found_in_a_datagram_by_their_headers():
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    def packet(system_id, component_id, mavlink1=False):
        encoder = dialect.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        message = encoder.heartbeat_encode(6, 8, 0, 0, 4)
        return message.pack(encoder, force_mavlink1=mavlink1)

    signer = dialect.MAVLink(None, srcSystem=3, srcComponent=1)
    signer.signing.secret_key = signing_key_from_passphrase("tupa")
    signer.signing.sign_outgoing = True
    signed = signer.ping_encode(0, 0, 0, 0).pack(signer)
    parts = [packet(1, 1), packet(42, 1, mavlink1=True), signed, packet(1, 7)]
    datagram = b"".join(parts) + b"\xfd\x09"  # and the start of a truncated packet
    found = packets(datagram)
    assert [(system, component, message) for _, _, system, component, message in found] == [
        (1, 1, 0),
        (42, 1, 0),
        (3, 1, dialect.MAVLINK_MSG_ID_PING),
        (1, 7, 0),
    ]
    assert [datagram[a:b] for a, b, *_ in found] == parts
    assert packets(b"garbage" + parts[0]) == []  # a walk stops at a byte that starts no packet
