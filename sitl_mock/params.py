"""A small parameter table, so that ground stations and MAVSDK can read the settings that matter to
a client (speeds, return and takeoff altitudes, fence, failsafe timeouts).

Names and units are the real ones of each autopilot (ArduPilot speeds in cm/s, altitudes in cm;
PX4 in m/s and m), so that a client reading them gets what it would from the real vehicle. Values
come from the vehicle's configuration, which the command line sets: PARAM_SET of those is answered
with the unchanged value. Two kinds are exceptions. PX4's ``MPC_XY_VEL_MAX`` (its horizontal
speed limit in every mode, offboard included; 0-20 m/s as on PX4) sets the vehicle's speed
limit, as ``MAV_CMD_DO_CHANGE_SPEED`` does; as PX4 does, a limit below ``MPC_XY_CRUISE`` or
``MPC_VEL_MANUAL`` lowers them to it and says so ("Cruise speed has been constrained by max
speed"), and those two may be set (up to the limit). The uploaded fence's parameters (ArduPilot
``FENCE_ENABLE`` (0 at boot, as on ArduPilot), ``FENCE_TYPE``, ``FENCE_ACTION``,
``FENCE_ALT_MAX``, ``FENCE_ALT_MIN``, ``FENCE_MARGIN``, ``AVOID_ENABLE``; PX4 ``GF_ACTION``,
``GF_MAX_VER_DIST``): :func:`set_parameter` takes them (within their ranges) and PARAM_VALUE
echoes the new value. ``FENCE_RADIUS`` / ``GF_MAX_HOR_DIST`` stay the mock's cylinder
(``--fence-radius-m``), which holds the vehicle whatever the parameters say.
"""

from __future__ import annotations

import math
import struct

from sitl_mock.flavours import Severity
from sitl_mock.vehicle import Vehicle

PARAM_TYPE_INT8 = 2
PARAM_TYPE_INT32 = 6
PARAM_TYPE_REAL32 = 9
PX4_XY_VEL_MAX_MPS = 20.0
"""The top of PX4's ``MPC_XY_VEL_MAX`` range."""
PX4_CAPPED_TEXT = {
    "MPC_XY_CRUISE": "Cruise speed has been constrained by max speed",
    "MPC_VEL_MANUAL": "Manual speed has been constrained by max speed",
}
"""What PX4 says when its horizontal limit lowers one of the speeds it caps."""
INT_TYPES = frozenset({1, 2, 3, 4, 5, 6})
"""MAV_PARAM_TYPE_UINT8 .. INT32."""


