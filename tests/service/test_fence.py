"""The envelope as the autopilot's fence (service/fence.py): items, parameters, the round trip
area -> degE7 -> area, the read-back comparisons, and the full-height exclusions."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from shapely.geometry import Point, Polygon

from service.fence import (
    CMD_EXCLUSION,
    CMD_INCLUSION,
    FenceError,
    FenceItem,
    FenceParam,
    compare_items,
    compare_params,
    fence_compatible,
    fence_plan,
    items_to_area,
    plan_summary,
)
from service.frames import FrameConfig, GeoPoint
from sim.config import AreaConfig
from sim.envelope import Envelope, Exclusion, plan_path

CMAC = GeoPoint(-35.363261, 149.165230, 584.0)
ZURICH = GeoPoint(47.397742, 8.545594, 488.0)
HELIPAD = Exclusion(Polygon([(100, 100), (160, 100), (160, 150), (100, 150)]), 0.0, 60.0, "pad")
TOWER = Exclusion(Polygon([(300, 300), (340, 300), (320, 360)]), 0.0, 90.0, "tower")


def area_envelope(*exclusions: Exclusion, clearance_m: float = 0.0) -> Envelope:
    return Envelope.for_area(AreaConfig(), exclusions, clearance_m=clearance_m)


def test_items_follow_the_polygons_in_order():
    plan = fence_plan(area_envelope(HELIPAD, TOWER), CMAC)
    assert [i.command for i in plan.items] == [CMD_INCLUSION] * 4 + [CMD_EXCLUSION] * 7
    assert [i.vertex_count for i in plan.items] == [4] * 8 + [3] * 3
    assert {i.frame for i in plan.items} == {mavlink.MAV_FRAME_GLOBAL}
    assert plan.polygons == 3
    # The area's south-west corner is home (default frame): the first vertex is home itself.
    assert (plan.items[0].lat_e7, plan.items[0].lon_e7) == (-353632610, 1491652300)
    # The corner 500 m east of it: same latitude, larger longitude.
    assert plan.items[1].lat_e7 == plan.items[0].lat_e7
    assert plan.items[1].lon_e7 > plan.items[0].lon_e7
    assert any("a no-fly column at every height" in note for note in plan.notes)


def test_constants_are_mavlinks():
    assert CMD_INCLUSION == 5001 == mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
    assert CMD_EXCLUSION == 5002 == mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION


def test_parameters_per_autopilot():
    frame = FrameConfig(area_origin_down_m=2.0)  # home 2 m above the area's ground
    ap = fence_plan(area_envelope(), CMAC, frame, "ardupilot", "rtl")
    assert [(p.name, p.value) for p in ap.params] == [
        ("FENCE_TYPE", 5),
        ("FENCE_ALT_MAX", 100.0),  # ceiling 100 - 2 m below home... + 2 m margin
        ("FENCE_ACTION", 1),
        ("FENCE_ENABLE", 1),
    ]
    assert ap.ceiling_above_home_m == pytest.approx(100.0)
    px4 = fence_plan(area_envelope(), ZURICH, frame, "px4", "hold", ceiling_margin_m=5.0)
    assert [(p.name, p.value) for p in px4.params] == [("GF_MAX_VER_DIST", 103.0), ("GF_ACTION", 2)]
    assert [p.is_int for p in px4.params] == [False, True]
    assert {p.name: p.value for p in fence_plan(area_envelope(), ZURICH, None, "px4").params}[
        "GF_ACTION"
    ] == 3
    land = fence_plan(area_envelope(), CMAC, action="land")
    assert land.params[2] == FenceParam("FENCE_ACTION", 2, mavlink.MAV_PARAM_TYPE_INT32)


def test_floor_only_where_asked_and_supported():
    envelope = area_envelope()  # floor 25 m
    ap = fence_plan(envelope, CMAC, include_floor=True)
    values = {p.name: p.value for p in ap.params}
    assert values["FENCE_TYPE"] == 1 | 4 | 8
    assert values["FENCE_ALT_MIN"] == 23.0
    assert ap.params[-1].name == "FENCE_ENABLE"  # still enabled last
    px4 = fence_plan(envelope, ZURICH, autopilot="px4", include_floor=True)
    assert "GF_MAX_VER_DIST" in {p.name for p in px4.params}
    assert any("PX4 has no floor fence" in note for note in px4.notes)


def test_inclusion_holes_become_exclusions():
    outer = [(0, 0), (500, 0), (500, 500), (0, 500)]
    hole = [(200, 200), (260, 200), (260, 260), (200, 260)]
    envelope = Envelope(Polygon(outer, [hole]), 25.0, 100.0)
    plan = fence_plan(envelope, CMAC)
    polygons = items_to_area(plan.items, CMAC)
    assert [command for command, _ in polygons] == [CMD_INCLUSION, CMD_EXCLUSION]
    assert len(polygons[1][1]) == 4


homes = st.builds(
    GeoPoint, st.floats(-70.0, 70.0), st.floats(-179.0, 179.0), st.floats(-100.0, 4000.0)
)
offsets_m = st.floats(-2000.0, 0.0)


@settings(max_examples=200, deadline=None)
@given(
    home=homes,
    north_m=offsets_m,
    east_m=offsets_m,
    corners=st.lists(
        st.tuples(st.floats(0, 3000), st.floats(0, 3000)), min_size=3, max_size=12, unique=True
    ),
)
def test_round_trip_within_a_centimetre(home, north_m, east_m, corners):
    """Area -> degE7 -> area comes back within 1 cm, anywhere up to a few km from home."""
    frame = FrameConfig(area_origin_north_m=north_m, area_origin_east_m=east_m)
    hull = Polygon(corners).convex_hull
    if hull.geom_type != "Polygon" or hull.area < 1.0:
        return
    inclusion = Polygon([(-1, -1), (4001, -1), (4001, 4001), (-1, 4001)])
    home_xy = (-east_m, -north_m)
    if hull.buffer(1.0).contains(Point(home_xy)):
        return
    envelope = Envelope(inclusion, 0.0, 100.0, (Exclusion(hull, 0.0, 50.0),))
    plan = fence_plan(envelope, home, frame)
    back = items_to_area(plan.items, home, frame)
    originals = [list(inclusion.exterior.coords)[:-1], list(hull.exterior.coords)[:-1]]
    for (_, ring), original in zip(back, originals, strict=True):
        assert len(ring) == len(original)
        for a, b in zip(ring, original, strict=True):
            assert math.dist(a, b) < 0.01


def test_bad_input_names_the_field():
    with pytest.raises(FenceError, match=r"^home: .* inside exclusions\[0\]"):
        fence_plan(area_envelope(HELIPAD), CMAC, FrameConfig(-120.0, -120.0))
    with pytest.raises(FenceError, match=r"^home: .* outside the inclusion"):
        fence_plan(area_envelope(), CMAC, FrameConfig(100.0, 0.0))
    many = Polygon(
        [(250 + 200 * math.cos(a / 50), 250 + 200 * math.sin(a / 50)) for a in range(315)]
    )
    with pytest.raises(FenceError, match=r"^inclusion: 315 vertices"):
        fence_plan(Envelope(many, 25.0, 100.0), CMAC, FrameConfig(-250.0, -250.0))
    with pytest.raises(FenceError, match=r"^autopilot:"):
        fence_plan(area_envelope(), CMAC, autopilot="inav")  # type: ignore[arg-type]
    with pytest.raises(FenceError, match=r"^action:"):
        fence_plan(area_envelope(), CMAC, action="loiter")  # type: ignore[arg-type]
    with pytest.raises(FenceError, match=r"^ceiling_margin_m:"):
        fence_plan(area_envelope(), CMAC, ceiling_margin_m=-1.0)
    with pytest.raises(FenceError, match=r"^ceiling_m: .* must be above home"):
        fence_plan(area_envelope(), CMAC, FrameConfig(area_origin_down_m=150.0))
    with pytest.raises(FenceError, match=r"^home:"):
        fence_plan(area_envelope(), GeoPoint(math.nan, 0.0, 0.0))


def test_comparisons():
    plan = fence_plan(area_envelope(HELIPAD), CMAC)
    items = list(plan.items)
    assert compare_items(plan.items, items) == []
    nudged = [FenceItem(i.command, i.vertex_count, i.lat_e7 + 1, i.lon_e7 - 1) for i in items]
    assert compare_items(plan.items, nudged) == []  # 1 degE7 is within tolerance
    moved = [*items[:3], FenceItem(CMD_INCLUSION, 4, items[3].lat_e7 + 2, items[3].lon_e7)]
    assert compare_items(plan.items, [*moved, *items[4:]]) == [
        f"item 3: at {items[3].lat_e7 + 2}, {items[3].lon_e7} degE7, sent "
        f"{items[3].lat_e7}, {items[3].lon_e7}"
    ]
    assert compare_items(plan.items, items[:-1])[0] == "7 items read back, 8 sent"
    swapped = [FenceItem(CMD_EXCLUSION, 4, i.lat_e7, i.lon_e7) for i in items[:1]] + items[1:]
    assert compare_items(plan.items, swapped) == ["item 0: exclusion read back, inclusion sent"]
    values = {p.name: p.value for p in plan.params}
    assert compare_params(plan.params, values) == []
    assert compare_params(plan.params, {**values, "FENCE_ALT_MAX": 102.004}) == []
    assert compare_params(plan.params, {**values, "FENCE_ALT_MAX": 102.5}) == [
        "FENCE_ALT_MAX: 102.5 read back, 102 set"
    ]
    assert compare_params(plan.params, {**values, "FENCE_ACTION": 0.0}) == [
        "FENCE_ACTION: 0 read back, 1 set"
    ]
    del values["FENCE_ENABLE"]
    assert compare_params(plan.params, values) == ["FENCE_ENABLE: not read back"]
    summary = plan_summary(plan)
    assert summary["items"] == 8 and summary["params"]["FENCE_ENABLE"] == 1


def test_fence_compatible_plans_no_route_over_an_exclusion():
    """With a low exclusion the envelope climbs over it; the fence-compatible one, whose
    exclusions are columns as on the autopilot, never does."""
    low = Exclusion(Polygon([(200, 0), (260, 0), (260, 500), (200, 500)]), 0.0, 40.0, "wall")
    envelope = Envelope.for_area(AreaConfig(), [low], clearance_m=5.0)
    start, goal = (100.0, 250.0, 30.0), (400.0, 250.0, 30.0)
    over = plan_path(envelope, start, goal)
    assert any(point[2] > 45.0 for point in getattr(over, "waypoints", ())), over
    compatible = fence_compatible(envelope)
    assert compatible.exclusions[0].floor_m < compatible.floor_m
    assert compatible.exclusions[0].ceiling_m > compatible.ceiling_m
    assert compatible.violation((230.0, 250.0, 90.0)) is not None  # above the wall
    assert envelope.violation((230.0, 250.0, 90.0)) is None
    blocked = plan_path(compatible, start, goal)
    assert not hasattr(blocked, "waypoints") or all(
        compatible.segment_violation(a, b) is None
        for a, b in zip(blocked.waypoints, blocked.waypoints[1:], strict=False)
    )
    assert envelope.exclusions[0].ceiling_m == 40.0  # the original is unchanged


def test_a_sites_buildings_stay_off_the_autopilots_fence_and_keep_their_heights():
    """Over munich the fence holds the inclusion and the document's own no-fly volume only;
    the routes planned for the fence keep that one as a column and the buildings at their
    heights (a low roof may still be flown over)."""
    from sim.envelope.files import envelope_from_document

    area = AreaConfig(environment="site:munich")
    mast = {"name": "mast", "polygon": [[20, 20], [40, 20], [40, 40], [20, 40]],
            "floor_m": 0, "ceiling_m": 30}  # fmt: skip
    envelope = envelope_from_document({"format": "tupa-envelope/1", "exclusions": [mast]}, area)
    buildings = [e for e in envelope.exclusions if not e.on_autopilot_fence]
    assert len(buildings) == len(envelope.exclusions) - 1 > 10
    plan = fence_plan(envelope, CMAC)
    assert plan.polygons == 2  # the inclusion and the mast
    assert [i.vertex_count for i in plan.items] == [4] * 8
    compatible = fence_compatible(envelope)
    assert compatible.exclusions[0].ceiling_m > compatible.ceiling_m  # the mast: a column
    assert compatible.exclusions[1:] == envelope.exclusions[1:]  # the buildings: as they are
