"""The MAVSDK backend of the vehicle link (service.mavsdk_link) against the sitl_mock autopilot.

Every mock and link a test starts is stopped at teardown (also on failure); every wait is on a
condition with a timeout, never a fixed sleep.
"""

from __future__ import annotations

import logging
import math
import socket
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from service.frames import FrameConfig, area_to_ned
from service.mavlink_link import LinkConfig, signing_key_from_passphrase
from service.mavsdk_link import MavsdkLink, mavsdk_url
from sim.config import AreaConfig
from sitl_mock.server import MockAutopilot
from tests.sitl_mock.helpers import wait_for

AREA = AreaConfig(size_x_m=60.0, size_y_m=60.0, zone_m=5.0, z_min_m=5.0, z_max_m=20.0)
FRAMES = FrameConfig(area_origin_north_m=-20.0, area_origin_east_m=-10.0)
"""Home (the vehicle's NED origin) is at area (10, 20, 0)."""
HOME_AREA_M = (10.0, 20.0, 0.0)
FAST_VEHICLE = {"accel_h_mps2": 5.0, "accel_v_mps2": 5.0, "max_speed_up_mps": 5.0}


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def open_mavsdk_link() -> Iterator[Callable[..., MavsdkLink]]:
    """Factory: ``open_mavsdk_link(url, **LinkConfig fields)``: a started link, closed at
    teardown."""
    links: list[MavsdkLink] = []

    def _open(url: str, **options: Any) -> MavsdkLink:
        options.setdefault("area", AREA)
        options.setdefault("frames", FRAMES)
        link = MavsdkLink(LinkConfig(url, **options))
        links.append(link)
        return link.start()

    yield _open
    for link in links:
        link.close()


def mock_in_area_m(mock: MockAutopilot) -> tuple[float, float, float]:
    """The mock's true position, converted to the area frame independently of service.frames."""
    ned = mock.state().position_ned_m
    return (ned.e - FRAMES.area_origin_east_m, ned.n - FRAMES.area_origin_north_m, -ned.d)


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


def test_targets_are_geofenced_and_non_finite_targets_refused():
    link = MavsdkLink(LinkConfig("tcp:127.0.0.1:1", area=AREA, frames=FRAMES))  # not started
    assert link.set_target((30.0, 30.0, 10.0)) == (30.0, 30.0, 10.0)
    assert link.set_target((-5.0, 99.0, 500.0)) == (0.0, 60.0, 20.0)
    assert link.counters["geofence_clamps"] == 1
    with pytest.raises(ValueError, match="finite"):
        link.set_target((math.nan, 1.0, 10.0))
    assert link.counters["targets_rejected"] == 1
    state = link.state()
    assert state.target_m == (0.0, 60.0, 20.0)
    assert state.link == "connecting" and not state.streaming
    link.clear_target()
    assert link.state().target_m is None


def test_unreachable_vehicle_keeps_connecting_without_blocking(open_mavsdk_link):
    port = free_udp_port()  # nothing listens on this TCP port either (almost surely)
    link = open_mavsdk_link(
        f"tcp:127.0.0.1:{port}",
        reconnect_min_s=0.05,
        reconnect_max_s=0.2,
        heartbeat_timeout_s=0.3,  # MAVSDK takes any URL: silence is how a failure shows
    )
    future = link.arm_and_takeoff(timeout_s=0.5)
    assert not future.done()  # the call returned before its own work could end: no blocking
    wait_for(lambda: link.counters["connect_failures"] >= 3, 5.0, message="connection attempts")
    assert link.state().link == "connecting"
    assert isinstance(future.exception(timeout=3.0), TimeoutError)
    assert link.state().takeoff.startswith("failed")


def test_mavsdk_log_lines_reach_the_mavsdk_logger_off_mavsdk_threads(open_mavsdk_link, caplog):
    caplog.set_level(logging.DEBUG, logger="mavsdk")
    open_mavsdk_link(f"tcp:127.0.0.1:{free_udp_port()}", reconnect_min_s=0.05)
    # Every MAVSDK instance logs (its version, then the connection attempts).
    record = wait_for(
        lambda: next((r for r in caplog.records if r.name == "mavsdk"), None),
        10.0,
        message="a MAVSDK log line",
    )
    assert record.threadName == "mavsdk-log"  # not the MAVSDK thread that produced it
    assert ".cpp:" in record.getMessage()  # MAVSDK's source location comes along


