"""The autopilot's own fence, as ArduPilot and PX4 keep it: zones uploaded with the mission
protocol (``MAV_MISSION_TYPE_FENCE``: polygon and circle inclusions and exclusions, a return
point), a ceiling and a breach action set as parameters. Pure: no clock, no I/O.

Zones are stored as the items came (latitude/longitude in degE7) and tested in local NED metres
around home (:func:`sitl_mock.geo.global_to_ned`), with even-odd ray casting as both autopilots
do. Heights do not exist in a fence zone: a polygon forbids (or allows) a column at every height.

Parameters (names, units and defaults of the real autopilots):

* ArduPilot: ``FENCE_ENABLE`` (0), ``FENCE_TYPE`` (7: bit 1 ceiling, 2 circle, 4 polygons,
  8 floor: settable, not modelled), ``FENCE_ACTION`` (1: RTL or Land; 0 report only, 2 Land,
  3 SmartRTL, 4 Brake, 5 SmartRTL or Land; SmartRTL is not modelled: its fallback is taken),
  ``FENCE_ALT_MAX`` (m above home), ``FENCE_ALT_MIN``, ``FENCE_MARGIN`` (2 m),
  ``AVOID_ENABLE`` (3: bit 1 stops GUIDED velocity control ``FENCE_MARGIN`` short of the fence,
  as AC_Avoid does). A mode change while breached starts a
  10 s "manual recovery" in which new breaches are ignored (ArduCopter's, its own fence
  action's mode change included).
* PX4: ``GF_ACTION`` (2: Hold; 0 none, 1 warning, 3 Return, 4 Terminate, 5 Land),
  ``GF_MAX_VER_DIST`` (m above home, 0: none). PX4's fence is on whenever it has zones or a
  ceiling and ``GF_ACTION`` is not 0.

The circle of ``FENCE_TYPE`` bit 2 (``FENCE_RADIUS``, PX4 ``GF_MAX_HOR_DIST``) is the mock's own
cylinder (:class:`sitl_mock.kinematics.Fence`, set from the command line), which holds the
vehicle at its edge; it is not repeated here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

from sitl_mock.geo import GeoPoint, global_to_ned
from sitl_mock.kinematics import Vec3

CMD_RETURN_POINT = 5000
CMD_POLYGON_INCLUSION = 5001
CMD_POLYGON_EXCLUSION = 5002
CMD_CIRCLE_INCLUSION = 5003
CMD_CIRCLE_EXCLUSION = 5004
FENCE_COMMANDS = (
    CMD_RETURN_POINT,
    CMD_POLYGON_INCLUSION,
    CMD_POLYGON_EXCLUSION,
    CMD_CIRCLE_INCLUSION,
    CMD_CIRCLE_EXCLUSION,
)
GLOBAL_FRAMES = (0, 3, 5, 6, 10, 11)
"""MAV_FRAME values a fence item may use (ArduPilot's list): global, relative, terrain."""

# ArduPilot FENCE_TYPE bits, also the breach bitmask.
ALT_MAX, CIRCLE, POLYGON, ALT_MIN = 1, 2, 4, 8
FENCE_NAMES = {ALT_MAX: "Max Alt", CIRCLE: "Circle", POLYGON: "Polygon", ALT_MIN: "Min Alt"}
GIVE_UP_DISTANCE_M = 100.0
"""ArduCopter lands instead of its action when the breach is farther than this."""
AVOID_STOP_AT_FENCE = 1

# MAV_MISSION_RESULT values.
MISSION_ACCEPTED = 0
MISSION_ERROR = 1
MISSION_UNSUPPORTED_FRAME = 2
MISSION_UNSUPPORTED = 3
MISSION_NO_SPACE = 4
MISSION_INVALID_PARAM1 = 6


@dataclass(frozen=True)
class FenceItem:
    """A fence mission item as received (``x``/``y``: degE7)."""

    command: int
    frame: int
    param1: float
    x: int
    y: int


@dataclass(frozen=True)
class Zone:
    """One zone in local NED around home: a polygon's (north, east) corners, or a circle."""

    inclusion: bool
    polygon: tuple[tuple[float, float], ...] = ()
    circle: tuple[float, float, float] | None = None
    """(north_m, east_m, radius_m)."""

    def contains(self, north_m: float, east_m: float) -> bool:
        if self.circle is not None:
            n, e, r = self.circle
            return math.hypot(north_m - n, east_m - e) <= r
        return inside_polygon(north_m, east_m, self.polygon)

    def distance_m(self, north_m: float, east_m: float) -> float:
        """Distance from the point to the zone's boundary."""
        if self.circle is not None:
            n, e, r = self.circle
            return abs(math.hypot(north_m - n, east_m - e) - r)
        corners = self.polygon
        return min(
            _segment_distance(north_m, east_m, corners[i], corners[(i + 1) % len(corners)])
            for i in range(len(corners))
        )


def inside_polygon(north_m: float, east_m: float, corners: Sequence[tuple[float, float]]) -> bool:
    """Even-odd ray casting (what ArduPilot's ``Polygon_outside`` and PX4's geofence do)."""
    inside = False
    n = len(corners)
    for i in range(n):
        (na, ea), (nb, eb) = corners[i], corners[(i + 1) % n]
        if (ea > east_m) != (eb > east_m) and north_m < na + (east_m - ea) * (nb - na) / (eb - ea):
            inside = not inside
    return inside


def _segment_distance(n: float, e: float, a: tuple[float, float], b: tuple[float, float]) -> float:
    dn, de = b[0] - a[0], b[1] - a[1]
    length2 = dn * dn + de * de
    t = 0.0 if length2 == 0 else max(0.0, min(1.0, ((n - a[0]) * dn + (e - a[1]) * de) / length2))
    return math.hypot(n - (a[0] + t * dn), e - (a[1] + t * de))


def check_items(items: Sequence[FenceItem], ardupilot: bool) -> tuple[int, str]:
    """Whether ``items`` make a valid fence: (MAV_MISSION_RESULT, the STATUSTEXT saying why, or
    ""). ArduPilot's rules (``validate_fence``, with its texts); PX4 checks the same shapes."""
    expecting: int | None = None
    left = 0
    first_count = 0
    return_points = 0
    for item in items:
        if item.frame not in GLOBAL_FRAMES:
            return MISSION_UNSUPPORTED_FRAME, ""
        if item.command not in FENCE_COMMANDS:
            return MISSION_UNSUPPORTED, ""
        if item.command in (CMD_POLYGON_INCLUSION, CMD_POLYGON_EXCLUSION):
            if item.param1 > 255:
                return MISSION_INVALID_PARAM1, ""
            count = int(item.param1)
            if count < 3:
                return MISSION_ERROR, f"Invalid vertex count ({count})"
            if left == 0:
                expecting, left, first_count = item.command, count, count
            elif item.command != expecting:
                return MISSION_ERROR, "Received incorrect vertex type"
            elif count != first_count:
                return MISSION_ERROR, f"Unexpected vertex count want={first_count} got={count}"
            left -= 1
        else:
            if left:
                return MISSION_ERROR, "Received incorrect type"
            if item.command in (CMD_CIRCLE_INCLUSION, CMD_CIRCLE_EXCLUSION) and not item.param1 > 0:
                return MISSION_ERROR, "Non-positive circle radius"
            if item.command == CMD_RETURN_POINT:
                return_points += 1
                if return_points > 1:
                    return MISSION_ERROR, "Multiple return points"
        if not (abs(item.x) <= 90e7 and abs(item.y) <= 180e7):
            return MISSION_ERROR, "Bad lat or lon"
    if left:
        return MISSION_ERROR, "Incorrect item count"
    return MISSION_ACCEPTED, ""


def zones_from_items(items: Sequence[FenceItem], home: GeoPoint) -> tuple[Zone, ...]:
    """The zones of valid ``items`` (see :func:`check_items`) in local NED around ``home``."""
    zones: list[Zone] = []
    i = 0
    while i < len(items):
        item = items[i]
        if item.command in (CMD_POLYGON_INCLUSION, CMD_POLYGON_EXCLUSION):
            count = int(item.param1)
            corners = tuple(_ne(home, v) for v in items[i : i + count])
            zones.append(Zone(item.command == CMD_POLYGON_INCLUSION, corners))
            i += count
            continue
        if item.command in (CMD_CIRCLE_INCLUSION, CMD_CIRCLE_EXCLUSION):
            n, e = _ne(home, item)
            zones.append(Zone(item.command == CMD_CIRCLE_INCLUSION, circle=(n, e, item.param1)))
        i += 1
    return tuple(zones)


def _ne(home: GeoPoint, item: FenceItem) -> tuple[float, float]:
    north_m, east_m, _ = global_to_ned(home, item.x / 1e7, item.y / 1e7, home.alt_amsl_m)
    return north_m, east_m


@dataclass(frozen=True)
class Breach:
    """What the vehicle breaches now: a FENCE_TYPE bitmask, and how far outside (m)."""

    fences: int
    distance_m: float

    @property
    def names(self) -> str:
        """ArduPilot's wording: "Polygon fence", "Max Alt and Polygon fences"."""
        names = [name for bit, name in FENCE_NAMES.items() if self.fences & bit]
        if len(names) == 1:
            return f"{names[0]} fence"
        return ", ".join(names[:-1]) + f" and {names[-1]} fences"


class AutopilotFence:
    """The fence zones and parameters of one vehicle (see the module docstring)."""

    def __init__(self, ardupilot: bool, home: GeoPoint, alt_max_m: float | None) -> None:
        self.ardupilot = ardupilot
        self.home = home
        self.items: tuple[FenceItem, ...] = ()
        self.zones: tuple[Zone, ...] = ()
        if ardupilot:
            self.params: dict[str, float] = {
                "FENCE_ENABLE": 0.0,
                "FENCE_TYPE": float(ALT_MAX | CIRCLE | POLYGON),
                "FENCE_ACTION": 1.0,
                "FENCE_ALT_MAX": float(alt_max_m or 100.0),
                "FENCE_ALT_MIN": -10.0,
                "FENCE_MARGIN": 2.0,
                "AVOID_ENABLE": 3.0,
            }
        else:
            self.params = {"GF_ACTION": 2.0, "GF_MAX_VER_DIST": float(alt_max_m or 0.0)}

    # ------------------------------------------------------------------ parameters

    INTEGER_PARAMS: ClassVar[frozenset[str]] = frozenset(
        {"FENCE_ENABLE", "FENCE_TYPE", "FENCE_ACTION", "AVOID_ENABLE", "GF_ACTION"}
    )
    _RANGES: ClassVar[dict[str, tuple[float, float]]] = {
        "FENCE_ENABLE": (0, 1),
        "FENCE_TYPE": (0, 15),
        "FENCE_ACTION": (0, 5),
        "FENCE_ALT_MAX": (10.0, 1000.0),
        "FENCE_ALT_MIN": (-100.0, 100.0),
        "FENCE_MARGIN": (1.0, 10.0),
        "AVOID_ENABLE": (0, 7),
        "GF_ACTION": (0, 5),
        "GF_MAX_VER_DIST": (0.0, 10000.0),
    }

    def set_param(self, name: str, value: float) -> bool:
        """Set a fence parameter; False (value kept) for a value out of its range or not whole
        where it must be."""
        if name not in self.params or not math.isfinite(value):
            return False
        low, high = self._RANGES[name]
        if not low <= value <= high:
            return False
        if name in self.INTEGER_PARAMS and value != int(value):
            return False
        self.params[name] = float(value)
        return True

    @property
    def enabled(self) -> bool:
        """Whether breaches are acted on (PX4: a non-zero GF_ACTION)."""
        if self.ardupilot:
            return self.params["FENCE_ENABLE"] == 1
        return self.params["GF_ACTION"] != 0

    @property
    def action(self) -> int:
        return int(self.params["FENCE_ACTION" if self.ardupilot else "GF_ACTION"])

    @property
    def avoidance(self) -> bool:
        """ArduPilot's AC_Avoid stops GUIDED velocity control at an enabled fence."""
        return (
            self.ardupilot
            and self.enabled
            and int(self.params["AVOID_ENABLE"]) & AVOID_STOP_AT_FENCE != 0
        )

    def _types(self) -> int:
        if self.ardupilot:
            return int(self.params["FENCE_TYPE"])
        return POLYGON | (ALT_MAX if self.params["GF_MAX_VER_DIST"] > 0 else 0)

    def _alt_max_m(self) -> float:
        return self.params["FENCE_ALT_MAX" if self.ardupilot else "GF_MAX_VER_DIST"]

    # ------------------------------------------------------------------ zones

    def store(self, items: Sequence[FenceItem]) -> None:
        """Keep ``items`` (checked with :func:`check_items`) as the fence."""
        self.items = tuple(items)
        self.zones = zones_from_items(self.items, self.home)

    # ------------------------------------------------------------------ checks

    def breach(self, position: Vec3) -> Breach:
        """What ``position`` (NED around home) breaches among the fences its parameters select
        (ceiling, polygons and circles), whether or not acted on. ArduPilot's ceiling is
        breached at it, PX4's above it."""
        fences, distance_m = 0, 0.0
        types = self._types()
        alt_m = -position.d
        alt_max_m = self._alt_max_m()
        if types & ALT_MAX and alt_max_m > 0:
            over = alt_m >= alt_max_m if self.ardupilot else alt_m > alt_max_m
            if over:
                fences |= ALT_MAX
                distance_m = max(distance_m, alt_m - alt_max_m)
        if types & POLYGON and self.zones:
            outside = self._zone_distance(position.n, position.e)
            if outside is not None:
                fences |= POLYGON
                distance_m = max(distance_m, outside)
        return Breach(fences, distance_m)

    def near(self, position: Vec3) -> int:
        """The fences ``position`` is within FENCE_MARGIN of, or beyond (ArduPilot; where
        AC_Avoid stops velocity control)."""
        margin_m = self.params.get("FENCE_MARGIN", 0.0)
        fences = 0
        types = self._types()
        if types & ALT_MAX and -position.d >= self._alt_max_m() - margin_m:
            fences |= ALT_MAX
        if types & POLYGON:
            for zone in self.zones:
                inside = zone.contains(position.n, position.e)
                if inside != zone.inclusion or zone.distance_m(position.n, position.e) < margin_m:
                    fences |= POLYGON
                    break
        return fences

    def destination_ok(self, position: Vec3) -> bool:
        """ArduPilot's ``check_destination_within_fence``: a GUIDED position target above
        FENCE_ALT_MAX or outside the zones of an enabled fence is refused (PX4 does not check
        offboard setpoints)."""
        if not (self.ardupilot and self.enabled):
            return True
        types = self._types()
        if types & ALT_MAX and -position.d > self._alt_max_m():
            return False
        return not (types & POLYGON and self._zone_distance(position.n, position.e) is not None)

    def _zone_distance(self, north_m: float, east_m: float) -> float | None:
        """How far outside the zones the point is (None: inside every inclusion and outside
        every exclusion)."""
        worst: float | None = None
        for zone in self.zones:
            inside = zone.contains(north_m, east_m)
            if inside != zone.inclusion:
                d = zone.distance_m(north_m, east_m)
                worst = d if worst is None else max(worst, d)
        return worst
