"""The flight-safety envelope as the autopilot's own fence: a second layer under the service's.

Pure functions, no I/O. :func:`fence_plan` turns an :class:`sim.envelope.Envelope` (area frame:
x east, y north, z up, metres) into a :class:`FencePlan`: the fence mission items
(``mission_type`` ``MAV_MISSION_TYPE_FENCE``) and the parameters that set the ceiling and the
breach action on ArduPilot or PX4. :mod:`service.mission_protocol` uploads it and reads it back;
:func:`compare_items` and :func:`compare_params` say whether what came back is what was sent.

Items (one per polygon vertex, in order, as both autopilots store them):

* the inclusion polygon's exterior: ``MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION``;
* each exclusion's footprint, and each hole of the inclusion polygon (a hole is a place the
  vehicle may not be, at any height): ``MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION``;
* ``param1`` = the vertex count of that polygon, ``x``/``y`` = latitude/longitude in degE7,
  ``z`` = 0, ``frame`` = ``MAV_FRAME_GLOBAL`` (what ArduPilot sends back on a download).

Geodesy: area frame -> local NED (:func:`service.frames.area_to_ned`, through the
:class:`~service.frames.FrameConfig`) -> latitude/longitude around the vehicle's home with the
flat-earth (equirectangular) approximation of :mod:`service.frames` (WGS-84 equatorial radius),
the one the link uses for global setpoints; rounding to degE7 (1.1 cm of latitude) is the only
loss: a round trip area -> degE7 -> area is within 1 cm. ArduPilot's own scaling uses a 37 m
smaller earth radius (6 ppm: 6 mm at 1 km from home).

**Exclusions lose their heights.** Fence polygons are 2-D on both autopilots: an exclusion
volume (footprint between ``floor_m`` and ``ceiling_m``) becomes a no-fly column from the ground
up, stricter than the envelope. The service's planner may route *over* a low exclusion
(:func:`sim.envelope.plan_path`'s climb-over); with the autopilot's fence on, that route crosses
the exclusion polygon and the autopilot refuses the setpoint (ArduPilot) or breaches and takes
its action (RTL, hold). Plan with :func:`fence_compatible` (every exclusion made full-height) when
the fence is uploaded.

**The ceiling** becomes a parameter (metres above home): ArduPilot ``FENCE_ALT_MAX`` with
``FENCE_TYPE`` bit 1 (and ``FENCE_ENABLE`` 1), PX4 ``GF_MAX_VER_DIST``; ``ceiling_margin_m``
(default 2 m) above the envelope's ceiling, because ArduPilot calls a vehicle *at* its
``FENCE_ALT_MAX`` a breach and the service may hold a target exactly on the envelope's ceiling.
The floor becomes ArduPilot's ``FENCE_ALT_MIN`` (``FENCE_TYPE`` bit 8) only when asked
(``include_floor``): ArduCopter arms and lands below it, enabling it only once above; PX4 has no
floor fence.

**The breach action**: ``rtl`` (ArduPilot ``FENCE_ACTION`` 1 "RTL or Land", PX4 ``GF_ACTION`` 3
"Return"), ``hold`` (ArduPilot 4 "Brake or Land", PX4 2 "Hold"), ``land`` (2 / 5), ``report``
(ArduPilot 0 "Report only", PX4 1 "Warning").
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from service.frames import FrameConfig, GeoPoint, area_to_global, global_to_area
from sim.envelope import Envelope, Exclusion

Autopilot = Literal["ardupilot", "px4"]
FenceAction = Literal["rtl", "hold", "land", "report"]

CMD_INCLUSION = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
CMD_EXCLUSION = mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION
FENCE_COMMANDS = {CMD_INCLUSION: "inclusion", CMD_EXCLUSION: "exclusion"}
FRAME_GLOBAL = mavlink.MAV_FRAME_GLOBAL
PARAM_INT = mavlink.MAV_PARAM_TYPE_INT32
PARAM_REAL = mavlink.MAV_PARAM_TYPE_REAL32
MAX_VERTICES = 255
"""ArduPilot refuses a vertex count above 255 (``MAV_MISSION_INVALID_PARAM1``)."""
DEG_E7_TOLERANCE = 1
"""Read-back tolerance of a vertex: 1 degE7 (1e-7 degree)."""
PARAM_TOLERANCE = 0.01
"""Read-back tolerance of a parameter: 1 cm for the metres, exact for the integers."""

# ArduPilot FENCE_TYPE bits (AC_Fence.h).
AP_FENCE_ALT_MAX, AP_FENCE_CIRCLE, AP_FENCE_POLYGON, AP_FENCE_ALT_MIN = 1, 2, 4, 8
AP_FENCE_ACTION = {"report": 0, "rtl": 1, "land": 2, "hold": 4}
PX4_GF_ACTION = {"report": 1, "hold": 2, "rtl": 3, "land": 5}


class FenceError(ValueError):
    """The envelope cannot become this autopilot's fence (one line naming the field)."""


