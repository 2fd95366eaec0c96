"""Every command the service sends, checked against the MAVLink common message set's own words
for its parameters (pymavlink's copy of the XML): positions and yaw NaN when unused, "Empty" and
"Reserved (default:0)" zero, so that no autopilot reads a 0 as a coordinate (PX4 flew nowhere
with a take-off position of latitude/longitude 0/0)."""

from __future__ import annotations

import math

import pytest

from service import mavlink_commands
from service.vehicle_link import mavlink

SENT = {
    mavlink.MAV_CMD_NAV_TAKEOFF: mavlink_commands.takeoff(25.0),
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: mavlink_commands.arm(),
    mavlink.MAV_CMD_DO_SET_MODE: mavlink_commands.set_mode(4),
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: mavlink_commands.set_message_interval(32, 10.0),
    mavlink.MAV_CMD_DO_CHANGE_SPEED: mavlink_commands.change_speed(6.0),
}
USED = {
    mavlink.MAV_CMD_NAV_TAKEOFF: {7},
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: {1, 2},
    mavlink.MAV_CMD_DO_SET_MODE: {1, 2, 3},
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: {1, 2, 7},
    mavlink.MAV_CMD_DO_CHANGE_SPEED: {1, 2, 3},
}
"""The params each command means to set (the rest are unused)."""


def _unused_value(description: str) -> float | None:
    """What the message set says an unused param holds: NaN for a position or where it names
    NaN, 0 for "Empty" and "Reserved (default:0)"; None where it says neither."""
    text = description.strip()
    if text in ("Latitude", "Longitude", "Altitude") or "NaN" in text:
        return math.nan
    if text == "Empty" or "default:0" in text or text.startswith("Bitmask"):
        return 0.0
    if text.startswith("Minimum pitch"):
        return 0.0  # a fixed-wing's climb-out pitch: a multicopter ignores it; 0 is level
    return None


@pytest.mark.parametrize("command", sorted(SENT))
def test_every_param_is_what_the_message_set_defines(command):
    params = SENT[command]
    assert len(params) == 7
    definition = mavlink.enums["MAV_CMD"][command]
    for index in range(1, 8):
        value = params[index - 1]
        if index in USED[command]:
            assert math.isfinite(value), (definition.name, index)
            continue
        expected = _unused_value(definition.param.get(index, "Empty"))
        assert expected is not None, f"{definition.name} param{index}: no rule for it"
        if math.isnan(expected):
            assert math.isnan(value), f"{definition.name} param{index} must be NaN when unused"
        else:
            assert value == expected, f"{definition.name} param{index} must be {expected}"


def test_takeoff_sends_the_altitude_and_nan_for_where_and_heading():
    params = mavlink_commands.takeoff(513.9)
    assert params[6] == 513.9
    assert all(math.isnan(p) for p in params[3:6])
    assert params[:3] == (0.0, 0.0, 0.0)
