"""Decoding SET_POSITION_TARGET_LOCAL_NED / _GLOBAL_INT: which fields the type_mask enables, which
frames are understood, and the conversion of the target to local NED around home.

A decoder returns a :class:`Target` or the name of the reason it is refused (``unsupported``,
``rejected_invalid``, ``rejected_frame``); the vehicle counts those as ``setpoints_<reason>``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl_mock.geo import GeoPoint, global_to_ned
from sitl_mock.kinematics import Vec3

# POSITION_TARGET_TYPEMASK bits.
IGNORE_X, IGNORE_Y, IGNORE_Z = 1, 2, 4
IGNORE_VX, IGNORE_VY, IGNORE_VZ = 8, 16, 32
IGNORE_AX, IGNORE_AY, IGNORE_AZ = 64, 128, 256
IGNORE_YAW, IGNORE_YAW_RATE = 1024, 2048
IGNORE_POSITION = IGNORE_X | IGNORE_Y | IGNORE_Z
IGNORE_VELOCITY = IGNORE_VX | IGNORE_VY | IGNORE_VZ
POSITION_ONLY_MASK = 3576
"""type_mask of a position-only setpoint without yaw (velocity, acceleration, yaw ignored)."""

# MAV_FRAME values the mock understands.
FRAME_GLOBAL = 0
FRAME_LOCAL_NED = 1
FRAME_GLOBAL_RELATIVE_ALT = 3
FRAME_GLOBAL_INT = 5
FRAME_GLOBAL_RELATIVE_ALT_INT = 6
FRAME_LOCAL_OFFSET_NED = 7
FRAME_BODY_NED = 8
FRAME_BODY_OFFSET_NED = 9
FRAME_GLOBAL_TERRAIN_ALT = 10
FRAME_GLOBAL_TERRAIN_ALT_INT = 11
LOCAL_FRAMES = (FRAME_LOCAL_NED, FRAME_LOCAL_OFFSET_NED, FRAME_BODY_NED, FRAME_BODY_OFFSET_NED)
GLOBAL_AMSL_FRAMES = (FRAME_GLOBAL, FRAME_GLOBAL_INT)
GLOBAL_RELATIVE_FRAMES = (
    FRAME_GLOBAL_RELATIVE_ALT,
    FRAME_GLOBAL_RELATIVE_ALT_INT,
    FRAME_GLOBAL_TERRAIN_ALT,  # flat terrain at home altitude: terrain-relative == home-relative
    FRAME_GLOBAL_TERRAIN_ALT_INT,
)


@dataclass(frozen=True)
class Target:
    """An external setpoint in local NED. ``None`` parts are the ones the type_mask ignores."""

    position: Vec3 | None
    velocity: Vec3 | None
    yaw_rad: float | None
    type_mask: int
    received_s: float


def mask_parts(type_mask: int) -> tuple[bool, bool, bool] | None:
    """(use position, use velocity, use yaw); None when neither a full position nor a full
    velocity is given (some axes only, or acceleration/force-only setpoints)."""
    use_pos = type_mask & IGNORE_POSITION == 0
    use_vel = type_mask & IGNORE_VELOCITY == 0
    partial_pos = 0 < type_mask & IGNORE_POSITION < IGNORE_POSITION
    if partial_pos or not (use_pos or use_vel):
        return None
    return use_pos, use_vel, type_mask & IGNORE_YAW == 0


def _all_finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _checked_parts(
    type_mask: int,
    position: tuple[float, float, float],
    vxyz: tuple[float, float, float],
    yaw_rad: float,
) -> tuple[bool, bool, bool] | str:
    """(use position, use velocity, use yaw) from ``type_mask``, or the reason to refuse:
    "unsupported" for a mask the mock does not handle, "rejected_invalid" for a used field that
    is not finite."""
    parts = mask_parts(type_mask)
    if parts is None:
        return "unsupported"
    use_pos, use_vel, use_yaw = parts
    if not (
        (not use_pos or _all_finite(*position))
        and (not use_vel or _all_finite(*vxyz))
        and (not use_yaw or math.isfinite(yaw_rad))
    ):
        return "rejected_invalid"
    return parts


def _rotate_yaw(v: Vec3, yaw_rad: float) -> Vec3:
    cos_y, sin_y = math.cos(yaw_rad), math.sin(yaw_rad)
    return Vec3(v.n * cos_y - v.e * sin_y, v.n * sin_y + v.e * cos_y, v.d)


def decode_local(
    frame: int,
    type_mask: int,
    xyz: tuple[float, float, float],
    vxyz: tuple[float, float, float],
    yaw_rad: float,
    position_now: Vec3,
    yaw_now_rad: float,
    now_s: float,
) -> Target | str:
    """SET_POSITION_TARGET_LOCAL_NED. LOCAL_NED is relative to home; the OFFSET and BODY frames
    to the current position (BODY ones also rotated by the current yaw)."""
    parts = _checked_parts(type_mask, xyz, vxyz, yaw_rad)
    if isinstance(parts, str):
        return parts
    use_pos, use_vel, use_yaw = parts
    if frame not in LOCAL_FRAMES:
        return "rejected_frame"
    position = Vec3(*xyz) if use_pos else None
    velocity = Vec3(*vxyz) if use_vel else None
    if frame in (FRAME_BODY_NED, FRAME_BODY_OFFSET_NED):
        position = _rotate_yaw(position, yaw_now_rad) if position is not None else None
        velocity = _rotate_yaw(velocity, yaw_now_rad) if velocity is not None else None
    if position is not None and frame != FRAME_LOCAL_NED:
        p = position_now
        position = Vec3(p.n + position.n, p.e + position.e, p.d + position.d)
    return Target(position, velocity, yaw_rad if use_yaw else None, type_mask, now_s)


def decode_global(
    frame: int,
    type_mask: int,
    lat_lon_alt: tuple[float, float, float],
    vxyz: tuple[float, float, float],
    yaw_rad: float,
    home: GeoPoint,
    now_s: float,
) -> Target | str:
    """SET_POSITION_TARGET_GLOBAL_INT (latitude and longitude in degrees): GLOBAL(_INT) altitudes
    are AMSL, RELATIVE_ALT and TERRAIN_ALT ones relative to home."""
    parts = _checked_parts(type_mask, lat_lon_alt, vxyz, yaw_rad)
    if isinstance(parts, str):
        return parts
    use_pos, use_vel, use_yaw = parts
    lat_deg, lon_deg, alt_m = lat_lon_alt
    if use_pos and not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 180.0):
        return "rejected_invalid"
    if frame in GLOBAL_AMSL_FRAMES:
        alt_amsl_m = alt_m
    elif frame in GLOBAL_RELATIVE_FRAMES:
        alt_amsl_m = home.alt_amsl_m + alt_m
    else:
        return "rejected_frame"
    position = Vec3(*global_to_ned(home, lat_deg, lon_deg, alt_amsl_m)) if use_pos else None
    velocity = Vec3(*vxyz) if use_vel else None
    return Target(position, velocity, yaw_rad if use_yaw else None, type_mask, now_s)
