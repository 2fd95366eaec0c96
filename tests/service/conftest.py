"""Fixtures and constants for the service's tests: started vehicle links on either backend,
closed at teardown, and the small area and frames the link tests fly in."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest

from service import links
from service.frames import FrameConfig
from service.vehicle_link import LinkConfig, VehicleLink
from sim.config import AreaConfig
from sitl_mock.server import MockAutopilot
from tests.tiers import needs

AREA = AreaConfig(size_x_m=60.0, size_y_m=60.0, zone_m=5.0, z_min_m=5.0, z_max_m=20.0)
FRAMES = FrameConfig(area_origin_north_m=-20.0, area_origin_east_m=-10.0)
"""Home (the vehicle's NED origin) is at area (10, 20, 0)."""
HOME_AREA_M = (10.0, 20.0, 0.0)
FAST_VEHICLE = {"accel_h_mps2": 5.0, "accel_v_mps2": 5.0, "max_speed_up_mps": 5.0}
"""sitl_mock options for a vehicle that takes off and flies quickly."""


def mock_in_area_m(mock: MockAutopilot) -> tuple[float, float, float]:
    """The mock's true position, converted to the area frame independently of service.frames."""
    ned = mock.state().position_ned_m
    return (ned.e - FRAMES.area_origin_east_m, ned.n - FRAMES.area_origin_north_m, -ned.d)


@pytest.fixture
@needs("flying")
def open_link() -> Iterator[Callable[..., Any]]:
    """Factory: ``open_link(url, backend="pymavlink", **LinkConfig fields)``: a started link in
    :data:`AREA` and :data:`FRAMES` (unless given), closed at teardown."""
    opened: list[VehicleLink] = []

    def _open(url: str, backend: str = "pymavlink", **options: Any) -> Any:
        options.setdefault("area", AREA)
        options.setdefault("frames", FRAMES)
        link = links.open_link(backend, LinkConfig(url, **options))
        opened.append(link)
        return link.start()

    yield _open
    for link in opened:
        link.close()