def parameter_table(vehicle: Vehicle, system_id: int) -> list[tuple[str, float, int]]:
    """The parameters as (name, value, MAV_PARAM_TYPE), in a fixed order (the PARAM_VALUE index)."""
    cfg = vehicle.config
    fence_radius_m = cfg.fence_radius_m or 0.0
    if vehicle.flavour.name == "ardupilot":
        fs_gcs = {"none": 0, "rtl": 1, "land": 5}[cfg.gcs_failsafe_action]
        table = [
            ("SYSID_THISMAV", system_id, PARAM_TYPE_INT32),
            ("WPNAV_SPEED", vehicle.max_speed_h_mps * 100.0, PARAM_TYPE_REAL32),
            ("WPNAV_SPEED_UP", vehicle.max_speed_up_mps * 100.0, PARAM_TYPE_REAL32),
            ("WPNAV_SPEED_DN", vehicle.max_speed_down_mps * 100.0, PARAM_TYPE_REAL32),
            ("WPNAV_ACCEL", cfg.accel_h_mps2 * 100.0, PARAM_TYPE_REAL32),
            ("LAND_SPEED", vehicle.land_speed_mps * 100.0, PARAM_TYPE_REAL32),
            ("RTL_ALT", vehicle.rtl_alt_m * 100.0, PARAM_TYPE_REAL32),
            ("DISARM_DELAY", cfg.auto_disarm_s, PARAM_TYPE_INT32),
            ("FS_GCS_ENABLE", fs_gcs, PARAM_TYPE_INT32),
            ("FS_GCS_TIMEOUT", cfg.gcs_failsafe_s, PARAM_TYPE_REAL32),
            ("FENCE_RADIUS", fence_radius_m, PARAM_TYPE_REAL32),
            ("BATT_CAPACITY", cfg.battery_capacity_mah, PARAM_TYPE_INT32),
        ]
    else:
        nav_dll = {"none": 0, "rtl": 2, "land": 3}[cfg.gcs_failsafe_action]
        table = [
            ("MAV_SYS_ID", system_id, PARAM_TYPE_INT32),
            ("MPC_XY_VEL_MAX", vehicle.max_speed_h_mps, PARAM_TYPE_REAL32),
            *((n, v, PARAM_TYPE_REAL32) for n, v in vehicle.px4_capped_speeds_mps.items()),
            *((n, v, PARAM_TYPE_REAL32) for n, v in vehicle.px4_manual_sides_mps.items()),
            ("MPC_Z_VEL_MAX_UP", vehicle.max_speed_up_mps, PARAM_TYPE_REAL32),
            ("MPC_Z_VEL_MAX_DN", vehicle.max_speed_down_mps, PARAM_TYPE_REAL32),
            ("MPC_ACC_HOR", cfg.accel_h_mps2, PARAM_TYPE_REAL32),
            ("MPC_LAND_SPEED", vehicle.land_speed_mps, PARAM_TYPE_REAL32),
            ("MIS_TAKEOFF_ALT", vehicle.default_takeoff_alt_m or 0.0, PARAM_TYPE_REAL32),
            ("RTL_RETURN_ALT", vehicle.rtl_alt_m, PARAM_TYPE_REAL32),
            ("COM_OF_LOSS_T", cfg.offboard_timeout_s, PARAM_TYPE_REAL32),
            ("COM_DISARM_PRFLT", cfg.auto_disarm_s, PARAM_TYPE_REAL32),
            ("NAV_DLL_ACT", nav_dll, PARAM_TYPE_INT32),
            ("COM_DL_LOSS_T", cfg.gcs_failsafe_s, PARAM_TYPE_INT32),
            ("GF_MAX_HOR_DIST", fence_radius_m, PARAM_TYPE_REAL32),
            ("BAT1_CAPACITY", cfg.battery_capacity_mah, PARAM_TYPE_REAL32),
        ]
    fence = vehicle.autopilot_fence
    # ArduPilot's fence integers are AP_Int8s (FENCE_ENABLE, FENCE_TYPE, FENCE_ACTION,
    # AVOID_ENABLE), sent float-cast; PX4's GF_ACTION is an INT32, sent bytewise.
    integer = PARAM_TYPE_INT8 if vehicle.flavour.name == "ardupilot" else PARAM_TYPE_INT32
    for name, value in fence.params.items():
        kind = integer if name in fence.INTEGER_PARAMS else PARAM_TYPE_REAL32
        table.append((name, value, kind))
    return [(name, float(value), kind) for name, value, kind in table]


def set_parameter(vehicle: Vehicle, name: str, value: float, param_type: int) -> bool:
    """PARAM_SET of ``name``: True when the vehicle took ``value`` (PX4's speed limit or one of
    the fence's parameters, within its range); False when it keeps its own (read-only, unknown,
    out of range). PX4 (``params_bytewise``) sends integers bit for bit in the float: decoded
    here."""
    if vehicle.flavour.params_bytewise and param_type in INT_TYPES:
        value = float(struct.unpack("<i", struct.pack("<f", value))[0])
    if not math.isfinite(value):
        return False
    if vehicle.flavour.name == "px4" and name == "MPC_XY_VEL_MAX":
        if not 0.0 < value <= PX4_XY_VEL_MAX_MPS:
            return False
        vehicle.max_speed_h_mps = value
        for capped, current in vehicle.px4_capped_speeds_mps.items():
            if current > value:
                vehicle.px4_capped_speeds_mps[capped] = value
                vehicle.say(Severity.CRITICAL, PX4_CAPPED_TEXT[capped])
        return True
    if vehicle.flavour.name == "px4" and name in vehicle.px4_capped_speeds_mps:
        if not 0.0 < value <= PX4_XY_VEL_MAX_MPS:
            return False
        vehicle.px4_capped_speeds_mps[name] = min(value, vehicle.max_speed_h_mps)
        return True
    return vehicle.autopilot_fence.set_param(name, value)