@dataclass(frozen=True)
class FenceItem:
    """One fence mission item (its index in the list is its ``seq``)."""

    command: int
    """``MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION`` or ``..._EXCLUSION``."""
    vertex_count: int
    """``param1``: the number of vertices of the polygon this vertex belongs to."""
    lat_e7: int
    lon_e7: int
    frame: int = FRAME_GLOBAL

    @property
    def kind(self) -> str:
        return FENCE_COMMANDS.get(self.command, f"command {self.command}")


@dataclass(frozen=True)
class FenceParam:
    """One parameter to set: name, value, MAV_PARAM_TYPE (INT32 values are whole numbers)."""

    name: str
    value: float
    param_type: int = PARAM_REAL

    @property
    def is_int(self) -> bool:
        return self.param_type != PARAM_REAL


@dataclass(frozen=True)
class FencePlan:
    """What the autopilot is told: the items (in upload order), then the parameters (in the
    order to set them: the enabling one last), for the vehicle whose home is ``home``."""

    autopilot: Autopilot
    home: GeoPoint
    items: tuple[FenceItem, ...]
    params: tuple[FenceParam, ...]
    polygons: int
    """How many polygons the items make (inclusion first, then the exclusions)."""
    ceiling_above_home_m: float
    notes: tuple[str, ...] = ()
    """What the autopilot's fence does differently from the envelope (one line each)."""


