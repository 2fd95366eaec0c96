"""Line of sight over a site's building-height map: numpy and numba only.

A link is in line of sight when the straight segment from the user (at the site's
``user_height_m``) to the UAV passes above the building height of every ground cell it
crosses. Each segment is sampled at most half a cell apart along its ground track, from
just off the user to the UAV (every link on its own: the answer does not depend on the other
links of a call); the user's own cell is skipped (a cell counts at its tallest point, which
may be a wall beside the user; users are to stand on walkable cells, height 0 anyway). The
height map is 2.5-D: an overhang, a bridge or an arcade counts as a solid block up to its top,
and a cell counts at its tallest point (the build takes the highest of several downward rays
per cell), so the map errs towards blocking.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sim.errors import InputError
from sim.sites.format import Site
from sim.sites.lookup import check_uav, ground_cells, interpolate


def line_of_sight(site: Site, uav_xyz: np.ndarray, users_xy: np.ndarray) -> np.ndarray:
    """Whether each link is unobstructed: ``(N, M)`` bool for ``uav_xyz`` (N, 3), ``(M,)`` for
    one position (3,). Users are checked as :func:`sim.sites.lookup.path_loss_db` checks them."""
    uav = np.asarray(uav_xyz, dtype=np.float64)
    single = uav.ndim == 1
    uav = np.atleast_2d(uav)
    users = np.asarray(users_xy, dtype=np.float64)
    row0, column0 = ground_cells(site, users)
    clear = _clear(site, uav, users[None], row0[None, :], column0[None, :])
    return clear[0] if single else clear


def site_links(
    site: Site, uav_xyz: np.ndarray, users_xy: np.ndarray, with_los: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """Every link's mean path loss (dB, ``+inf`` without a path: :func:`sim.sites.lookup.
    path_loss_db`) and, ``with_los``, its line of sight (:func:`line_of_sight`; else None), the
    users' ground cells found once: ``(N, M)`` each for ``uav_xyz`` (N, 3) and ``users_xy``
    (M, 2), every position the same users, or (N, M, 2), each position its own (a vectorised
    environment's cells; a fleet's links to their own APs as N positions of one user each).
    InputError naming the argument for a wrong shape or a user off the site."""
    uav = check_uav(np.asarray(uav_xyz, dtype=np.float64))
    users = np.asarray(users_xy, dtype=np.float64)
    if users.ndim == 3:
        if users.shape[0] != uav.shape[0] or users.shape[2] != 2:
            raise InputError(
                f"users_xy: must have shape (M, 2) or ({uav.shape[0]}, M, 2), got {users.shape}"
            )
        row, column = ground_cells(site, users.reshape(-1, 2))
        row, column = row.reshape(users.shape[:2]), column.reshape(users.shape[:2])
    else:
        row, column = ground_cells(site, users)
        users, row, column = users[None], row[None, :], column[None, :]
    loss = interpolate(site, uav, row, column)
    return loss, _clear(site, uav, users, row, column) if with_los else None


def _clear(
    site: Site, uav: np.ndarray, users: np.ndarray, row0: np.ndarray, column0: np.ndarray
) -> np.ndarray:
    """The links' line of sight (module doc): ``uav`` (N, 3), ``users`` (1 or N, M, 2) and
    their ground cells (1 or N, M) → (N, M) bool; each link on its own (the same answer in any
    batch)."""
    out = np.empty((uav.shape[0], users.shape[1]), dtype=np.bool_)
    heights = site.building_height_m
    _clear_kernel(
        heights, float(heights.max()) if heights.size else 0.0, float(site.cell_m),
        float(site.user_height_m), np.ascontiguousarray(uav), np.ascontiguousarray(users),
        np.ascontiguousarray(row0, dtype=np.intp), np.ascontiguousarray(column0, dtype=np.intp),
        out,
    )  # fmt: skip
    return out


@njit(cache=True, nogil=True)
def _clear_kernel(
    heights: np.ndarray,
    top_m: float,
    cell_m: float,
    user_height_m: float,
    uav: np.ndarray,
    users: np.ndarray,
    row0: np.ndarray,
    column0: np.ndarray,
    out: np.ndarray,
) -> None:
    """Each link's line of sight into ``out`` (N, M): the segment from the user to the UAV at
    evenly spaced fractions of the way, at most half a cell apart along the ground (the user's
    end left out), clear while above every cell it crosses but the user's own. A rising
    segment that is above ``top_m``, the tallest cell, stays clear: the march stops there."""
    shared = users.shape[0] == 1
    last_x, last_y = heights.shape[1] - 1, heights.shape[0] - 1
    for n in range(uav.shape[0]):
        s = 0 if shared else n
        dz = uav[n, 2] - user_height_m
        for m in range(users.shape[1]):
            x0, y0 = users[s, m, 0], users[s, m, 1]
            dx = uav[n, 0] - x0
            dy = uav[n, 1] - y0
            intervals = max(1, math.ceil(math.sqrt(dx * dx + dy * dy) / (0.5 * cell_m)))
            clear = True
            for i in range(1, intervals + 1):
                t = i / intervals
                if dz >= 0.0 and user_height_m + t * dz >= top_m:
                    break  # above every building from here on
                column = min(max(int((x0 + t * dx) // cell_m), 0), last_x)
                row = min(max(int((y0 + t * dy) // cell_m), 0), last_y)
                if row == row0[s, m] and column == column0[s, m]:
                    continue  # the user's own cell
                if user_height_m + t * dz < heights[row, column]:
                    clear = False
                    break
            out[n, m] = clear
