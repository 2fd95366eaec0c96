"""The simulated vehicle's settings: speeds, start-up time, failsafes, geofence, battery."""

from __future__ import annotations

import math
from dataclasses import dataclass

from sitl_mock.geo import GeoPoint


@dataclass
class VehicleConfig:
    """Everything about the simulated vehicle a user may change; None: the flavour's default."""

    home: GeoPoint | None = None
    max_speed_h_mps: float = 10.0
    max_speed_up_mps: float = 3.0
    max_speed_down_mps: float = 3.0
    accel_h_mps2: float = 2.5
    accel_v_mps2: float = 2.5
    yaw_rate_max_dps: float = 90.0
    ready_delay_s: float | None = None
    """Time from boot until the position estimate is ready (arming/GUIDED refused before)."""
    origin_delay_s: float | None = None
    """Time from boot until the EKF origin is set (no LOCAL_POSITION_NED before); never later
    than ``ready_delay_s``."""
    prearm_delay_s: float | None = None
    """Time from boot until arming passes in modes that need no position; never later than
    ``ready_delay_s``."""
    mode_switch_read_s: float | None = None
    """When the RC mode switch is first read and sets the initial mode (ArduPilot); never later
    than ``ready_delay_s``. A negative value: never."""
    offboard_timeout_s: float = 1.0
    """PX4 OFFBOARD: setpoints older than this trigger the hold failsafe (PX4's COM_OF_LOSS_T)."""
    offboard_stream_min_s: float = 1.0
    """PX4: the setpoint stream must have run this long before OFFBOARD is accepted."""
    offboard_stream_max_gap_s: float = 0.5
    """PX4: setpoints further apart than this do not count as a stream (PX4 wants > 2 Hz)."""
    auto_disarm_s: float = 10.0
    """Armed on the ground without taking off for this long: disarm (ArduPilot DISARM_DELAY,
    PX4 COM_DISARM_PRFLT)."""
    gcs_failsafe_s: float = 5.0
    """Armed and no ground-station HEARTBEAT for this long (after one was seen): failsafe."""
    gcs_failsafe_action: str = "rtl"
    """``rtl``, ``land`` or ``none``. On the ground the failsafe disarms."""
    fence_radius_m: float | None = 1000.0
    """Horizontal fence: a cylinder around home. None or 0: no horizontal fence."""
    fence_alt_max_m: float | None = 150.0
    """Fence ceiling above home. None or 0: no ceiling."""
    fence_action: str = "reject"
    """For a setpoint outside the fence: ``reject`` (ignore and count) or ``clamp`` (go to the
    nearest point on the fence). The vehicle itself is always held at the fence."""
    battery_capacity_mah: float = 5000.0
    battery_failsafe_pct: float = 10.0
    """Remaining charge at which a flying vehicle lands. 0: no battery failsafe."""
    rtl_alt_m: float | None = None
    land_speed_mps: float | None = None
    takeoff_alt_m: float | None = None
    """PX4: takeoff altitude when MAV_CMD_NAV_TAKEOFF gives none (PX4's MIS_TAKEOFF_ALT)."""

    def validate(self) -> None:
        """Raise ValueError naming the first field with an impossible value."""
        positive = (
            "max_speed_h_mps",
            "max_speed_up_mps",
            "max_speed_down_mps",
            "accel_h_mps2",
            "accel_v_mps2",
            "yaw_rate_max_dps",
            "offboard_timeout_s",
            "offboard_stream_max_gap_s",
            "auto_disarm_s",
            "gcs_failsafe_s",
            "battery_capacity_mah",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive number, got {value!r}")
        optional_non_negative = (
            "ready_delay_s",
            "origin_delay_s",
            "prearm_delay_s",
            "fence_radius_m",
            "fence_alt_max_m",
            "rtl_alt_m",
            "land_speed_mps",
            "takeoff_alt_m",
        )
        for name in (*optional_non_negative, "offboard_stream_min_s", "battery_failsafe_pct"):
            value = getattr(self, name)
            if value is None and name in optional_non_negative:
                continue
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: must be a number >= 0, got {value!r}")
        if self.mode_switch_read_s is not None and not (
            isinstance(self.mode_switch_read_s, int | float)
            and math.isfinite(self.mode_switch_read_s)
        ):
            raise ValueError(
                f"mode_switch_read_s: must be a number (negative: never), "
                f"got {self.mode_switch_read_s!r}"
            )
        if self.land_speed_mps == 0:
            raise ValueError("land_speed_mps: must be positive")
        if self.battery_failsafe_pct >= 100:
            raise ValueError(
                f"battery_failsafe_pct: must be below 100, got {self.battery_failsafe_pct}"
            )
        if self.gcs_failsafe_action not in ("rtl", "land", "none"):
            raise ValueError(
                f"gcs_failsafe_action: must be rtl, land or none, got {self.gcs_failsafe_action!r}"
            )
        if self.fence_action not in ("reject", "clamp"):
            raise ValueError(f"fence_action: must be reject or clamp, got {self.fence_action!r}")
        if self.home is not None:
            home = self.home
            if not (
                math.isfinite(home.lat_deg)
                and math.isfinite(home.lon_deg)
                and math.isfinite(home.alt_amsl_m)
                and -90 < home.lat_deg < 90
                and -180 <= home.lon_deg <= 180
            ):
                raise ValueError(f"home: not a valid position: {home}")
