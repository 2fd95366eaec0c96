"""Fixtures for the service's tests: started vehicle links, closed at teardown."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest

from service.frames import FrameConfig
from service.mavlink_link import LinkConfig, MavlinkLink
from sim.config import AreaConfig

AREA = AreaConfig(size_x_m=60.0, size_y_m=60.0, zone_m=5.0, z_min_m=5.0, z_max_m=20.0)
FRAMES = FrameConfig(area_origin_north_m=-20.0, area_origin_east_m=-10.0)
"""Home (the vehicle's NED origin) is at area (10, 20, 0)."""


@pytest.fixture
def open_link() -> Iterator[Callable[..., MavlinkLink]]:
    """Factory: ``open_link(url, **LinkConfig fields)``: a started link, closed at teardown."""
    links: list[MavlinkLink] = []

    def _open(url: str, **options: Any) -> MavlinkLink:
        options.setdefault("area", AREA)
        options.setdefault("frames", FRAMES)
        link = MavlinkLink(LinkConfig(url, **options))
        links.append(link)
        return link.start()

    yield _open
    for link in links:
        link.close()
