"""The MAVLink dialect every module of the vehicle link speaks, and the names of its results.

MAVLink 2 is needed for signing; pymavlink picks the wire version from ``MAVLINK20`` when its
dialect module is first loaded (it would also switch on the first MAVLink 2 packet it sees), so
it is set here, before the import, for every module that takes ``mavlink`` from here.
"""

from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink

__all__ = ["mavlink", "result_name"]


def result_name(result: int | None) -> str:
    """``ACCEPTED``, ``FAILED``, ... for a MAV_RESULT; ``no answer`` for None."""
    if result is None:
        return "no answer"
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name.removeprefix("MAV_RESULT_") if entry is not None else f"result {result}"
