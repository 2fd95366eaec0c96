"""The mock's own tables against MAVLink's. (Its import rule — pymavlink and the standard library
only, never the project's own packages — is checked with every room's in
``tests/test_rooms.py``.)"""

from __future__ import annotations

from pathlib import Path

import sitl_mock
from sitl_mock.flavours import ARDUPILOT, PX4, MavResult, Severity

PACKAGE_DIR = Path(sitl_mock.__file__).parent


def test_enums_match_mavlink():
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    for result in MavResult:
        assert getattr(mavlink, f"MAV_RESULT_{result.name}") == result.value
    for severity in Severity:
        assert getattr(mavlink, f"MAV_SEVERITY_{severity.name}") == severity.value
    assert ARDUPILOT.autopilot_type == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert PX4.autopilot_type == mavlink.MAV_AUTOPILOT_PX4


def test_mode_numbers():
    assert ARDUPILOT.mode("GUIDED").custom_mode == 4
    assert ARDUPILOT.mode("LAND").custom_mode == 9
    assert PX4.mode("OFFBOARD").custom_mode == 393216  # 6 << 16, as QGroundControl shows it
    assert PX4.mode("AUTO.LOITER").custom_mode == 4 << 16 | 3 << 24
    assert PX4.custom_mode_from_command(4.0, 6.0) == PX4.mode("AUTO.LAND").custom_mode
    assert PX4.custom_mode_from_command(6.0, 0.0) == PX4.mode("OFFBOARD").custom_mode
    # Sub mode bits do not matter outside AUTO.
    assert PX4.mode_by_custom(6 << 16 | 7 << 24) == PX4.mode("OFFBOARD")
    assert ARDUPILOT.custom_mode_from_command(float("nan"), 0.0) is None
    assert ARDUPILOT.mode_by_custom(3) is None  # AUTO: the mock flies no missions


def test_geo_round_trip():
    from sitl_mock.geo import GeoPoint, global_to_ned, ned_to_global

    home = GeoPoint(-35.363261, 149.165230, 584.0)
    for ned in [(0.0, 0.0, 0.0), (500.0, -250.0, -100.0), (-1000.0, 1000.0, 5.0)]:
        point = ned_to_global(home, *ned)
        back = global_to_ned(home, point.lat_deg, point.lon_deg, point.alt_amsl_m)
        assert all(abs(a - b) < 1e-6 for a, b in zip(back, ned, strict=True))
    north = ned_to_global(home, 111_319.49, 0.0, 0.0)  # ~1 degree of latitude
    assert abs(north.lat_deg - home.lat_deg - 1.0) < 1e-4
