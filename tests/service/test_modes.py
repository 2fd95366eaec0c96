"""Flight-mode names (service.modes): built on pymavlink's tables, named as the autopilots name
them, and the numbers DO_SET_MODE takes for them."""

from __future__ import annotations

import pytest

from service.modes import (
    ARDUPILOT_COPTER_MODES,
    GUIDED_MODE_NAME,
    flavour_of,
    mode_name,
    set_mode_numbers,
)
from service.vehicle_link import mavlink
from sitl_mock.flavours import px4_custom_mode


def test_flavours_from_the_heartbeats_autopilot_field():
    assert flavour_of(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA) == "ardupilot"
    assert flavour_of(mavlink.MAV_AUTOPILOT_PX4) == "px4"
    assert flavour_of(mavlink.MAV_AUTOPILOT_GENERIC) == "generic"


@pytest.mark.parametrize(
    ("flavour", "custom_mode", "name"),
    [
        ("ardupilot", 0, "STABILIZE"),
        ("ardupilot", 4, "GUIDED"),
        ("ardupilot", 5, "LOITER"),
        ("ardupilot", 21, "SMART_RTL"),
        ("ardupilot", 12, "MODE(12)"),  # no such ArduCopter mode
        ("px4", px4_custom_mode(6), "OFFBOARD"),
        ("px4", px4_custom_mode(3), "POSCTL"),
        ("px4", px4_custom_mode(4, 3), "AUTO.LOITER"),
        ("px4", px4_custom_mode(4, 2), "AUTO.TAKEOFF"),
        ("px4", px4_custom_mode(4, 9), "AUTO.PRECLAND"),  # not in pymavlink's table
        ("px4", px4_custom_mode(4, 42), "AUTO.42"),
        ("px4", px4_custom_mode(42), "MODE(42)"),
        ("generic", 7, "MODE(7)"),
    ],
)
def test_mode_names(flavour, custom_mode, name):
    assert mode_name(flavour, custom_mode) == name


def test_the_guided_modes_numbers_are_what_the_autopilots_take():
    assert set_mode_numbers("ardupilot", GUIDED_MODE_NAME["ardupilot"]) == (4, 0)
    assert set_mode_numbers("px4", GUIDED_MODE_NAME["px4"]) == (6, 0)
    assert set_mode_numbers("px4", "AUTO.LOITER") == (4, 3)


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_names_and_numbers_round_trip(flavour):
    if flavour == "ardupilot":
        names = list(ARDUPILOT_COPTER_MODES.values())
    else:
        names = ["MANUAL", "POSCTL", "OFFBOARD", "AUTO.LOITER", "AUTO.RTL", "AUTO.LAND"]
    for name in names:
        main, sub = set_mode_numbers(flavour, name)
        custom_mode = main if flavour == "ardupilot" else px4_custom_mode(main, sub)
        assert mode_name(flavour, custom_mode) == name
    with pytest.raises(KeyError):
        set_mode_numbers(flavour, "NO_SUCH_MODE")