def fence_plan(
    envelope: Envelope,
    home: GeoPoint,
    frame: FrameConfig | None = None,
    autopilot: Autopilot = "ardupilot",
    action: FenceAction = "rtl",
    ceiling_margin_m: float = 2.0,
    include_floor: bool = False,
    floor_margin_m: float = 2.0,
) -> FencePlan:
    """The envelope as ``autopilot``'s fence around ``home``: the latitude/longitude/AMSL of the
    vehicle's local NED origin, in which the area frame sits as ``frame`` says (the EKF origin,
    GPS_GLOBAL_ORIGIN; HOME_POSITION is the same point unless home was moved after the origin
    was set, as ArduCopter does when it arms away from where it booted). Ceilings are
    relative to it too (FENCE_ALT_MAX and GF_MAX_VER_DIST are above home).

    FenceError, naming the field, for what cannot be a fence: a polygon with more than 255
    vertices, a ceiling at or below home, a home outside the inclusion or inside an exclusion's
    footprint (the autopilot refuses to arm there: "PreArm: Vehicle breaching Polygon fence"), a
    bad argument. ``frame`` None: the area's origin at home."""
    frame = frame if frame is not None else FrameConfig()
    if autopilot not in ("ardupilot", "px4"):
        raise FenceError(f"autopilot: must be ardupilot or px4, got {autopilot!r}")
    if action not in AP_FENCE_ACTION:
        raise FenceError(f"action: must be one of {sorted(AP_FENCE_ACTION)}, got {action!r}")
    for name, value in (("ceiling_margin_m", ceiling_margin_m), ("floor_margin_m", floor_margin_m)):
        if not (math.isfinite(value) and value >= 0):
            raise FenceError(f"{name}: must be a number >= 0, got {value!r}")
    if not all(math.isfinite(v) for v in (home.lat_deg, home.lon_deg, home.alt_amsl_m)) or not (
        -90 < home.lat_deg < 90 and -180 <= home.lon_deg <= 180
    ):
        raise FenceError(f"home: not a valid position: {home}")
    _check_home(envelope, frame)
    notes: list[str] = []
    rings: list[tuple[int, str, list[tuple[float, float]]]] = [
        (CMD_INCLUSION, "inclusion", _ring(envelope.inclusion.exterior.coords))
    ]
    for i, hole in enumerate(envelope.inclusion.interiors):
        rings.append((CMD_EXCLUSION, f"inclusion hole {i}", _ring(hole.coords)))
    for i, exclusion in enumerate(envelope.exclusions):
        if not exclusion.on_autopilot_fence:
            continue
        label = f"exclusions[{i}]" + (f" {exclusion.name!r}" if exclusion.name else "")
        rings.append((CMD_EXCLUSION, label, _ring(exclusion.footprint.exterior.coords)))
        notes.append(
            f"{label}: {exclusion.floor_m:g}-{exclusion.ceiling_m:g} m in the envelope, "
            "a no-fly column at every height in the autopilot's fence"
        )
    items: list[FenceItem] = []
    for command, label, ring in rings:
        if len(ring) > MAX_VERTICES:
            raise FenceError(
                f"{label}: {len(ring)} vertices, an autopilot fence polygon has at most "
                f"{MAX_VERTICES}"
            )
        for x_m, y_m in ring:
            point = area_to_global(home, x_m, y_m, 0.0, frame)
            items.append(
                FenceItem(command, len(ring), _deg_e7(point.lat_deg), _deg_e7(point.lon_deg))
            )
    ceiling_above_home_m = envelope.ceiling_m - frame.area_origin_down_m + ceiling_margin_m
    if ceiling_above_home_m <= 0:
        raise FenceError(
            f"ceiling_m: {envelope.ceiling_m:g} m in the area frame is "
            f"{ceiling_above_home_m:g} m above home with the margin: must be above home"
        )
    params = _params(autopilot, action, ceiling_above_home_m)
    if include_floor:
        floor_above_home_m = envelope.floor_m - frame.area_origin_down_m - floor_margin_m
        if autopilot == "px4":
            notes.append("floor: PX4 has no floor fence; the envelope's floor is the service's")
        elif floor_above_home_m > 0:
            params = _with_floor(params, floor_above_home_m)
            notes.append(
                f"floor: FENCE_ALT_MIN {floor_above_home_m:g} m, enabled by ArduCopter once "
                "the vehicle is above it (not on the ground, not while landing)"
            )
        else:
            notes.append("floor: at or below home: no floor fence")
    notes.append(
        f"ceiling: {ceiling_above_home_m:g} m above home ({ceiling_margin_m:g} m above the "
        "envelope's)"
    )
    return FencePlan(
        autopilot,
        home,
        tuple(items),
        params,
        len(rings),
        ceiling_above_home_m,
        tuple(notes),
    )


