"""Coordinate frames: the area frame, MAVLink local NED and global latitude/longitude/altitude.

Three frames meet in the service (DESIGN.md, "Frames and units"):

* **Area frame** — the simulator's and the policy's frame: origin at the area's south-west
  corner, x east, y north, z up, metres (``x_m, y_m, z_m``).
* **Local NED** — MAVLink's ``MAV_FRAME_LOCAL_NED``: origin at the vehicle's home / EKF origin,
  x north, y east, z down, metres (``north_m, east_m, down_m``).
* **Global** — WGS-84 latitude and longitude in degrees, altitude above mean sea level in metres.

:class:`FrameConfig` says where the area sits in the vehicle's local frame: the NED offset of the
area's south-west corner at z = 0 from home. ``area_origin_down_m`` handles home altitude: if home
(where the vehicle boots) is 2 m above the area's ground level, the area's z = 0 lies 2 m below
home, so ``area_origin_down_m = 2.0``.

Local NED <-> global uses the flat-earth (equirectangular) approximation ArduPilot and PX4 use for
local offsets around an origin; its error is millimetres over a kilometre.

Every function here is pure: no I/O, no state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6_378_137.0
"""WGS-84 equatorial radius, metres."""


@dataclass(frozen=True)
class GeoPoint:
    """A global position: latitude/longitude in degrees, altitude above mean sea level in m."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float


@dataclass(frozen=True)
class FrameConfig:
    """Where the area frame sits in the vehicle's local NED frame.

    The defaults put the area's south-west corner at home, at home's altitude.
    """

    area_origin_north_m: float = 0.0
    """North offset of the area's south-west corner from home (EKF origin), metres."""
    area_origin_east_m: float = 0.0
    """East offset of the area's south-west corner from home, metres."""
    area_origin_down_m: float = 0.0
    """Down offset of the area's z = 0 level from home, metres (positive: below home)."""

    def __post_init__(self) -> None:
        for name in ("area_origin_north_m", "area_origin_east_m", "area_origin_down_m"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ValueError(f"{name}: must be a finite number, got {value!r}")


def area_to_ned(
    x_m: float, y_m: float, z_m: float, config: FrameConfig = FrameConfig()
) -> tuple[float, float, float]:
    """Area frame (x east, y north, z up) -> local NED ``(north_m, east_m, down_m)``."""
    return (
        config.area_origin_north_m + y_m,
        config.area_origin_east_m + x_m,
        config.area_origin_down_m - z_m,
    )


def ned_to_area(
    north_m: float, east_m: float, down_m: float, config: FrameConfig = FrameConfig()
) -> tuple[float, float, float]:
    """Local NED -> area frame ``(x_m, y_m, z_m)``; the inverse of :func:`area_to_ned`."""
    return (
        east_m - config.area_origin_east_m,
        north_m - config.area_origin_north_m,
        config.area_origin_down_m - down_m,
    )


def ned_to_global(home: GeoPoint, north_m: float, east_m: float, down_m: float) -> GeoPoint:
    """The global position of a local NED offset from ``home`` (flat earth)."""
    lat_deg = home.lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
    lon_deg = home.lon_deg + math.degrees(
        east_m / (EARTH_RADIUS_M * math.cos(math.radians(home.lat_deg)))
    )
    return GeoPoint(lat_deg, lon_deg, home.alt_amsl_m - down_m)


def global_to_ned(home: GeoPoint, point: GeoPoint) -> tuple[float, float, float]:
    """The local NED offset ``(north_m, east_m, down_m)`` of ``point`` from ``home``."""
    north_m = math.radians(point.lat_deg - home.lat_deg) * EARTH_RADIUS_M
    east_m = (
        math.radians(point.lon_deg - home.lon_deg)
        * EARTH_RADIUS_M
        * math.cos(math.radians(home.lat_deg))
    )
    return north_m, east_m, home.alt_amsl_m - point.alt_amsl_m


def area_to_global(
    home: GeoPoint, x_m: float, y_m: float, z_m: float, config: FrameConfig = FrameConfig()
) -> GeoPoint:
    """Area frame -> global, through local NED around ``home``."""
    return ned_to_global(home, *area_to_ned(x_m, y_m, z_m, config))


def global_to_area(
    home: GeoPoint, point: GeoPoint, config: FrameConfig = FrameConfig()
) -> tuple[float, float, float]:
    """Global -> area frame ``(x_m, y_m, z_m)``; the inverse of :func:`area_to_global`."""
    return ned_to_area(*global_to_ned(home, point), config)


def frame_config_from_geodetic(home: GeoPoint, area_origin: GeoPoint) -> FrameConfig:
    """A :class:`FrameConfig` from the geodetic position of the area's south-west corner at z = 0.

    Use it when the area is surveyed in latitude/longitude: ``area_origin`` is the corner's
    position (its altitude: the area's ground level, AMSL), ``home`` the vehicle's home.
    """
    north_m, east_m, down_m = global_to_ned(home, area_origin)
    return FrameConfig(north_m, east_m, down_m)
