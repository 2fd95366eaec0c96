"""The site's path loss at any UAV position: numpy only, no ray tracer.

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

from sim.errors import InputError
from sim.sites.format import LOSS_STEP_DB, NO_PATH_CODE, Site

COVERED_WEIGHT = 0.5
"""The least weight of interpolation corners with a path for a link to have one."""


def _bracket(axis: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each value: the grid indices below and above and the fraction of the way between
    them (0 at the lower one), values clamped to the axis' range."""
    if axis.size == 1:
        zeros = np.zeros(values.shape, dtype=np.intp)
        return zeros, zeros, np.zeros(values.shape)
    clamped = np.clip(values, axis[0], axis[-1])
    lower = np.clip(np.searchsorted(axis, clamped, side="right") - 1, 0, axis.size - 2)
    upper = lower + 1
    fraction = (clamped - axis[lower]) / (axis[upper] - axis[lower])
    return lower, upper, fraction


def ground_cells(site: Site, users_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each user's ground cell, ``(row j, column i)``; InputError naming the first user outside
    the site's area."""
    users = np.asarray(users_xy, dtype=np.float64)
    if users.ndim != 2 or users.shape[1] != 2:
        raise InputError(f"users_xy: must have shape (M, 2), got {users.shape}")
    inside = (
        np.isfinite(users).all(axis=1)
        & (users[:, 0] >= 0)
        & (users[:, 0] <= site.size_x_m)
        & (users[:, 1] >= 0)
        & (users[:, 1] <= site.size_y_m)
    )
    if not inside.all():
        k = int(np.flatnonzero(~inside)[0])
        raise InputError(
            f"users_xy[{k}]: {users[k].tolist()} is outside the site's area "
            f"[0, {site.size_x_m:g}] × [0, {site.size_y_m:g}] m"
        )
    column = np.minimum((users[:, 0] // site.cell_m).astype(np.intp), site.cells_x - 1)
    row = np.minimum((users[:, 1] // site.cell_m).astype(np.intp), site.cells_y - 1)
    return row, column


def path_loss_db(site: Site, uav_xyz: np.ndarray, users_xy: np.ndarray) -> np.ndarray:
    """Mean path loss in dB from each UAV position to each user (module doc): ``(N, M)`` for
    ``uav_xyz`` of shape ``(N, 3)``, ``(M,)`` for one position ``(3,)``; ``+inf`` where there
    is no path. InputError naming the argument for a wrong shape or a user off the site."""
    uav = np.asarray(uav_xyz, dtype=np.float64)
    single = uav.ndim == 1
    uav = np.atleast_2d(uav)
    if uav.ndim != 2 or uav.shape[1] != 3 or not np.isfinite(uav).all():
        raise InputError(f"uav_xyz: must be finite with shape (3,) or (N, 3), got {uav.shape}")
    row, column = ground_cells(site, users_xy)
    axes = [_bracket(site.uav_x_m, uav[:, 0]), _bracket(site.uav_y_m, uav[:, 1])]
    axes.append(_bracket(site.uav_z_m, uav[:, 2]))
    total = np.zeros((uav.shape[0], row.size))
    weight = np.zeros_like(total)
    for corner in range(8):
        index = []
        corner_weight = np.ones(uav.shape[0])
        for axis, (lower, upper, fraction) in enumerate(axes):
            high = (corner >> axis) & 1
            index.append(upper if high else lower)
            corner_weight = corner_weight * (fraction if high else 1.0 - fraction)
        ix, iy, iz = (i[:, None] for i in index)
        codes = site.loss_code[iz, iy, ix, row[None, :], column[None, :]]
        covered = codes != NO_PATH_CODE
        w = np.where(covered, corner_weight[:, None], 0.0)
        total += w * codes.astype(np.float64)
        weight += w
    has_path = weight >= COVERED_WEIGHT
    loss = np.full(total.shape, np.inf)
    loss[has_path] = total[has_path] / weight[has_path] * LOSS_STEP_DB
    return loss[0] if single else loss
