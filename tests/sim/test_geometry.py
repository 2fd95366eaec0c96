"""The zone grid's functions: their fast paths give exactly what the numpy formulas give."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.config import AreaConfig
from sim.geometry import MOVES, grid_shape, move_mask, zone_index, zone_position

AREAS = (
    AreaConfig(),
    AreaConfig(size_x_m=300.0, size_y_m=200.0, zone_m=20.0, z_min_m=20.0, z_max_m=120.0),
)


def reference_zone_index(xyz_m, area: AreaConfig) -> np.ndarray:
    raw = np.array(
        [
            np.floor(xyz_m[0] / area.zone_m),
            np.floor(xyz_m[1] / area.zone_m),
            np.rint((xyz_m[2] - area.z_min_m) / area.zone_m),
        ]
    ).astype(np.int64)
    return np.clip(raw, 0, grid_shape(area) - 1)


def reference_zone_position(index, area: AreaConfig) -> np.ndarray:
    return np.array(
        [
            (index[0] + 0.5) * area.zone_m,
            (index[1] + 0.5) * area.zone_m,
            area.z_min_m + index[2] * area.zone_m,
        ]
    )


def reference_move_mask(index, area: AreaConfig) -> np.ndarray:
    landing = np.asarray(index) + MOVES
    return np.all((landing >= 0) & (landing < grid_shape(area)), axis=1)


def assert_same(a: np.ndarray, b: np.ndarray) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    np.testing.assert_array_equal(a, b)


coordinate = st.floats(-200.0, 800.0) | st.sampled_from([0.0, 12.5, 25.0, 37.5, 62.5, 500.0])


@settings(max_examples=300, deadline=None)
@given(x=coordinate, y=coordinate, z=coordinate, area=st.sampled_from(AREAS))
def test_zone_index_matches_the_numpy_formula(x, y, z, area):
    """Half-way altitudes round to even, as np.rint does; off-grid points clip."""
    xyz = np.array([x, y, z])
    assert_same(zone_index(xyz, area), reference_zone_index(xyz, area))
    assert_same(zone_index([x, y, z], area), reference_zone_index([x, y, z], area))


@settings(max_examples=300, deadline=None)
@given(
    index=st.tuples(st.integers(-8, 30), st.integers(-8, 30), st.integers(-8, 12)),
    area=st.sampled_from(AREAS),
)
def test_move_mask_and_zone_position_match_the_numpy_formulas(index, area):
    for form in (np.array(index), np.array(index, dtype=np.int32), list(index), index):
        assert_same(move_mask(form, area), reference_move_mask(form, area))
        assert_same(zone_position(form, area), reference_zone_position(form, area))
    as_float = np.array(index, dtype=float)
    assert_same(zone_position(as_float, area), reference_zone_position(as_float, area))


def test_move_mask_is_a_fresh_array_each_call():
    """Masks are cached per index: callers must still be free to change the one they get."""
    index = np.array([0, 0, 0])
    first = move_mask(index, AREAS[0])
    first[:] = False
    assert move_mask(index, AREAS[0])[0]


def test_zone_index_of_non_finite_positions_is_numpy_s():
    with np.errstate(invalid="ignore"):
        for bad in ([np.nan, 10.0, 30.0], [np.inf, 10.0, 30.0], [1e300, -1e300, 30.0]):
            xyz = np.array(bad)
            assert_same(zone_index(xyz, AREAS[0]), reference_zone_index(xyz, AREAS[0]))
