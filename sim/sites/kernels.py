"""The sites' compiled kernels, all in one module (numba only).

Numba caches a kernel beside its source and re-checks only that file's time stamp, and the
package's cache directory is named by the sources of ``sim/*.py`` alone (``sim/__init__.py``),
not of ``sim/sites``: a kernel here that called a compiled function of another module would
keep running the old callee after that module changed. So every kernel that calls another
lives here, and :mod:`sim.sites.lookup` and :mod:`sim.sites.los` call them from Python.

What they compute is documented where they are used: the lookup's interpolation in
:mod:`sim.sites.lookup`, the line of sight in :mod:`sim.sites.los`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from sim.sites.format import LOSS_STEP_DB, NO_PATH_CODE

COVERED_WEIGHT = 0.5
"""The least weight of interpolation corners with a path for a link to have one."""
BAD_UAV = -2
""":func:`links_kernel`'s answer for a UAV position that is not finite."""


@njit(cache=True, nogil=True, inline="always")
def cell_index(x: float, cell_m: float, exact: bool) -> int:
    """``int(x // cell_m)``, Python's floor division, the same integer always: with ``exact``
    (:func:`sim.sites.lookup.exact_cells`) the rounded quotient's floor corrected by exact
    products (a float ``//`` costs an ``fmod``, a third of a line-of-sight march), else ``//``
    itself."""
    if exact:
        q = np.floor(x / cell_m)
        if abs(q) < 1048576.0:
            if q * cell_m > x:
                q -= 1.0
            elif (q + 1.0) * cell_m <= x:
                q += 1.0
            return int(q)
    return int(x // cell_m)


@njit(cache=True, nogil=True)
def _bracket(axis: np.ndarray, value: float) -> tuple[int, float]:
    """The grid index below ``value`` and the fraction of the way to the one above (0 at the
    lower one), the value clamped to the axis' range; (0, 0.0) on a one-point axis."""
    if axis.size == 1:
        return 0, 0.0
    clamped = min(max(value, axis[0]), axis[-1])
    lower = min(max(np.searchsorted(axis, clamped, side="right") - 1, 0), axis.size - 2)
    return lower, (clamped - axis[lower]) / (axis[lower + 1] - axis[lower])


@njit(cache=True, nogil=True)
def cells_kernel(
    users: np.ndarray,
    size_x_m: float,
    size_y_m: float,
    cell_m: float,
    exact: bool,
    last_x: int,
    last_y: int,
    row: np.ndarray,
    column: np.ndarray,
) -> int:
    """:func:`sim.sites.lookup.ground_cells` into ``row`` and ``column``: the index of the
    first user outside ``[0, size_x_m] × [0, size_y_m]`` (NaN included), or -1."""
    for u in range(users.shape[0]):
        x, y = users[u, 0], users[u, 1]
        if not (0.0 <= x <= size_x_m and 0.0 <= y <= size_y_m):
            return u
        column[u] = min(cell_index(x, cell_m, exact), last_x)
        row[u] = min(cell_index(y, cell_m, exact), last_y)
    return -1


@njit(cache=True, nogil=True)
def corners(
    axis_x: np.ndarray, axis_y: np.ndarray, axis_z: np.ndarray, x: float, y: float, z: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The eight corners of the grid cell around ``(x, y, z)`` (clamped to the grid's box) in
    a fixed order (x fastest): their weights (8,), grid indices (8, 3: iz, iy, ix) and
    positions (8, 3: x, y, z). A corner beyond a one-point axis has weight 0."""
    lx, fx = _bracket(axis_x, x)
    ly, fy = _bracket(axis_y, y)
    lz, fz = _bracket(axis_z, z)
    weight = np.empty(8)
    index = np.empty((8, 3), dtype=np.intp)
    point = np.empty((8, 3))
    for corner in range(8):
        w = 1.0
        w *= fx if corner & 1 else 1.0 - fx
        w *= fy if corner & 2 else 1.0 - fy
        w *= fz if corner & 4 else 1.0 - fz
        ix = lx + 1 if corner & 1 and axis_x.size > 1 else lx
        iy = ly + 1 if corner & 2 and axis_y.size > 1 else ly
        iz = lz + 1 if corner & 4 and axis_z.size > 1 else lz
        weight[corner] = w
        index[corner, 0], index[corner, 1], index[corner, 2] = iz, iy, ix
        point[corner, 0], point[corner, 1], point[corner, 2] = axis_x[ix], axis_y[iy], axis_z[iz]
    return weight, index, point


@njit(cache=True, nogil=True)
def link_loss_db(
    codes: np.ndarray,
    gain: np.ndarray,
    weight: np.ndarray,
    index: np.ndarray,
    point: np.ndarray,
    row: int,
    column: int,
    cell_m: float,
    user_height_m: float,
) -> float:
    """One link's loss (:mod:`sim.sites.lookup`'s doc) from the corners of :func:`corners` to
    ground cell ``(row, column)``."""
    centre_x = (column + 0.5) * cell_m
    centre_y = (row + 0.5) * cell_m
    power = 0.0
    spread = 0.0
    covered = 0.0
    for corner in range(8):
        w = weight[corner]
        if w == 0.0:
            continue
        code = codes[index[corner, 0], index[corner, 1], index[corner, 2], row, column]
        if w >= 1.0:  # on a grid point (or a face of a one-point axis): the stored value
            return math.inf if code == NO_PATH_CODE else code * LOSS_STEP_DB
        dx = point[corner, 0] - centre_x
        dy = point[corner, 1] - centre_y
        dz = point[corner, 2] - user_height_m
        squared = w * (dx * dx + dy * dy + dz * dz)
        spread += squared
        if code != NO_PATH_CODE:
            covered += w
            power += squared * gain[code]
    if covered < COVERED_WEIGHT or power <= 0.0:
        return math.inf
    return -10.0 * math.log10(power / spread)


@njit(cache=True, nogil=True)
def interpolate_kernel(
    codes: np.ndarray,
    gain: np.ndarray,
    axis_x: np.ndarray,
    axis_y: np.ndarray,
    axis_z: np.ndarray,
    cell_m: float,
    user_height_m: float,
    uav: np.ndarray,
    row: np.ndarray,
    column: np.ndarray,
    out: np.ndarray,
) -> None:
    """:func:`sim.sites.lookup.interpolate` into ``out`` (N, M)."""
    shared = row.shape[0] == 1
    for n in range(uav.shape[0]):
        weight, index, point = corners(axis_x, axis_y, axis_z, uav[n, 0], uav[n, 1], uav[n, 2])
        s = 0 if shared else n
        for m in range(row.shape[1]):
            out[n, m] = link_loss_db(
                codes, gain, weight, index, point, row[s, m], column[s, m], cell_m, user_height_m
            )


@njit(cache=True, nogil=True)
def link_clear(
    heights: np.ndarray,
    top_m: float,
    cell_m: float,
    exact: bool,
    user_height_m: float,
    ux: float,
    uy: float,
    uz: float,
    x0: float,
    y0: float,
    row0: int,
    column0: int,
) -> bool:
    """One link's line of sight (:mod:`sim.sites.los`'s doc), the user at ``(x0, y0)`` in ground
    cell ``(row0, column0)``, the UAV at ``(ux, uy, uz)``: the segment at evenly spaced fractions of
    the way, at most half a cell apart along the ground (the user's end left out), clear while above
    every cell it crosses but the user's own. A rising segment that is above ``top_m``, the tallest
    cell, stays clear: the march stops there."""
    last_x, last_y = heights.shape[1] - 1, heights.shape[0] - 1
    dz = uz - user_height_m
    dx = ux - x0
    dy = uy - y0
    intervals = max(1, math.ceil(math.sqrt(dx * dx + dy * dy) / (0.5 * cell_m)))
    for i in range(1, intervals + 1):
        t = i / intervals
        if dz >= 0.0 and user_height_m + t * dz >= top_m:
            return True  # above every building from here on
        column = min(max(cell_index(x0 + t * dx, cell_m, exact), 0), last_x)
        row = min(max(cell_index(y0 + t * dy, cell_m, exact), 0), last_y)
        if row == row0 and column == column0:
            continue  # the user's own cell
        if user_height_m + t * dz < heights[row, column]:
            return False
    return True


@njit(cache=True, nogil=True)
def clear_kernel(
    heights: np.ndarray,
    top_m: float,
    cell_m: float,
    exact: bool,
    user_height_m: float,
    uav: np.ndarray,
    users: np.ndarray,
    row0: np.ndarray,
    column0: np.ndarray,
    out: np.ndarray,
) -> None:
    """Each link's line of sight (:func:`link_clear`) into ``out`` (N, M)."""
    shared = users.shape[0] == 1
    for n in range(uav.shape[0]):
        s = 0 if shared else n
        for m in range(users.shape[1]):
            out[n, m] = link_clear(
                heights, top_m, cell_m, exact, user_height_m, uav[n, 0], uav[n, 1], uav[n, 2],
                users[s, m, 0], users[s, m, 1], row0[s, m], column0[s, m],
            )  # fmt: skip


@njit(cache=True, nogil=True)
def links_kernel(
    codes: np.ndarray,
    gain: np.ndarray,
    axis_x: np.ndarray,
    axis_y: np.ndarray,
    axis_z: np.ndarray,
    heights: np.ndarray,
    top_m: float,
    cell_m: float,
    exact: bool,
    size_x_m: float,
    size_y_m: float,
    user_height_m: float,
    uav: np.ndarray,
    users: np.ndarray,
    loss: np.ndarray,
    los: np.ndarray,
) -> int:
    """:func:`sim.sites.los.site_links` in one pass: :data:`BAD_UAV` if a UAV position is not
    finite, the index of the first user (flattened over ``users`` (S, M, 2)) outside the area, both
    before anything else is computed; then every link's loss (:func:`link_loss_db`) into ``loss``
    (N, M) and, when ``los`` is (N, M) rather than empty, its line of sight (:func:`link_clear`),
    and -1."""
    for n in range(uav.shape[0]):
        if not (math.isfinite(uav[n, 0]) and math.isfinite(uav[n, 1]) and math.isfinite(uav[n, 2])):
            return BAD_UAV
    n_sets, n_users = users.shape[0], users.shape[1]
    rows = np.empty((n_sets, n_users), dtype=np.intp)
    columns = np.empty((n_sets, n_users), dtype=np.intp)
    last_x, last_y = heights.shape[1] - 1, heights.shape[0] - 1
    for s in range(n_sets):
        for m in range(n_users):
            x, y = users[s, m, 0], users[s, m, 1]
            if not (0.0 <= x <= size_x_m and 0.0 <= y <= size_y_m):
                return s * n_users + m
            columns[s, m] = min(cell_index(x, cell_m, exact), last_x)
            rows[s, m] = min(cell_index(y, cell_m, exact), last_y)
    with_los = los.shape[0] > 0
    shared = n_sets == 1
    for n in range(uav.shape[0]):
        weight, index, point = corners(axis_x, axis_y, axis_z, uav[n, 0], uav[n, 1], uav[n, 2])
        s = 0 if shared else n
        for m in range(n_users):
            loss[n, m] = link_loss_db(
                codes, gain, weight, index, point, rows[s, m], columns[s, m], cell_m,
                user_height_m,
            )  # fmt: skip
            if with_los:
                los[n, m] = link_clear(
                    heights, top_m, cell_m, exact, user_height_m, uav[n, 0], uav[n, 1], uav[n, 2],
                    users[s, m, 0], users[s, m, 1], rows[s, m], columns[s, m],
                )  # fmt: skip
    return -1
