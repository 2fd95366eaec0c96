"""Flight modes as the vehicle's HEARTBEAT states them: the autopilot's flavour, and readable
names for its ``custom_mode`` and back, built on pymavlink's own tables.

* ArduPilot (ArduCopter: TUPA flies copters): ``pymavlink.mavutil.mode_mapping_acm``, the custom
  mode numbers ArduCopter uses, named as ArduPilot names them (``GUIDED``, ``LOITER``, ...).
* PX4: ``custom_mode`` packs a main mode (bits 16-23) and, in AUTO, a sub mode (bits 24-31)
  (PX4's ``px4_custom_mode.h``); the numbers are pymavlink's ``PX4_CUSTOM_MAIN_MODE_*`` and
  ``PX4_CUSTOM_SUB_MODE_AUTO_*``. Names are PX4's own (``OFFBOARD``, ``AUTO.LOITER``, as
  QGroundControl shows them), not pymavlink's ``interpret_px4_mode`` (which says ``LOITER`` for
  ``AUTO.LOITER``). PX4's ``AUTO.PRECLAND`` (sub mode 9) is not in pymavlink: added here.

Both link backends decode HEARTBEATs through :func:`flavour_of` and :func:`mode_name`, and ask for
the guided mode through :func:`set_mode_numbers`.
"""

from __future__ import annotations

import os
from typing import Literal

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink loads its dialect (signing needs v2)
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

Flavour = Literal["ardupilot", "px4", "generic"]

ARDUPILOT_COPTER_MODES: dict[int, str] = dict(mavutil.mode_mapping_acm)
"""ArduCopter's custom mode number -> name (pymavlink's table)."""

_MAIN_PREFIX = "PX4_CUSTOM_MAIN_MODE_"
_AUTO_PREFIX = "PX4_CUSTOM_SUB_MODE_AUTO_"
PX4_MAIN_MODES: dict[int, str] = {
    value: name.removeprefix(_MAIN_PREFIX)
    for name, value in vars(mavutil).items()
    if name.startswith(_MAIN_PREFIX)
}
"""PX4's main mode number -> name (pymavlink's ``PX4_CUSTOM_MAIN_MODE_*``)."""
PX4_AUTO_SUB_MODES: dict[int, str] = {
    **{
        value: name.removeprefix(_AUTO_PREFIX)
        for name, value in vars(mavutil).items()
        if name.startswith(_AUTO_PREFIX)
    },
    9: "PRECLAND",  # PX4's PX4_CUSTOM_SUB_MODE_AUTO_PRECLAND, missing from pymavlink
}
"""PX4's AUTO sub mode number -> name (pymavlink's ``PX4_CUSTOM_SUB_MODE_AUTO_*``)."""
PX4_MAIN_AUTO = mavutil.PX4_CUSTOM_MAIN_MODE_AUTO

GUIDED_MODE_NAME: dict[str, str] = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}
"""The mode in which each flavour follows position setpoints from outside."""


def flavour_of(autopilot: int) -> Flavour:
    """The flavour for a HEARTBEAT ``autopilot`` value."""
    if autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    if autopilot == mavlink.MAV_AUTOPILOT_PX4:
        return "px4"
    return "generic"


def mode_name(flavour: Flavour, custom_mode: int) -> str:
    """A readable name for HEARTBEAT ``custom_mode`` (``MODE(n)`` when unknown)."""
    if flavour == "ardupilot":
        return ARDUPILOT_COPTER_MODES.get(custom_mode, f"MODE({custom_mode})")
    if flavour == "px4":
        main = (custom_mode >> 16) & 0xFF
        sub = (custom_mode >> 24) & 0xFF
        if main == PX4_MAIN_AUTO:
            return f"AUTO.{PX4_AUTO_SUB_MODES.get(sub, str(sub))}"
        return PX4_MAIN_MODES.get(main, f"MODE({main})")
    return f"MODE({custom_mode})"


def set_mode_numbers(flavour: Flavour, name: str) -> tuple[int, int]:
    """(custom main mode, sub mode) that MAV_CMD_DO_SET_MODE takes for mode ``name`` (param2,
    param3; the sub mode is 0 outside PX4's AUTO). KeyError for a name the flavour lacks."""
    if flavour == "ardupilot":
        numbers = {mode: number for number, mode in ARDUPILOT_COPTER_MODES.items()}
        return numbers[name], 0
    if flavour == "px4":
        if name.startswith("AUTO."):
            subs = {mode: number for number, mode in PX4_AUTO_SUB_MODES.items()}
            return PX4_MAIN_AUTO, subs[name.removeprefix("AUTO.")]
        mains = {mode: number for number, mode in PX4_MAIN_MODES.items() if mode != "AUTO"}
        return mains[name], 0
    raise KeyError(f"{flavour}: no custom modes known")
