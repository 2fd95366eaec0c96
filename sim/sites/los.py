"""Line of sight over a site's building-height map: numpy only.

A link is in line of sight when the straight segment from the user (at the site's
``user_height_m``) to the UAV passes above the building height of every ground cell it
crosses. The segment is sampled at most half a cell apart along the ground, from just off the
user to the UAV; the user's own cell is skipped (a cell counts at its tallest point, which
may be a wall beside the user; users are to stand on walkable cells, height 0 anyway). The
height map is 2.5-D: an overhang, a bridge or an arcade counts as a solid block up to its top,
and a cell counts at its tallest point (the build takes the highest of several downward rays
per cell), so the map errs towards blocking.
"""

from __future__ import annotations

import math

import numpy as np

from sim.sites.format import Site
from sim.sites.lookup import ground_cells


def line_of_sight(site: Site, uav_xyz: np.ndarray, users_xy: np.ndarray) -> np.ndarray:
    """Whether each link is unobstructed: ``(N, M)`` bool for ``uav_xyz`` (N, 3), ``(M,)`` for
    one position (3,). Users are checked as :func:`sim.sites.lookup.path_loss_db` checks them."""
    uav = np.asarray(uav_xyz, dtype=np.float64)
    single = uav.ndim == 1
    uav = np.atleast_2d(uav)
    users = np.asarray(users_xy, dtype=np.float64)
    row0, column0 = ground_cells(site, users)
    dx = uav[:, None, 0] - users[None, :, 0]
    dy = uav[:, None, 1] - users[None, :, 1]
    dz = uav[:, None, 2] - site.user_height_m
    longest = float(np.sqrt(dx * dx + dy * dy).max()) if dx.size else 0.0
    samples = max(2, math.ceil(longest / (0.5 * site.cell_m)) + 1)
    heights = site.building_height_m
    clear = np.ones(dx.shape, dtype=bool)
    last_x, last_y = site.cells_x - 1, site.cells_y - 1
    for t in np.linspace(0.0, 1.0, samples)[1:]:
        x = users[None, :, 0] + t * dx
        y = users[None, :, 1] + t * dy
        column = np.clip((x // site.cell_m).astype(np.intp), 0, last_x)
        row = np.clip((y // site.cell_m).astype(np.intp), 0, last_y)
        own = (row == row0[None, :]) & (column == column0[None, :])
        above = site.user_height_m + t * dz >= heights[row, column]
        clear &= above | own
    return clear[0] if single else clear
