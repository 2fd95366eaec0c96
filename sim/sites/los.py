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

import weakref

import numpy as np

from sim.errors import InputError
from sim.sites.format import Site
from sim.sites.kernels import BAD_UAV, clear_kernel, links_kernel
from sim.sites.lookup import GAIN_OF_CODE, check_uav, exact_cells, ground_cells, outside_error


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
    path_loss_db`) and, ``with_los``, its line of sight (:func:`line_of_sight`; else None):
    ``(N, M)`` each for ``uav_xyz`` (N, 3) and ``users_xy`` (M, 2), every position the same
    users, or (N, M, 2), each position its own (a vectorised environment's cells; a fleet's
    links to their own APs as N positions of one user each). One compiled pass over the links
    (the network model calls it every step), the same values as those two functions give.
    InputError naming the argument for a wrong shape or a user off the site."""
    uav = np.asarray(uav_xyz, dtype=np.float64)
    if uav.ndim == 1:
        uav = uav[None]
    if uav.ndim != 2 or uav.shape[1] != 3:
        check_uav(uav)  # raises, naming uav_xyz
    users = np.asarray(users_xy, dtype=np.float64)
    if users.ndim == 3:
        if users.shape[0] != uav.shape[0] or users.shape[2] != 2:
            raise InputError(
                f"users_xy: must have shape (M, 2) or ({uav.shape[0]}, M, 2), got {users.shape}"
            )
    elif users.ndim != 2 or users.shape[1] != 2:
        raise InputError(f"users_xy: must have shape (M, 2), got {users.shape}")
    else:
        users = users[None]
    shape = (uav.shape[0], users.shape[1])
    loss = np.empty(shape)
    los = np.empty(shape, dtype=np.bool_) if with_los else _NO_LOS
    top_m, cell_m, exact, size_x_m, size_y_m, user_height_m = _constants(site)
    bad = links_kernel(
        site.loss_code, GAIN_OF_CODE, site.uav_x_m, site.uav_y_m, site.uav_z_m,
        site.building_height_m, top_m, cell_m, exact, size_x_m, size_y_m, user_height_m,
        uav if uav.flags.c_contiguous else np.ascontiguousarray(uav),
        users if users.flags.c_contiguous else np.ascontiguousarray(users), loss, los,
    )  # fmt: skip
    if bad == BAD_UAV:
        check_uav(uav)  # raises, naming uav_xyz
    if bad >= 0:
        raise outside_error(site, users.reshape(-1, 2)[bad], bad)
    return loss, los if with_los else None


_NO_LOS = np.empty((0, 0), dtype=np.bool_)
"""The kernel's ``los`` when line of sight is not asked for (never written)."""


_CONSTANTS: dict[int, tuple[weakref.ref, tuple[float, float, bool, float, float, float]]] = {}


def _constants(site: Site) -> tuple[float, float, bool, float, float, float]:
    """What the kernels take of a site besides its arrays, worked out once per site (the
    model calls :func:`site_links` every step): the tallest cell, the cell side, whether
    :func:`sim.sites.kernels.cell_index` may take its fast path, the area's size, the users'
    height."""
    known = _CONSTANTS.get(id(site))
    if known is not None and known[0]() is site:
        return known[1]
    heights = site.building_height_m
    values = (
        float(heights.max()) if heights.size else 0.0,
        float(site.cell_m),
        exact_cells(site.cell_m),
        float(site.size_x_m),
        float(site.size_y_m),
        float(site.user_height_m),
    )
    if len(_CONSTANTS) >= 16:
        _CONSTANTS.clear()
    _CONSTANTS[id(site)] = (weakref.ref(site), values)  # a weak one: sites are large
    return values


def _clear(
    site: Site, uav: np.ndarray, users: np.ndarray, row0: np.ndarray, column0: np.ndarray
) -> np.ndarray:
    """The links' line of sight (module doc): ``uav`` (N, 3), ``users`` (1 or N, M, 2) and
    their ground cells (1 or N, M) → (N, M) bool; each link on its own (the same answer in any
    batch)."""
    out = np.empty((uav.shape[0], users.shape[1]), dtype=np.bool_)
    top_m, cell_m, exact, _, _, user_height_m = _constants(site)
    clear_kernel(
        site.building_height_m, top_m, cell_m, exact, user_height_m,
        np.ascontiguousarray(uav), np.ascontiguousarray(users),
        np.ascontiguousarray(row0, dtype=np.intp), np.ascontiguousarray(column0, dtype=np.intp),
        out,
    )  # fmt: skip
    return out
