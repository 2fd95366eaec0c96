"""The zone grid the discrete policy moves on, as pure functions shared by training and serving.

The area is cut into ``zone_m`` squares (20 × 20 for the paper's 500 m area and 25 m zones) and
``n_levels_z`` altitude levels ``zone_m`` apart from ``z_min_m``. A grid index ``(ix, iy, iz)``
stands for the point at the centre of zone ``(ix, iy)``, at altitude ``z_min_m + iz · zone_m``.
The 13 discrete moves (:data:`MOVES`) step the index by ±1 or ±5 along one axis, or stay.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from sim.config import AreaConfig

# (dx, dy, dz) in zones for each discrete action; index 0 is "stay".
MOVES: np.ndarray = np.array(
    [
        (0, 0, 0),
        (1, 0, 0),
        (-1, 0, 0),
        (0, 1, 0),
        (0, -1, 0),
        (0, 0, 1),
        (0, 0, -1),
        (5, 0, 0),
        (-5, 0, 0),
        (0, 5, 0),
        (0, -5, 0),
        (0, 0, 5),
        (0, 0, -5),
    ],
    dtype=np.int64,
)
MOVE_NAMES: tuple[str, ...] = (
    "stay",
    "east 1",
    "west 1",
    "north 1",
    "south 1",
    "up 1",
    "down 1",
    "east 5",
    "west 5",
    "north 5",
    "south 5",
    "up 5",
    "down 5",
)


def grid_shape(area: AreaConfig) -> np.ndarray:
    """``(n_zones_x, n_zones_y, n_levels_z)`` as an int array."""
    return np.array([area.n_zones_x, area.n_zones_y, area.n_levels_z], dtype=np.int64)


def zone_index(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """The grid index of the zone holding ``xyz_m`` (nearest level in z), clipped to the grid."""
    if type(xyz_m) is np.ndarray and xyz_m.dtype == np.float64 and xyz_m.shape == (3,):
        x, y, z = xyz_m.tolist()  # Python floats: the same arithmetic, less overhead
        qx, qy, qz = x / area.zone_m, y / area.zone_m, (z - area.z_min_m) / area.zone_m
        if abs(qx) + abs(qy) + abs(qz) < _EXACT:  # finite, and int64 holds the index
            n_x, n_y, n_z = _grid_dims(area)
            ix, iy, iz = math.floor(qx), math.floor(qy), round(qz)  # round: half to even
            return np.array(
                [min(max(ix, 0), n_x - 1), min(max(iy, 0), n_y - 1), min(max(iz, 0), n_z - 1)],
                dtype=np.int64,
            )
    raw = np.array(
        [
            np.floor(xyz_m[0] / area.zone_m),
            np.floor(xyz_m[1] / area.zone_m),
            np.rint((xyz_m[2] - area.z_min_m) / area.zone_m),
        ]
    ).astype(np.int64)
    return np.clip(raw, 0, grid_shape(area) - 1)


def zone_position(index: np.ndarray, area: AreaConfig) -> np.ndarray:
    """The point a grid index stands for (zone centre, level altitude), metres."""
    if type(index) is np.ndarray and index.ndim == 1 and index.dtype.kind in "iu":
        index = index.tolist()  # Python ints: the same arithmetic, less overhead
    return np.array(
        [
            (index[0] + 0.5) * area.zone_m,
            (index[1] + 0.5) * area.zone_m,
            area.z_min_m + index[2] * area.zone_m,
        ]
    )


def move_mask(index: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Boolean (13,): the moves from ``index`` that stay on the grid (``stay`` always)."""
    if type(index) is np.ndarray and index.shape == (3,) and index.dtype.kind == "i":
        ix, iy, iz = index.tolist()
        return _move_mask_at(area, ix, iy, iz).copy()
    landing = np.asarray(index) + MOVES
    return np.all((landing >= 0) & (landing < grid_shape(area)), axis=1)


# Grid coordinates below this (sum of magnitudes) floor and round the same in Python and numpy.
_EXACT = 2.0**52


@lru_cache(maxsize=16)
def _grid_dims(area: AreaConfig) -> tuple[int, int, int]:
    return area.n_zones_x, area.n_zones_y, area.n_levels_z


@lru_cache(maxsize=65536)
def _move_mask_at(area: AreaConfig, ix: int, iy: int, iz: int) -> np.ndarray:
    landing = np.array([ix, iy, iz], dtype=np.int64) + MOVES
    mask = np.all((landing >= 0) & (landing < grid_shape(area)), axis=1)
    mask.setflags(write=False)  # cached: callers get copies
    return mask
