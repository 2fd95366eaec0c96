"""What only the MAVSDK backend of the vehicle link (service.mavsdk_link) does: the connection
strings it takes, what it refuses (a signing key), and MAVSDK's own log lines. The contract both
backends keep, against the sitl_mock autopilot, is in ``test_link_contract.py``.

Every link a test starts is stopped at teardown (also on failure); every wait is on a condition
with a timeout, never a fixed sleep.
"""

from __future__ import annotations

import logging

import pytest

from service.mavsdk_link import MavsdkLink
from service.mavsdk_session import mavsdk_url
from service.vehicle_link import LinkConfig, signing_key_from_passphrase
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