def test_link_comes_up_over_udp_as_with_px4_sitl(start_mock, open_mavsdk_link):
    port = free_udp_port()
    mock = start_mock("px4", listen=f"udpout:127.0.0.1:{port}")
    link = open_mavsdk_link(f"udpin:127.0.0.1:{port}")
    state = wait_for(
        lambda: (s := link.state()).link == "up" and s.position_m is not None and s,
        10.0,
        message="link up with a position",
    )
    assert state.flavour == "px4"
    assert state.mode == "AUTO.LOITER"
    assert not state.armed
    assert state.heartbeat_age_s is not None and state.heartbeat_age_s < 1.5
    assert math.dist(state.position_m, HOME_AREA_M) < 0.1
    wait_for(lambda: mock.stats["gcs_heartbeats"] >= 1, 3.0, message="our HEARTBEAT at the mock")
    assert mock.stats["handler_errors"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_mavsdk_link_arms_takes_off_and_flies_to_a_point(start_mock, open_mavsdk_link, flavour):
    mock = start_mock(flavour, **FAST_VEHICLE)
    link = open_mavsdk_link(f"tcp:127.0.0.1:{mock.port}")
    started = time.monotonic()
    link.arm_and_takeoff().result(timeout=30.0)
    takeoff_s = time.monotonic() - started
    assert mock.state().alt_m >= 0.9 * AREA.z_min_m - 0.5
    assert mock.state().armed
    assert mock.stats.get("takeoffs_cancelled", 0) == 0

    target = (25.0, 35.0, 8.0)  # 18.9 m from home, 3 m up from the takeoff altitude
    assert link.set_target(target) == target
    started = time.monotonic()
    wait_for(
        lambda: math.dist(mock_in_area_m(mock), target) < 1.5,
        30.0,
        0.05,
        message="the vehicle at target",
    )
    reach_s = time.monotonic() - started
    state = wait_for(
        lambda: math.dist((s := link.state()).position_m, target) < 1.5 and s,
        3.0,
        message="the link's telemetry at target",
    )
    assert state.mode == {"px4": "OFFBOARD", "ardupilot": "GUIDED"}[flavour]
    assert state.armed and state.streaming and state.flavour == flavour
    assert mock.state().target_ned_m == pytest.approx(area_to_ned(*target, FRAMES), abs=1e-4)

    # The rate the mock measures: MAVSDK re-sends at 20 Hz between the link's own 10 Hz calls.
    before, sent_before = mock.stats["setpoints_received"], link.counters["setpoints_sent"]
    t0 = time.monotonic()
    wait_for(
        lambda: mock.stats["setpoints_received"] >= before + 30, 3.0, 0.01, message="setpoints"
    )
    elapsed_s = time.monotonic() - t0
    mock_rate_hz = (mock.stats["setpoints_received"] - before) / elapsed_s
    link_rate_hz = (link.counters["setpoints_sent"] - sent_before) / elapsed_s
    print(
        f"\nmavsdk {flavour}: takeoff {takeoff_s:.1f} s, reach {reach_s:.1f} s, "
        f"setpoints at the mock {mock_rate_hz:.1f}/s, link calls {link_rate_hz:.1f}/s"
    )
    assert mock_rate_hz >= 15.0
    stats = mock.stats
    assert stats["setpoints_rejected_fence"] == 0
    assert stats["setpoints_rejected_invalid"] == 0
    assert stats["failsafe_offboard"] == 0
    assert stats["handler_errors"] == 0


@pytest.mark.slow
def test_link_loss_stops_streaming_and_a_restarted_vehicle_gets_it_again(
    start_mock, open_mavsdk_link
):
    mock = start_mock("px4")
    port = mock.port
    link = open_mavsdk_link(f"tcp:127.0.0.1:{port}", reconnect_min_s=0.1, reconnect_max_s=0.5)
    wait_for(lambda: link.state().link == "up", 10.0, message="link up")
    link.set_target((20.0, 20.0, 10.0))
    wait_for(lambda: mock.stats["setpoints_received"] >= 5, 3.0, message="setpoints at the mock")

    mock.stop()
    stopped = time.monotonic()
    wait_for(lambda: link.state().link == "link_lost", 15.0, message="link_lost")
    # Not at once: the 3 s heartbeat timeout runs from the last HEARTBEAT, which came up to 1 s
    # before the stop (the upper bound is the wait above: a loaded machine only delays it).
    assert time.monotonic() - stopped >= 1.5
    assert not link.state().streaming
    sent = link.counters["setpoints_sent"]
    failures = link.counters["connect_failures"]
    wait_for(lambda: link.counters["connect_failures"] >= failures + 1, 8.0, message="retries")
    assert link.counters["setpoints_sent"] == sent  # nothing streams into the void

    again = start_mock("px4", listen=f"tcp:127.0.0.1:{port}")
    wait_for(lambda: link.state().link == "up", 10.0, message="link up again")
    wait_for(lambda: again.stats["setpoints_received"] >= 5, 3.0, message="streaming resumed")
    assert link.counters["reconnects"] >= 1
    assert link.counters["setpoints_sent"] > sent
    state = wait_for(lambda: (s := link.state()).position_m is not None and s, 3.0)
    assert state.flavour == "px4"
