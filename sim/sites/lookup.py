"""The site's path loss at any UAV position: numpy (and numba, as the network model) only,
no ray tracer.

:func:`path_loss_db` interpolates the stored mean path loss trilinearly (in dB) over the UAV
grid and takes each user's ground cell (the cell the user stands in: the stored value is the
loss at its centre). "No path" is out of coverage, ``+inf``. Between a grid point with a path
and one without, the interpolation uses the corners that have one, their weights renormalised,
as long as they carry at least half of the weight; below that the link has no path. So the
value at a grid point is exactly the stored one, and coverage changes half-way between grid
points, where the nearer corners change.

A UAV outside the grid's box is looked up at the nearest point of the box (the grid covers
the area's flight volume; a world that flies outside it must be refused where the site is
attached to the area). Users must lie in the site's area.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from sim.errors import InputError
from sim.sites.format import LOSS_STEP_DB, NO_PATH_CODE, Site

COVERED_WEIGHT = 0.5
"""The least weight of interpolation corners with a path for a link to have one."""


@njit(cache=True, nogil=True)
def _bracket(axis: np.ndarray, value: float) -> tuple[int, float]:
    """The grid index below ``value`` and the fraction of the way to the one above (0 at the
    lower one), the value clamped to the axis' range; (0, 0.0) on a one-point axis."""
    if axis.size == 1:
        return 0, 0.0
    clamped = min(max(value, axis[0]), axis[-1])
    lower = min(max(np.searchsorted(axis, clamped, side="right") - 1, 0), axis.size - 2)
    return lower, (clamped - axis[lower]) / (axis[lower + 1] - axis[lower])


def ground_cells(site: Site, users_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each user's ground cell, ``(row j, column i)``; InputError naming the first user outside
    the site's area."""
    users = np.asarray(users_xy, dtype=np.float64)
    if users.ndim != 2 or users.shape[1] != 2:
        raise InputError(f"users_xy: must have shape (M, 2), got {users.shape}")
    users = np.ascontiguousarray(users)
    row = np.empty(users.shape[0], dtype=np.intp)
    column = np.empty(users.shape[0], dtype=np.intp)
    k = _cells_kernel(
        users, float(site.size_x_m), float(site.size_y_m), float(site.cell_m),
        site.cells_x - 1, site.cells_y - 1, row, column,
    )  # fmt: skip
    if k >= 0:
        raise InputError(
            f"users_xy[{k}]: {users[k].tolist()} is outside the site's area "
            f"[0, {site.size_x_m:g}] × [0, {site.size_y_m:g}] m"
        )
    return row, column


@njit(cache=True, nogil=True)
def _cells_kernel(
    users: np.ndarray,
    size_x_m: float,
    size_y_m: float,
    cell_m: float,
    last_x: int,
    last_y: int,
    row: np.ndarray,
    column: np.ndarray,
) -> int:
    """:func:`ground_cells` into ``row`` and ``column``: the index of the first user outside
    ``[0, size_x_m] × [0, size_y_m]`` (NaN included), or -1."""
    for u in range(users.shape[0]):
        x, y = users[u, 0], users[u, 1]
        if not (0.0 <= x <= size_x_m and 0.0 <= y <= size_y_m):
            return u
        column[u] = min(int(x // cell_m), last_x)
        row[u] = min(int(y // cell_m), last_y)
    return -1


def path_loss_db(site: Site, uav_xyz: np.ndarray, users_xy: np.ndarray) -> np.ndarray:
    """Mean path loss in dB from each UAV position to each user (module doc): ``(N, M)`` for
    ``uav_xyz`` of shape ``(N, 3)``, ``(M,)`` for one position ``(3,)``; ``+inf`` where there
    is no path. InputError naming the argument for a wrong shape or a user off the site."""
    uav = np.asarray(uav_xyz, dtype=np.float64)
    single = uav.ndim == 1
    uav = check_uav(uav)
    row, column = ground_cells(site, users_xy)
    loss = interpolate(site, uav, row[None, :], column[None, :])
    return loss[0] if single else loss


def check_uav(uav: np.ndarray) -> np.ndarray:
    """UAV positions (3,) or (N, 3) as (N, 3), or InputError naming ``uav_xyz``."""
    uav = np.atleast_2d(uav)
    if uav.ndim != 2 or uav.shape[1] != 3 or not np.isfinite(uav).all():
        raise InputError(f"uav_xyz: must be finite with shape (3,) or (N, 3), got {uav.shape}")
    return uav


def interpolate(site: Site, uav: np.ndarray, row: np.ndarray, column: np.ndarray) -> np.ndarray:
    """The trilinear lookup (module doc) for positions ``uav`` (N, 3), checked, and ground cells
    ``row``, ``column`` (:func:`ground_cells`) of shape (N, M), each position its own users, or
    (1, M), every position the same users: (N, M) dB."""
    out = np.empty((uav.shape[0], row.shape[1]))
    _interpolate_kernel(
        site.loss_code, site.uav_x_m, site.uav_y_m, site.uav_z_m,
        np.ascontiguousarray(uav), np.ascontiguousarray(row, dtype=np.intp),
        np.ascontiguousarray(column, dtype=np.intp), out,
    )  # fmt: skip
    return out


@njit(cache=True, nogil=True)
def _interpolate_kernel(
    codes: np.ndarray,
    axis_x: np.ndarray,
    axis_y: np.ndarray,
    axis_z: np.ndarray,
    uav: np.ndarray,
    row: np.ndarray,
    column: np.ndarray,
    out: np.ndarray,
) -> None:
    """:func:`interpolate` into ``out`` (N, M): the eight corners of each position's grid
    cell in a fixed order (x fastest), weights the products of the axes' fractions, the
    corners without a path left out and the rest renormalised when they carry at least
    :data:`COVERED_WEIGHT`, else ``+inf``."""
    shared = row.shape[0] == 1
    for n in range(uav.shape[0]):
        lx, fx = _bracket(axis_x, uav[n, 0])
        ly, fy = _bracket(axis_y, uav[n, 1])
        lz, fz = _bracket(axis_z, uav[n, 2])
        s = 0 if shared else n
        for m in range(row.shape[1]):
            r, c = row[s, m], column[s, m]
            total = 0.0
            weight = 0.0
            for corner in range(8):
                w = 1.0
                w *= fx if corner & 1 else 1.0 - fx
                w *= fy if corner & 2 else 1.0 - fy
                w *= fz if corner & 4 else 1.0 - fz
                ix = lx + 1 if corner & 1 and axis_x.size > 1 else lx
                iy = ly + 1 if corner & 2 and axis_y.size > 1 else ly
                iz = lz + 1 if corner & 4 and axis_z.size > 1 else lz
                code = codes[iz, iy, ix, r, c]
                if code != NO_PATH_CODE:
                    total += w * code
                    weight += w
            out[n, m] = total / weight * LOSS_STEP_DB if weight >= COVERED_WEIGHT else np.inf
