"""A small read-only parameter table, so that ground stations and MAVSDK can read the settings that
matter to a client (speeds, return and takeoff altitudes, fence, failsafe timeouts).

Names and units are the real ones of each autopilot (ArduPilot speeds in cm/s, altitudes in cm;
PX4 in m/s and m), so that a client reading them gets what it would from the real vehicle. Values
come from the vehicle's configuration; PARAM_SET is answered with the unchanged value (the mock is
configured from its command line, not through parameters).
"""

from __future__ import annotations

from sitl_mock.vehicle import Vehicle

PARAM_TYPE_INT32 = 6
PARAM_TYPE_REAL32 = 9


def parameter_table(vehicle: Vehicle, system_id: int) -> list[tuple[str, float, int]]:
    """The parameters as (name, value, MAV_PARAM_TYPE), in a fixed order (the PARAM_VALUE index)."""
    cfg = vehicle.config
    fence_radius_m = cfg.fence_radius_m or 0.0
    fence_alt_m = cfg.fence_alt_max_m or 0.0
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
            ("FENCE_ENABLE", 1 if fence_radius_m or fence_alt_m else 0, PARAM_TYPE_INT32),
            ("FENCE_RADIUS", fence_radius_m, PARAM_TYPE_REAL32),
            ("FENCE_ALT_MAX", fence_alt_m, PARAM_TYPE_REAL32),
            ("BATT_CAPACITY", cfg.battery_capacity_mah, PARAM_TYPE_INT32),
        ]
    else:
        nav_dll = {"none": 0, "rtl": 2, "land": 3}[cfg.gcs_failsafe_action]
        table = [
            ("MAV_SYS_ID", system_id, PARAM_TYPE_INT32),
            ("MPC_XY_VEL_MAX", vehicle.max_speed_h_mps, PARAM_TYPE_REAL32),
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
            ("GF_MAX_VER_DIST", fence_alt_m, PARAM_TYPE_REAL32),
            ("BAT1_CAPACITY", cfg.battery_capacity_mah, PARAM_TYPE_REAL32),
        ]
    return [(name, float(value), kind) for name, value, kind in table]