def fence_compatible(envelope: Envelope) -> Envelope:
    """The envelope with every exclusion made a full-height column (from below the floor to
    above the ceiling), as the autopilot's 2-D fence polygons have them: plan routes with it
    while the fence is uploaded, so that no route climbs over an exclusion the autopilot forbids
    at every height. The inclusion, band, clearance and speed are unchanged; an exclusion the
    fence does not hold (:attr:`~sim.envelope.volume.Exclusion.on_autopilot_fence`: a site's
    buildings) keeps its heights."""
    low = envelope.floor_m - envelope.clearance_m - 1.0
    high = envelope.ceiling_m + envelope.clearance_m + 1.0
    exclusions = tuple(
        Exclusion(e.footprint, min(e.floor_m, low), max(e.ceiling_m, high), e.name)
        if e.on_autopilot_fence
        else e
        for e in envelope.exclusions
    )
    return Envelope(
        envelope.inclusion,
        envelope.floor_m,
        envelope.ceiling_m,
        exclusions,
        envelope.clearance_m,
        envelope.max_speed_mps,
    )


def item_polygons(items: Sequence[FenceItem]) -> list[tuple[int, list[FenceItem]]]:
    """The items grouped into their polygons: ``(command, [item, ...])`` each, in order;
    ValueError for items whose vertex counts do not make whole polygons."""
    polygons: list[tuple[int, list[FenceItem]]] = []
    i = 0
    while i < len(items):
        first = items[i]
        count = first.vertex_count
        if count < 3 or i + count > len(items):
            raise ValueError(f"items[{i}]: vertex count {count} does not fit the items")
        block = list(items[i : i + count])
        if any((item.command, item.vertex_count) != (first.command, count) for item in block):
            raise ValueError(f"items[{i}]: the polygon's items differ in command or count")
        polygons.append((first.command, block))
        i += count
    return polygons


def items_to_area(
    items: Sequence[FenceItem], home: GeoPoint, frame: FrameConfig | None = None
) -> list[tuple[int, list[tuple[float, float]]]]:
    """The polygons the items make, back in the area frame: ``(command, [(x_m, y_m), ...])``
    each, in order; ValueError for items whose vertex counts do not make whole polygons."""
    frame = frame if frame is not None else FrameConfig()
    polygons: list[tuple[int, list[tuple[float, float]]]] = []
    for command, block in item_polygons(items):
        ring = []
        for item in block:
            point = GeoPoint(item.lat_e7 / 1e7, item.lon_e7 / 1e7, home.alt_amsl_m)
            x_m, y_m, _ = global_to_area(home, point, frame)
            ring.append((x_m, y_m))
        polygons.append((command, ring))
    return polygons


def compare_items(expected: Sequence[FenceItem], got: Sequence[FenceItem]) -> list[str]:
    """What differs between the items sent and the items read back (empty: the same, each
    vertex within 1 degE7); one line per difference, at most the first 10."""
    differences: list[str] = []
    if len(expected) != len(got):
        differences.append(f"{len(got)} items read back, {len(expected)} sent")
    for seq, (a, b) in enumerate(zip(expected, got, strict=False)):
        if a.command != b.command:
            differences.append(f"item {seq}: {b.kind} read back, {a.kind} sent")
        elif a.vertex_count != b.vertex_count:
            differences.append(f"item {seq}: vertex count {b.vertex_count}, {a.vertex_count} sent")
        elif (
            abs(a.lat_e7 - b.lat_e7) > DEG_E7_TOLERANCE
            or abs(a.lon_e7 - b.lon_e7) > DEG_E7_TOLERANCE
        ):
            differences.append(
                f"item {seq}: at {b.lat_e7}, {b.lon_e7} degE7, sent {a.lat_e7}, {a.lon_e7}"
            )
    return differences[:10]


def compare_params(expected: Iterable[FenceParam], got: Mapping[str, float]) -> list[str]:
    """What differs between the parameters set and their values read back (empty: all within
    1 cm, integers exact); a parameter missing from ``got`` is a difference."""
    differences = []
    for param in expected:
        value = got.get(param.name)
        if value is None:
            differences.append(f"{param.name}: not read back")
        elif abs(value - param.value) > (0.0 if param.is_int else PARAM_TOLERANCE):
            differences.append(f"{param.name}: {value:g} read back, {param.value:g} set")
    return differences


