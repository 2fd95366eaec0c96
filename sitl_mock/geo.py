"""Local NED <-> global (WGS-84 latitude/longitude/altitude) around the vehicle's home.

The mock's local frame is MAVLink's MAV_FRAME_LOCAL_NED: origin at home (the EKF origin, set
when the vehicle becomes ready), x north, y east, z down, metres. Over the few kilometres a copter
covers, the flat-earth (equirectangular) approximation used here is what ArduPilot and PX4
themselves use for local offsets; its error is millimetres at 1 km.

This module is the mock's own: it must not share code with the service's frame conversions, so that
tests between the two catch a mistake on either side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6_378_137.0
"""WGS-84 equatorial radius, metres."""


@dataclass(frozen=True)
class GeoPoint:
    """A global position: latitude and longitude in degrees, altitude above mean sea level in m."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float


def ned_to_global(home: GeoPoint, north_m: float, east_m: float, down_m: float) -> GeoPoint:
    """The global position of a local NED offset from ``home``."""
    lat_deg = home.lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
    lon_deg = home.lon_deg + math.degrees(
        east_m / (EARTH_RADIUS_M * math.cos(math.radians(home.lat_deg)))
    )
    return GeoPoint(lat_deg, lon_deg, home.alt_amsl_m - down_m)


def global_to_ned(
    home: GeoPoint, lat_deg: float, lon_deg: float, alt_amsl_m: float
) -> tuple[float, float, float]:
    """The local NED offset (north_m, east_m, down_m) of a global position from ``home``."""
    north_m = math.radians(lat_deg - home.lat_deg) * EARTH_RADIUS_M
    east_m = (
        math.radians(lon_deg - home.lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(home.lat_deg))
    )
    return north_m, east_m, home.alt_amsl_m - alt_amsl_m
