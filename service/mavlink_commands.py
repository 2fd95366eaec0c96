"""The COMMAND_LONG parameters the service sends, written out in full, one function a command.

Every command fills all seven params the way the MAVLink common message set defines them:
a param that carries a position or a yaw is NaN when unused (MAVLink's "use the current/default"
value; 0 there is a real value: PX4 reads latitude/longitude 0/0 as a point in the Gulf of Guinea
and does not climb), and a param marked "Empty" or "Reserved (default:0)" is 0. Both backends
send these tuples as they are (pymavlink as floats, MAVSDK with NaN as JSON null), and
``tests/service/test_mavlink_commands.py`` checks each one against pymavlink's copy of the
message set's parameter descriptions.

What each autopilot makes of them:

* ``MAV_CMD_NAV_TAKEOFF``: param7 is the altitude above home on ArduPilot and AMSL on PX4
  (:func:`takeoff`'s caller picks); NaN yaw keeps the vehicle's heading; NaN latitude/longitude
  take off where the vehicle stands. ArduCopter reads param3 = 0 as "must navigate", which its
  navigating modes (GUIDED) accept.
* ``MAV_CMD_DO_CHANGE_SPEED``: ArduCopter's GUIDED takes it as its horizontal speed until it
  leaves GUIDED; PX4 applies it to its flight tasks (missions, hold), not to offboard.
* ``MAV_CMD_DO_SET_MODE``: param1 says the mode is a custom one; param2 is the custom (main) mode,
  param3 PX4's sub mode (0 for the main modes we ask for, and unused on ArduPilot).
"""

from __future__ import annotations

import math
import os

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink

Params = tuple[float, float, float, float, float, float, float]

NAN = math.nan


def takeoff(altitude_m: float) -> Params:
    """MAV_CMD_NAV_TAKEOFF to ``altitude_m`` (the flavour's altitude frame), here, heading kept."""
    return (0.0, 0.0, 0.0, NAN, NAN, NAN, float(altitude_m))


def arm(arm_: bool = True) -> Params:
    """MAV_CMD_COMPONENT_ARM_DISARM (never forced: the vehicle's safety checks apply)."""
    return (1.0 if arm_ else 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def set_mode(custom_mode: int, custom_sub_mode: int = 0) -> Params:
    """MAV_CMD_DO_SET_MODE to a custom (autopilot-specific) mode."""
    return (
        float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
        float(custom_mode),
        float(custom_sub_mode),
        0.0,
        0.0,
        0.0,
        0.0,
    )


def return_to_launch() -> Params:
    """MAV_CMD_NAV_RETURN_TO_LAUNCH: the autopilot's own return (its RTL mode and altitude)."""
    return (0.0,) * 7  # type: ignore[return-value]


def change_speed(ground_speed_mps: float) -> Params:
    """MAV_CMD_DO_CHANGE_SPEED: the horizontal ground speed (speed type 1), throttle unchanged
    (-1); ArduCopter applies it to GUIDED's position controller."""
    return (1.0, float(ground_speed_mps), -1.0, 0.0, 0.0, 0.0, 0.0)


def set_message_interval(message_id: int, rate_hz: float) -> Params:
    """MAV_CMD_SET_MESSAGE_INTERVAL: ``message_id`` every 1 / ``rate_hz`` s, to the requester's
    stream as the flight stack sends it by default (param7 = 0)."""
    return (float(message_id), 1e6 / rate_hz, 0.0, 0.0, 0.0, 0.0, 0.0)
