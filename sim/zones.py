"""The zone grid the discrete policy moves on, as pure functions shared by training and serving.

The area is cut into ``zone_m`` squares (20 × 20 for the paper's 500 m area and 25 m zones) and
``n_levels_z`` altitude levels ``zone_m`` apart from ``z_min_m``. A grid index ``(ix, iy, iz)``
stands for the point at the centre of zone ``(ix, iy)``, at altitude ``z_min_m + iz · zone_m``.
The 13 discrete moves (:data:`MOVES`) step the index by ±1 or ±5 along one axis, or stay.
"""

from __future__ import annotations

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
    return np.array(
        [
            (index[0] + 0.5) * area.zone_m,
            (index[1] + 0.5) * area.zone_m,
            area.z_min_m + index[2] * area.zone_m,
        ]
    )


def move_mask(index: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Boolean (13,): the moves from ``index`` that stay on the grid (``stay`` always)."""
    landing = np.asarray(index) + MOVES
    return np.all((landing >= 0) & (landing < grid_shape(area)), axis=1)
