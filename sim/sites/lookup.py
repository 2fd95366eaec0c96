"""The site's path loss at any UAV position: numpy (and numba, as the network model) only,
no ray tracer.

:func:`path_loss_db` takes each user's ground cell (the cell the user stands in: the stored
value is the cell's mean loss; distances are measured to the cell's centre at the site's
``user_height_m``) and averages the *path gains* ``g = 10^(−loss/10)`` of the eight UAV grid
points around the position, each weighted by its trilinear weight ``w`` times its squared
distance ``d²`` to the cell:

    loss(p) = −10·log10( Σ w·g·d² / Σ w·d² ),

a corner without a path counting as zero gain. That is received power relative to free-space
spreading (``g·d²``) interpolated, then spread again over the interpolated ``d²``: Sionna's
radio map is a mean of power, and averaging power lets a strong corner dominate a faded one
(trilinear interpolation in dB, the first lookup, averaged decibels). A constant loss stays
constant; free space stays free space at the interpolated squared distance — exact at grid
points and far away, at most ``10·log10(1 + Σ f(1−f)·h² / d²)`` dB off right under a low UAV
half-way between grid points (``f`` the fractions, ``h`` the grid's steps). It was chosen by
measured error against direct Sionna computation (docs/sites.md).

"No path" is out of coverage, ``+inf``: a link has a path when the corners that have one carry
at least :data:`COVERED_WEIGHT` of the trilinear weight. At a grid point the value is the
stored one, exactly.

A UAV outside the grid's box is looked up at the nearest point of the box (the grid covers
the area's flight volume; a world that flies outside it must be refused where the site is
attached to the area). Users must lie in the site's area.
"""

from __future__ import annotations

import numpy as np

from sim.errors import InputError
from sim.sites.format import LOSS_STEP_DB, NO_PATH_CODE, Site
from sim.sites.kernels import COVERED_WEIGHT as COVERED_WEIGHT
from sim.sites.kernels import cells_kernel, interpolate_kernel

GAIN_OF_CODE = 10.0 ** (-np.arange(int(NO_PATH_CODE) + 1, dtype=np.float64) * LOSS_STEP_DB / 10.0)
GAIN_OF_CODE[NO_PATH_CODE] = 0.0
GAIN_OF_CODE.setflags(write=False)
"""Path gain (linear) of each loss code; 0 for no path (losses beyond ~3000 dB underflow to 0
and count as no path too)."""


def exact_cells(cell_m: float) -> bool:
    """Whether :func:`sim.sites.kernels.cell_index` may take its fast path for ``cell_m``:
    products of the cell side with integers below 2²¹ are exact (its binary mantissa has at
    most 32 bits: 5 m, 2.5 m, 4 m do; 0.1 m does not)."""
    numerator = float(cell_m).as_integer_ratio()[0]
    return cell_m > 0 and abs(numerator).bit_length() <= 32


def ground_cells(site: Site, users_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each user's ground cell, ``(row j, column i)``; InputError naming the first user outside
    the site's area."""
    users = np.asarray(users_xy, dtype=np.float64)
    if users.ndim != 2 or users.shape[1] != 2:
        raise InputError(f"users_xy: must have shape (M, 2), got {users.shape}")
    users = np.ascontiguousarray(users)
    row = np.empty(users.shape[0], dtype=np.intp)
    column = np.empty(users.shape[0], dtype=np.intp)
    k = cells_kernel(
        users, float(site.size_x_m), float(site.size_y_m), float(site.cell_m),
        exact_cells(site.cell_m), site.cells_x - 1, site.cells_y - 1, row, column,
    )  # fmt: skip
    if k >= 0:
        raise outside_error(site, users[k], k)
    return row, column


def outside_error(site: Site, user: np.ndarray, k: int) -> InputError:
    """The error for user ``k`` at ``user`` (2,) outside the site's area."""
    return InputError(
        f"users_xy[{k}]: {user.tolist()} is outside the site's area "
        f"[0, {site.size_x_m:g}] × [0, {site.size_y_m:g}] m"
    )


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
    """The lookup (module doc) for positions ``uav`` (N, 3), checked, and ground cells ``row``,
    ``column`` (:func:`ground_cells`) of shape (N, M), each position its own users, or (1, M),
    every position the same users: (N, M) dB."""
    out = np.empty((uav.shape[0], row.shape[1]))
    interpolate_kernel(
        site.loss_code, GAIN_OF_CODE, site.uav_x_m, site.uav_y_m, site.uav_z_m, float(site.cell_m),
        float(site.user_height_m), np.ascontiguousarray(uav),
        np.ascontiguousarray(row, dtype=np.intp), np.ascontiguousarray(column, dtype=np.intp),
        out,
    )  # fmt: skip
    return out
