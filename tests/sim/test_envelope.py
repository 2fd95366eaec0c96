"""The flight-safety envelope (:mod:`sim.envelope`): legal targets and paths, and its file.

The property tests check every returned target and path with a test of their own: points
sampled every :data:`STEP_M` along each leg, each held to the envelope with plain shapely
distances (inside the inclusion by at least the clearance, within the altitude band, and at
least the clearance from every exclusion volume), not with the module's prepared geometry.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st
from shapely.geometry import Polygon, box

from sim.config import AreaConfig
from sim.envelope import (
    Envelope,
    Exclusion,
    FlightPath,
    Hold,
    envelope_from_document,
    legal_target,
    load_envelope,
    plan_path,
)
from sim.errors import InputError

AREA = AreaConfig(size_x_m=200.0, size_y_m=200.0, zone_m=25.0, z_min_m=25.0, z_max_m=100.0)
STEP_M = 0.25
TOL_M = 1e-3


def independent_violations(envelope: Envelope, points: np.ndarray) -> list[str]:
    """What breaks the envelope at each of ``points`` (N, 3), by plain distances."""
    c = envelope.clearance_m
    xy = shapely.points(points[:, :2])
    problems = []
    z = points[:, 2]
    if np.any(z < envelope.floor_m - TOL_M) or np.any(z > envelope.ceiling_m + TOL_M):
        problems.append("altitude")
    outside_by = shapely.distance(envelope.inclusion, xy)  # 0 inside
    margin = shapely.distance(envelope.inclusion.exterior, xy)
    if not np.all((outside_by <= TOL_M) & (margin >= c - TOL_M)):
        problems.append("inclusion")
    for exclusion in envelope.exclusions:
        in_band = (z > exclusion.floor_m - c + TOL_M) & (z < exclusion.ceiling_m + c - TOL_M)
        near = shapely.distance(exclusion.footprint, xy) < c - TOL_M
        inside_footprint = shapely.contains(exclusion.footprint, xy)
        if np.any(in_band & (near | inside_footprint)):
            problems.append(f"exclusion {exclusion.name}")
    return problems


def sampled(start: tuple[float, ...], path: FlightPath) -> np.ndarray:
    """Points every :data:`STEP_M` along each leg flown straight, and along both ways an
    autopilot that reaches height and position at separate speeds may fly it instead (height
    first, or position first: every path it flies lies between those)."""
    legs = [start, *path.waypoints]
    points = []
    for a, b in itertools.pairwise(legs):
        height_first = (a[0], a[1], b[2])
        position_first = (b[0], b[1], a[2])
        for piece in ((a, b), (a, height_first), (height_first, b), (a, position_first),
                      (position_first, b)):  # fmt: skip
            n = max(2, math.ceil(math.dist(*piece) / STEP_M) + 1)
            points.append(np.linspace(*piece, n))
    return np.concatenate(points)


@st.composite
def envelopes(draw: st.DrawFn) -> Envelope:
    exclusions = []
    for i in range(draw(st.integers(0, 6))):
        x = draw(st.floats(0, 180))
        y = draw(st.floats(0, 180))
        w = draw(st.floats(5, 60))
        h = draw(st.floats(5, 60))
        floor_m = draw(st.sampled_from([0.0, 20.0, 40.0]))
        ceiling_m = floor_m + draw(st.floats(10, 100))
        exclusions.append(Exclusion(box(x, y, x + w, y + h), floor_m, ceiling_m, f"x{i}"))
    clearance = draw(st.sampled_from([0.0, 2.0, 5.0]))
    return Envelope.for_area(AREA, exclusions, clearance_m=clearance)


points3 = st.tuples(st.floats(-20, 220), st.floats(-20, 220), st.floats(0, 130))


@settings(max_examples=300, deadline=None)
@given(envelope=envelopes(), start=points3, goal=points3)
def test_targets_and_paths_never_leave_the_envelope(
    envelope: Envelope, start: tuple[float, ...], goal: tuple[float, ...]
) -> None:
    here = legal_target(envelope, start)
    there = legal_target(envelope, goal)
    for point in (here, there):
        if point is not None:
            assert independent_violations(envelope, np.array([point])) == []
            assert envelope.violation(point) is None
    if here is None or there is None:
        return
    path = plan_path(envelope, here, there)
    if isinstance(path, Hold):
        assert path.reason
        return
    assert path.waypoints[-1] == pytest.approx(there)
    assert independent_violations(envelope, sampled(here, path)) == []


def test_a_straight_line_through_a_tower_goes_around_or_over() -> None:
    tower = Exclusion(box(80, 80, 120, 120), 0.0, 60.0, "tower")
    envelope = Envelope.for_area(AREA, [tower], clearance_m=5.0)
    assert "tower" in (envelope.segment_violation((50, 100, 40), (150, 100, 40)) or "")
    path = plan_path(envelope, (50, 100, 40), (150, 100, 40))
    assert isinstance(path, FlightPath) and path.kind in ("over", "around")
    # Over it costs 2 x 26 m of climb and descent; around it less: the shorter is chosen.
    assert path.kind == "around" and path.length_m < 100 + 2 * 26
    # A mast to the ceiling: only around.
    mast = Exclusion(box(80, 80, 120, 120), 0.0, 200.0, "mast")
    around = plan_path(Envelope.for_area(AREA, [mast], 5.0), (50, 100, 90), (150, 100, 90))
    assert isinstance(around, FlightPath) and around.kind == "around"
    # A wide low block: over it.
    block = Exclusion(box(60, 0, 140, 200), 0.0, 30.0, "block")
    over = plan_path(Envelope.for_area(AREA, [block], 5.0), (50, 100, 30), (150, 100, 30))
    assert isinstance(over, FlightPath) and over.kind == "over"
    assert max(w[2] for w in over.waypoints) == pytest.approx(36.0)


def test_a_climb_that_an_autopilot_would_fly_into_a_volume_goes_up_first() -> None:
    """The straight line climbs under the volume, but an autopilot reaching its position
    before its height would fly into it: the leg is split, height first."""
    roof = Exclusion(box(40, 90, 60, 110), 45.0, 55.0, "bridge")
    envelope = Envelope.for_area(AREA, [roof])
    start, target = (20.0, 100.0, 30.0), (180.0, 100.0, 70.0)
    assert envelope.segment_violation(start, target) is None
    assert "may cross exclusion 'bridge'" in (envelope.leg_violation(start, target) or "")
    path = plan_path(envelope, start, target)
    assert isinstance(path, FlightPath)
    assert path.waypoints == ((20.0, 100.0, 70.0), target)
    assert independent_violations(envelope, sampled(start, path)) == []


def test_no_way_through_a_wall_is_a_hold_that_says_why() -> None:
    wall = Exclusion(box(90, 0, 110, 200), 0.0, 500.0, "wall")
    envelope = Envelope.for_area(AREA, [wall])
    path = plan_path(envelope, (50, 100, 50), (150, 100, 50))
    assert isinstance(path, Hold) and "no legal path" in path.reason
    outside = plan_path(envelope, (100, 100, 50), (150, 100, 50))
    assert isinstance(outside, Hold) and "outside its envelope" in outside.reason


def test_an_illegal_target_moves_to_the_nearest_legal_point() -> None:
    tower = Exclusion(box(80, 80, 120, 120), 0.0, 60.0, "tower")
    envelope = Envelope.for_area(AREA, [tower], clearance_m=5.0)
    assert legal_target(envelope, (30, 30, 50)) == (30, 30, 50)
    assert legal_target(envelope, (30, 30, 500)) == (30, 30, 100)  # the ceiling
    # Near the tower's top: over it is nearer than out to its side.
    assert legal_target(envelope, (100, 100, 60)) == pytest.approx((100, 100, 66))
    # Low, at its edge: out to the side.
    x, _y, z = legal_target(envelope, (82, 100, 30))
    assert z == 30 and x == pytest.approx(80 - 5 - 0.5)
    # Outside the inclusion: onto the edge of what the clearance leaves (legal, and nearest).
    assert legal_target(envelope, (-50, 100, 50)) == pytest.approx((5.0, 100, 50))
    assert legal_target(envelope, (math.nan, 1, 1)) is None


def test_a_file_is_loaded_with_its_defaults(tmp_path: Path) -> None:
    path = tmp_path / "envelope.json"
    path.write_text(
        json.dumps(
            {
                "format": "tupa-envelope/1",
                "clearance_m": 5,
                "exclusions": [
                    {"name": "helipad", "polygon": [[10, 10], [40, 10], [40, 40]], "ceiling_m": 60}
                ],
            }
        )
    )
    envelope = load_envelope(path, AREA)
    assert envelope.floor_m == 25.0 and envelope.ceiling_m == 100.0
    assert envelope.inclusion.equals(box(0, 0, 200, 200))
    assert envelope.exclusions[0].name == "helipad" and envelope.exclusions[0].floor_m == 0.0
    assert envelope.max_speed_mps == 10.0


def doc(**fields: Any) -> dict[str, Any]:
    return {"format": "tupa-envelope/1", **fields}


BOWTIE = [[0, 0], [100, 100], [100, 0], [0, 100]]


@pytest.mark.parametrize(
    ("document", "message"),
    [
        ([], "not a JSON object"),
        ({"format": "x"}, "format: must be 'tupa-envelope/1'"),
        (doc(extra=1), "extra: unknown field"),
        (doc(inclusion=BOWTIE), "inclusion: not a simple polygon (Self-intersection"),
        (doc(inclusion=[[0, 0], [300, 0], [300, 300]]), "inclusion: extends outside the area"),
        (doc(inclusion=[[0, 0], [1, 1], [2, 2]]), "inclusion: has no area"),
        (doc(inclusion=[[0, 0], [1, "a"], [2, 0]]), "inclusion[1]: must be [x, y]"),
        (doc(floor_m=50, ceiling_m=40), "ceiling_m: 40 m must be above floor_m 50 m"),
        (doc(clearance_m=-1), "clearance_m: must be at least 0"),
        (doc(clearance_m=150), "clearance_m: 150 m leaves nothing"),
        (doc(max_speed_mps=0), "max_speed_mps: must be a positive number"),
        (doc(floor_m=float("nan")), "floor_m: must be a finite number"),
        (doc(exclusions={}), "exclusions: must be a list"),
        (
            doc(exclusions=[{"polygon": [[0, 0], [9, 0], [9, 9]] * 167, "ceiling_m": 9}] * 2),
            "exclusions: 1002 corners in all, at most 1000",
        ),
        (doc(exclusions=[{"polygon": BOWTIE, "ceiling_m": 9}]), "exclusions[0].polygon: not a"),
        (
            doc(exclusions=[{"polygon": [[0, 0], [9, 0], [9, 9]]}]),
            "exclusions[0].ceiling_m: missing",
        ),
        (
            doc(exclusions=[{"polygon": [[0, 0], [9, 0], [9, 9]], "floor_m": 5, "ceiling_m": 5}]),
            "exclusions[0].ceiling_m: 5 m must be above floor_m 5 m",
        ),
        (
            doc(
                exclusions=[
                    {"polygon": [[-1, -1], [201, -1], [201, 201], [-1, 201]], "ceiling_m": 999}
                ]
            ),
            "exclusions[0]: with the clearance, the exclusions cover the whole inclusion",
        ),
        (
            doc(exclusions=[{"polygon": [[0, 0], [9, 0], [9, 9]], "ceiling_m": 9, "x": 1}]),
            "exclusions[0].x",
        ),
    ],
)
def test_an_unflyable_envelope_is_refused_naming_the_field(document: Any, message: str) -> None:
    with pytest.raises(InputError) as error:
        envelope_from_document(document, AREA)
    assert message in str(error.value)
    assert "\n" not in str(error.value)


def test_a_bad_file_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="cannot read the envelope file"):
        load_envelope(tmp_path / "missing.json", AREA)
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    with pytest.raises(InputError, match=r"broken\.json: not JSON"):
        load_envelope(broken, AREA)


def test_the_default_envelope_is_the_area_box() -> None:
    envelope = Envelope.for_area(AREA)
    assert isinstance(envelope.inclusion, Polygon) and envelope.inclusion.area == 200 * 200
    assert envelope.violation((0, 0, 25)) is None
    assert "below the floor" in (envelope.violation((10, 10, 24)) or "")
    assert "outside the inclusion" in (envelope.violation((-1, 10, 50)) or "")
