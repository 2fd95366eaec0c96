"""The fence plan as MAVSDK's geofence data and back (service/mavsdk_fence.py): the polygons
MAVSDK uploads are the plan's, vertex for vertex, and what it reads back compares as the
pymavlink backend's items do. The upload itself, over real MAVSDK to the mock autopilot, is
tests/service/test_link_fence.py's."""

from __future__ import annotations

from shapely.geometry import box

from service.fence import CMD_EXCLUSION, CMD_INCLUSION, FencePlan, compare_items, fence_plan
from service.frames import GeoPoint
from service.mavsdk_fence import from_geofence_data, to_geofence_data
from sim.config import AreaConfig
from sim.envelope import Envelope, Exclusion

HOME = GeoPoint(47.397742, 8.545594, 488.0)


def _plan() -> FencePlan:
    envelope = Envelope.for_area(
        AreaConfig(size_x_m=200, size_y_m=200, z_max_m=100),
        [Exclusion(box(50, 50, 80, 90), 0.0, 40.0, "mast"), Exclusion(box(120, 20, 140, 30), 0, 9)],
    )
    return fence_plan(envelope, HOME, autopilot="px4")


def test_the_geofence_data_holds_the_plans_polygons_in_order() -> None:
    plan = _plan()
    data = to_geofence_data(plan)
    assert [int(p.fence_type) for p in data.polygons] == [0, 1, 1]  # inclusion, 2 exclusions
    assert [len(p.points) for p in data.polygons] == [4, 4, 4]
    assert data.circles == []
    first = plan.items[0]
    assert data.polygons[0].points[0].latitude_deg == first.lat_e7 / 1e7
    assert data.polygons[0].points[0].longitude_deg == first.lon_e7 / 1e7


def test_what_comes_back_compares_equal_and_a_moved_vertex_or_a_circle_does_not() -> None:
    from mavsdk.plugins.geofence import Circle, FenceType, Point

    plan = _plan()
    data = to_geofence_data(plan)
    items, circles = from_geofence_data(data)
    assert circles == 0 and compare_items(plan.items, items) == []
    assert [i.command for i in items[:5]] == [CMD_INCLUSION] * 4 + [CMD_EXCLUSION]
    data.polygons[1].points[2] = Point(data.polygons[1].points[2].latitude_deg + 1e-5, 8.5)
    items, _ = from_geofence_data(data)
    assert compare_items(plan.items, items) == [
        f"item 6: at {items[6].lat_e7}, {items[6].lon_e7} degE7, "
        f"sent {plan.items[6].lat_e7}, {plan.items[6].lon_e7}"
    ]
    data.circles = [Circle(Point(47.4, 8.5), 10.0, FenceType.EXCLUSION)]
    assert from_geofence_data(data)[1] == 1
