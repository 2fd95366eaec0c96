"""Frame conversions (area <-> local NED <-> global) and the geofence: property tests both ways."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from service.frames import (
    FrameConfig,
    GeoPoint,
    area_to_global,
    area_to_ned,
    frame_config_from_geodetic,
    global_to_area,
    global_to_ned,
    ned_to_area,
    ned_to_global,
)
from sim.config import AreaConfig
from sim.geometry import clamp_point

offsets = st.floats(-5000.0, 5000.0, allow_nan=False)
configs = st.builds(FrameConfig, offsets, offsets, st.floats(-200.0, 200.0))
homes = st.builds(
    GeoPoint, st.floats(-80.0, 80.0), st.floats(-179.0, 179.0), st.floats(-100.0, 4000.0)
)
TOL_M = 1e-6


def close(a: tuple[float, ...], b: tuple[float, ...], tol: float = TOL_M) -> bool:
    return all(abs(p - q) <= tol for p, q in zip(a, b, strict=True))


def test_axes_point_the_right_way():
    config = FrameConfig(area_origin_north_m=-100.0, area_origin_east_m=-50.0)
    # 10 m east, 20 m north, 30 m up of the corner.
    assert area_to_ned(10.0, 20.0, 30.0, config) == (-80.0, -40.0, -30.0)
    # Home (0, 0, 0 NED) lies 50 m east and 100 m north of the corner, at z = 0.
    assert ned_to_area(0.0, 0.0, 0.0, config) == (50.0, 100.0, 0.0)
    # Home 2 m above the area's ground: z = 0 is 2 m below home.
    assert area_to_ned(0.0, 0.0, 0.0, FrameConfig(area_origin_down_m=2.0)) == (0.0, 0.0, 2.0)


def test_global_offsets_match_the_usual_scale():
    home = GeoPoint(47.397742, 8.545594, 488.0)
    point = ned_to_global(home, 111.319_490_8, 0.0, -10.0)
    assert point.lat_deg == pytest.approx(home.lat_deg + 0.001, abs=1e-9)
    assert point.alt_amsl_m == pytest.approx(498.0)
    east = ned_to_global(home, 0.0, 100.0, 0.0)
    expected_deg = math.degrees(100.0 / (6_378_137.0 * math.cos(math.radians(home.lat_deg))))
    assert east.lon_deg - home.lon_deg == pytest.approx(expected_deg)


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="area_origin_east_m"):
        FrameConfig(area_origin_east_m=math.nan)


@given(configs, offsets, offsets, st.floats(-200.0, 500.0))
def test_area_ned_round_trip(config, x_m, y_m, z_m):
    assert close(ned_to_area(*area_to_ned(x_m, y_m, z_m, config), config), (x_m, y_m, z_m))
    assert close(area_to_ned(*ned_to_area(x_m, y_m, z_m, config), config), (x_m, y_m, z_m))


@given(homes, offsets, offsets, st.floats(-500.0, 500.0))
def test_ned_global_round_trip(home, north_m, east_m, down_m):
    point = ned_to_global(home, north_m, east_m, down_m)
    assert close(global_to_ned(home, point), (north_m, east_m, down_m))


@given(homes, configs, offsets, offsets, st.floats(0.0, 500.0))
def test_area_global_round_trip(home, config, x_m, y_m, z_m):
    point = area_to_global(home, x_m, y_m, z_m, config)
    assert close(global_to_area(home, point, config), (x_m, y_m, z_m))


@given(homes, offsets, offsets, st.floats(-50.0, 50.0))
def test_frame_config_from_geodetic_puts_the_corner_at_zero(home, north_m, east_m, down_m):
    corner = ned_to_global(home, north_m, east_m, down_m)
    config = frame_config_from_geodetic(home, corner)
    assert close(global_to_area(home, corner, config), (0.0, 0.0, 0.0))


# ---------------------------------------------------------------- geofence

AREA = AreaConfig(size_x_m=100.0, size_y_m=50.0, zone_m=5.0, z_min_m=5.0, z_max_m=20.0)


@given(st.tuples(*[st.floats(-1e9, 1e9, allow_nan=False)] * 3))
def test_nothing_leaves_the_fence(target):
    (x_m, y_m, z_m), was_clamped = clamp_point(target, AREA)
    assert 0.0 <= x_m <= AREA.size_x_m
    assert 0.0 <= y_m <= AREA.size_y_m
    assert AREA.z_min_m <= z_m <= AREA.z_max_m
    assert was_clamped == ((x_m, y_m, z_m) != tuple(target))


def test_a_point_inside_is_untouched_and_non_finite_is_refused():
    assert clamp_point((10.0, 20.0, 15.0), AREA) == ((10.0, 20.0, 15.0), False)
    assert clamp_point((-1.0, 60.0, 1.0), AREA) == ((0.0, 50.0, 5.0), True)
    for bad in ((math.nan, 0.0, 10.0), (0.0, math.inf, 10.0), (0.0, 0.0, -math.inf)):
        with pytest.raises(ValueError, match="finite"):
            clamp_point(bad, AREA)
    with pytest.raises(ValueError):
        clamp_point((1.0, 2.0), AREA)