def plan_summary(plan: FencePlan) -> dict[str, Any]:
    """The plan as a small JSON-able document (for logs and the operator)."""
    return {
        "autopilot": plan.autopilot,
        "home": [plan.home.lat_deg, plan.home.lon_deg, plan.home.alt_amsl_m],
        "items": len(plan.items),
        "polygons": plan.polygons,
        "params": {p.name: p.value for p in plan.params},
        "notes": list(plan.notes),
    }


# ---------------------------------------------------------------------- internals


def _params(
    autopilot: Autopilot, action: FenceAction, ceiling_above_home_m: float
) -> tuple[FenceParam, ...]:
    ceiling = round(ceiling_above_home_m, 2)
    if autopilot == "ardupilot":
        return (
            FenceParam("FENCE_TYPE", AP_FENCE_ALT_MAX | AP_FENCE_POLYGON, PARAM_INT),
            FenceParam("FENCE_ALT_MAX", ceiling),
            FenceParam("FENCE_ACTION", AP_FENCE_ACTION[action], PARAM_INT),
            FenceParam("FENCE_ENABLE", 1, PARAM_INT),
        )
    return (
        FenceParam("GF_MAX_VER_DIST", ceiling),
        FenceParam("GF_ACTION", PX4_GF_ACTION[action], PARAM_INT),
    )


def _with_floor(
    params: tuple[FenceParam, ...], floor_above_home_m: float
) -> tuple[FenceParam, ...]:
    out = []
    for param in params:
        if param.name == "FENCE_TYPE":
            param = FenceParam(param.name, int(param.value) | AP_FENCE_ALT_MIN, param.param_type)
        if param.name == "FENCE_ENABLE":
            out.append(FenceParam("FENCE_ALT_MIN", round(floor_above_home_m, 2)))
        out.append(param)
    return tuple(out)


def _ring(coords: Iterable[Sequence[float]]) -> list[tuple[float, float]]:
    """A shapely ring's corners, without the closing repeat of the first."""
    points = [(float(c[0]), float(c[1])) for c in coords]
    if len(points) > 1 and points[0] == points[-1]:
        points.pop()
    return points


def _deg_e7(deg: float) -> int:
    return round(deg * 1e7)


def _check_home(envelope: Envelope, frame: FrameConfig) -> None:
    """FenceError when home (NED origin) lies outside the inclusion or inside an exclusion's
    footprint (or a hole of the inclusion), where the autopilot's 2-D fence forbids it."""
    x_m, y_m = -frame.area_origin_east_m, -frame.area_origin_north_m
    inclusion = envelope.inclusion
    if not _inside(x_m, y_m, _ring(inclusion.exterior.coords)) or any(
        _inside(x_m, y_m, _ring(hole.coords)) for hole in inclusion.interiors
    ):
        raise FenceError(
            f"home: at ({x_m:.1f}, {y_m:.1f}) m in the area frame, outside the inclusion "
            "polygon: the autopilot would refuse to arm"
        )
    for i, exclusion in enumerate(envelope.exclusions):
        if _inside(x_m, y_m, _ring(exclusion.footprint.exterior.coords)):
            raise FenceError(
                f"home: at ({x_m:.1f}, {y_m:.1f}) m, inside exclusions[{i}]'s footprint, a "
                "no-fly column in the autopilot's fence: it would refuse to arm"
            )


def _inside(x: float, y: float, ring: Sequence[tuple[float, float]]) -> bool:
    """Whether (x, y) lies inside the polygon ``ring`` (even-odd ray casting, as both
    autopilots test it; a point on an edge may fall either way)."""
    inside = False
    n = len(ring)
    for i in range(n):
        (xa, ya), (xb, yb) = ring[i], ring[(i + 1) % n]
        if (ya > y) != (yb > y) and x < xa + (y - ya) * (xb - xa) / (yb - ya):
            inside = not inside
    return inside
