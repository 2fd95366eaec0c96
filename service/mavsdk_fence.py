"""The autopilot's fence on the MAVSDK backend: MAVSDK's Geofence and Param plugins.

:func:`apply_fence_plan_mavsdk` does for :class:`~service.mavsdk_link.MavsdkLink` what
:func:`service.mission_protocol.apply_fence_plan` does on the pymavlink backend, with the same
:class:`~service.fence.FencePlan` in and the same :class:`~service.mission_protocol.FenceReport`
out: upload the polygons (``Geofence.upload_geofence``), read them back
(``Geofence.download_geofence``) and compare them item by item with
:func:`~service.fence.compare_items`, then set the parameters (the enabling one last) and read
them back with :func:`~service.fence.compare_params`.

Parameters: integers with ``Param.set_param_int`` (MAVSDK reads the parameter first to learn
its width: ArduPilot's fence integers are INT8s, sent as a float cast; PX4's INT32s, bytewise),
floats with ``set_param_float``; read back with ``get_param_int`` / ``get_param_float``. A
parameter that already has its value is not set again: ArduPilot answers a PARAM_SET that
changes nothing with a PARAM_VALUE typed REAL32, which MAVSDK 4.1 calls ``WRONG_TYPE`` for an
integer (seen on ArduCopter 4.7's SITL with ``FENCE_ACTION`` 1 set to 1).

Any step that fails raises a :class:`~service.mission_protocol.MissionError` naming it; the link
streams nothing then.

MAVSDK builds the fence mission items itself from polygons of latitude/longitude in degrees (one
``MAV_CMD_NAV_FENCE_POLYGON_VERTEX_*`` item per vertex, ``param1`` the vertex count), which is
what the plan's items are: :func:`~service.fence.item_polygons` groups them into polygons and
:func:`items_from_polygons` turns what MAVSDK reads back into items again. Circles are never
sent, and one read back is a difference.

The MAVSDK calls are blocking ones; ``run(call, what)`` executes each (the link runs it on a
worker thread while its own I/O thread keeps handing the vehicle's datagrams to MAVSDK) and
returns its result, raising MissionError when it did not finish in time.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from service.fence import (
    CMD_EXCLUSION,
    CMD_INCLUSION,
    FenceItem,
    FenceParam,
    FencePlan,
    compare_items,
    compare_params,
    item_polygons,
)
from service.mission_protocol import FenceMismatchError, FenceReport, MissionError

T = TypeVar("T")
Runner = Callable[[Callable[[], Any], str], Any]
"""``run(call, what)``: the result of the blocking MAVSDK ``call``; MissionError naming
``what`` when it does not finish in time."""


def items_from_polygons(
    polygons: Sequence[tuple[int, Sequence[tuple[float, float]]]],
) -> list[FenceItem]:
    """Fence items (one per vertex, degE7) for polygons of ``(command, [(lat, lon), ...])``."""
    return [
        FenceItem(command, len(ring), round(lat_deg * 1e7), round(lon_deg * 1e7))
        for command, ring in polygons
        for lat_deg, lon_deg in ring
    ]


def to_geofence_data(plan: FencePlan) -> Any:
    """The plan's polygons as MAVSDK's ``GeofenceData`` (no circles)."""
    from mavsdk.plugins.geofence import FenceType, GeofenceData, Point, Polygon

    kinds = {CMD_INCLUSION: FenceType.INCLUSION, CMD_EXCLUSION: FenceType.EXCLUSION}
    return GeofenceData(
        polygons=[
            Polygon([Point(it.lat_e7 / 1e7, it.lon_e7 / 1e7) for it in block], kinds[command])
            for command, block in item_polygons(plan.items)
        ],
        circles=[],
    )


def from_geofence_data(data: Any) -> tuple[list[FenceItem], int]:
    """What MAVSDK read back, as fence items, and how many circles came with them."""
    from mavsdk.plugins.geofence import FenceType

    commands = {FenceType.INCLUSION: CMD_INCLUSION, FenceType.EXCLUSION: CMD_EXCLUSION}
    polygons = [
        (
            commands.get(FenceType(int(polygon.fence_type)), -1),
            [(p.latitude_deg, p.longitude_deg) for p in polygon.points or ()],
        )
        for polygon in data.polygons or ()
    ]
    return items_from_polygons(polygons), len(data.circles or ())


def apply_fence_plan_mavsdk(geofence: Any, param: Any, plan: FencePlan, run: Runner) -> FenceReport:
    """Put ``plan`` on the autopilot through MAVSDK's ``geofence`` and ``param`` plugins (see
    the module docstring); the report as :func:`~service.mission_protocol.apply_fence_plan`'s
    (``resends`` 0: MAVSDK retries by itself and does not say). MissionError at the first step
    that fails, FenceMismatchError when what came back differs."""
    from mavsdk.plugins.geofence import GeofenceError
    from mavsdk.plugins.param import ParamError

    def call(fn: Callable[[], T], what: str) -> T:
        try:
            return run(fn, what)
        except (GeofenceError, ParamError) as exc:
            raise MissionError(f"{what}: {_reason(exc)}") from None

    data = to_geofence_data(plan)
    t0 = time.monotonic()
    call(lambda: geofence.upload_geofence(data), "fence upload")
    t1 = time.monotonic()
    got, circles = from_geofence_data(call(geofence.download_geofence, "fence download"))
    t2 = time.monotonic()
    differences = compare_items(plan.items, got)
    if circles:
        differences.insert(0, f"{circles} circles read back, none sent")
    if differences:
        raise FenceMismatchError("fence read back differs: " + "; ".join(differences[:10]))

    def read(p: FenceParam) -> float:
        getter = param.get_param_int if p.is_int else param.get_param_float
        return float(call(lambda: getter(p.name), f"reading {p.name}"))

    for p in plan.params:
        if not compare_params([p], {p.name: read(p)}):
            continue  # already so: see the module docstring
        if p.is_int:
            call(lambda p=p: param.set_param_int(p.name, int(p.value)), f"setting {p.name}")
        else:
            call(lambda p=p: param.set_param_float(p.name, float(p.value)), f"setting {p.name}")
    values = {p.name: read(p) for p in plan.params}
    if differences := compare_params(plan.params, values):
        raise FenceMismatchError("fence parameters read back differ: " + "; ".join(differences))
    t3 = time.monotonic()
    return FenceReport(
        len(plan.items),
        len(got),
        values,
        round(t1 - t0, 3),
        round(t2 - t1, 3),
        round(t3 - t2, 3),
        0,
        (),
    )


def _reason(exc: Exception) -> str:
    """MAVSDK's error as one short line: its result's name (``TIMEOUT``, ``WRONG_TYPE``...)."""
    name = getattr(getattr(exc, "result", None), "name", None)
    return str(name) if name else str(exc).splitlines()[0]
