"""PX4's OFFBOARD failsafe when the service's setpoint stream stops, with either link backend.

The vehicle (the PX4 flavour of sitl_mock, offboard timeout 1 s as PX4's COM_OF_LOSS_T) flies to
a target in OFFBOARD; then the service stops streaming, by clearing its target or by closing the
link, and the vehicle must switch to its hold mode (AUTO.LOITER) about a timeout later, and hold
where it is. Every mock, link and observer is stopped at teardown; every wait is on a condition.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from service.frames import FrameConfig
from service.links import LINK_BACKENDS, open_link
from service.vehicle_link import LinkConfig, VehicleLink
from sim.config import AreaConfig
from sitl_mock.flavours import px4_custom_mode
from sitl_mock.server import MockAutopilot
from tests.helpers import wait_for
from tests.sitl_mock.helpers import MavClient

AREA = AreaConfig(size_x_m=60.0, size_y_m=60.0, zone_m=5.0, z_min_m=5.0, z_max_m=20.0)
FRAMES = FrameConfig(area_origin_north_m=-20.0, area_origin_east_m=-10.0)
FAST_VEHICLE = {"accel_h_mps2": 5.0, "accel_v_mps2": 5.0, "max_speed_up_mps": 5.0}
OFFBOARD_TIMEOUT_S = 1.0
AUTO_LOITER = px4_custom_mode(4, 3)
TARGET = (16.0, 26.0, 7.0)
"""Area frame: about 8.5 m from home (area (10, 20, 0)), 2 m above the takeoff altitude."""


@pytest.fixture
def open_any_link() -> Iterator[Callable[..., VehicleLink]]:
    """Factory: ``open_any_link(backend, url)``: a started link, closed at teardown."""
    links: list[VehicleLink] = []

    def _open(backend: str, url: str, **options: Any) -> VehicleLink:
        link = open_link(backend, LinkConfig(url, area=AREA, frames=FRAMES, **options))
        links.append(link)
        return link.start()

    yield _open
    for link in links:
        link.close()  # idempotent: a test may have closed it already


@pytest.fixture
def observer() -> Iterator[Callable[[MockAutopilot], MavClient]]:
    """Factory: a raw-pymavlink ground station watching the mock (it also keeps sending a GCS
    HEARTBEAT while it waits, so the mock's ground-station failsafe stays out of the way)."""
    clients: list[MavClient] = []

    def _connect(mock: MockAutopilot) -> MavClient:
        client = MavClient(("127.0.0.1", mock.port), kind="tcp")
        clients.append(client)
        return client

    yield _connect
    for client in clients:
        client.close()


def mock_in_area_m(mock: MockAutopilot) -> tuple[float, float, float]:
    ned = mock.state().position_ned_m
    return (ned.e - FRAMES.area_origin_east_m, ned.n - FRAMES.area_origin_north_m, -ned.d)


def fly_to_target_in_offboard(mock: MockAutopilot, link: VehicleLink) -> None:
    link.arm_and_takeoff().result(timeout=30.0)
    link.set_target(TARGET)
    wait_for(
        lambda: mock.state().mode == "OFFBOARD" and math.dist(mock_in_area_m(mock), TARGET) < 1.0,
        30.0,
        0.05,
        message="the vehicle at target in OFFBOARD",
    )
    assert mock.stats["failsafe_offboard"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("backend", LINK_BACKENDS)
def test_clearing_the_target_lets_px4_fail_safe_to_hold(start_mock, open_any_link, backend):
    mock = start_mock("px4", speedup=1.0, offboard_timeout_s=OFFBOARD_TIMEOUT_S, **FAST_VEHICLE)
    link = open_any_link(backend, f"tcp:127.0.0.1:{mock.port}")
    fly_to_target_in_offboard(mock, link)

    link.clear_target()
    cleared = time.monotonic()
    assert not link.state().streaming
    wait_for(lambda: mock.state().mode == "AUTO.LOITER", 5.0, 0.01, message="AUTO.LOITER")
    elapsed_s = time.monotonic() - cleared
    print(f"\n{backend}: hold {elapsed_s:.2f} s after clear_target")
    # The last setpoint left at most one setpoint period (0.1 s) before clear_target; the mock
    # waits the timeout after the last one it got. Generous above: the machine may be loaded.
    assert OFFBOARD_TIMEOUT_S - 0.2 <= elapsed_s <= OFFBOARD_TIMEOUT_S + 2.0
    assert mock.stats["failsafe_offboard"] == 1

    # The link sees the hold in its own telemetry, and sends nothing more.
    received = mock.stats["setpoints_received"]
    state = wait_for(
        lambda: (s := link.state()).mode == "AUTO.LOITER" and s, 3.0, message="hold at the link"
    )
    assert state.link == "up" and state.armed and not state.streaming and state.target_m is None
    assert mock.stats["setpoints_received"] == received
    # Holding where it was, not falling or flying off.
    assert math.dist(mock_in_area_m(mock), TARGET) < 1.0
    assert mock.state().armed and not mock.state().landed


@pytest.mark.slow
@pytest.mark.parametrize("backend", LINK_BACKENDS)
def test_closing_the_link_lets_px4_fail_safe_to_hold(start_mock, open_any_link, observer, backend):
    mock = start_mock("px4", speedup=1.0, offboard_timeout_s=OFFBOARD_TIMEOUT_S, **FAST_VEHICLE)
    watcher = observer(mock)
    link = open_any_link(backend, f"tcp:127.0.0.1:{mock.port}")
    fly_to_target_in_offboard(mock, link)

    watcher.mark()
    link.close()
    closed = time.monotonic()
    text = watcher.wait("STATUSTEXT", lambda m: "offboard" in m.text.lower(), timeout_s=5.0)
    elapsed_s = time.monotonic() - closed
    print(f"\n{backend}: failsafe STATUSTEXT {elapsed_s:.2f} s after close")
    assert text.severity == 2  # MAV_SEVERITY_CRITICAL
    assert OFFBOARD_TIMEOUT_S - 0.2 <= elapsed_s <= OFFBOARD_TIMEOUT_S + 2.0
    watcher.wait("HEARTBEAT", lambda m: m.custom_mode == AUTO_LOITER, timeout_s=3.0)
    stats = mock.stats
    assert stats["failsafe_offboard"] == 1
    assert stats["failsafe_gcs"] == 0
    assert math.dist(mock_in_area_m(mock), TARGET) < 1.0
    assert mock.state().armed and not mock.state().landed
