"""Where people may stand on a site: its walkable ground (numpy only).

A site's ``walkable`` mask (:mod:`sim.sites.format`) says which ground cells a user may stand
on (cells outside buildings). A point is on walkable ground when its ground cell is, the cell
found as the lookup finds it (:func:`sim.sites.lookup.ground_cells`: ``x // cell_m``, the far
edge in the last cell). The rest of the model uses three things from here:

* :func:`walkable_at` and :func:`check_walkable` — a scenario's users checked against the site
  (one-line :class:`~sim.errors.InputError` naming the first user inside a building);
* :func:`place_on_walkable` — the scenario generator's rule: users drawn inside a building are
  drawn again from their layout, at most ``tries`` times, and whoever is still inside one then
  moves to the centre of the nearest walkable cell of the area (:func:`nearest_walkable_xy`);
* :func:`walkable_path` — a user's step is allowed when every point of the straight segment,
  sampled at most half a cell apart, is on walkable ground (:mod:`sim.users`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import njit

from sim.errors import InputError
from sim.sites.format import Site
from sim.sites.lookup import ground_cells

PLACEMENT_TRIES = 32
"""How many times :func:`place_on_walkable` draws a user inside a building again."""


def walkable_at(site: Site, users_xy: np.ndarray) -> np.ndarray:
    """Whether each point (M, 2) stands on walkable ground: (M,) bool. InputError (from
    :func:`~sim.sites.lookup.ground_cells`) for a point off the site."""
    row, column = ground_cells(site, np.asarray(users_xy, dtype=float).reshape(-1, 2))
    return site.walkable[row, column]


def check_walkable(site: Site, users_xy: np.ndarray, environment: str, where: str = "") -> None:
    """InputError of one line naming the first user (M, 2) that stands inside a building:
    ``{where}users[3]: (120.0, 45.0) is inside a building on site:/path``."""
    users = np.asarray(users_xy, dtype=float).reshape(-1, 2)
    inside = ~walkable_at(site, users)
    if inside.any():
        k = int(np.flatnonzero(inside)[0])
        x, y = (float(v) for v in users[k])
        raise InputError(
            f"{where}users[{k}]: ({x:.1f}, {y:.1f}) is inside a building on {environment}"
        )


def nearest_walkable_xy(
    site: Site, users_xy: np.ndarray, size_x_m: float, size_y_m: float
) -> np.ndarray:
    """The centre of the walkable cell nearest each point (M, 2), among the cells whose centre
    lies in the area ``[0, size_x_m] × [0, size_y_m]``: (M, 2). Ties go to the lowest cell in
    row-major order. InputError naming ``environment`` when the area has no walkable cell."""
    rows, columns = np.nonzero(site.walkable)
    centres = np.stack([(columns + 0.5) * site.cell_m, (rows + 0.5) * site.cell_m], axis=1)
    inside = (centres[:, 0] <= size_x_m) & (centres[:, 1] <= size_y_m)
    centres = centres[inside]
    if centres.size == 0:
        raise InputError("environment: the site has no walkable ground in the area")
    users = np.asarray(users_xy, dtype=float).reshape(-1, 2)
    gap = users[:, None, :] - centres[None, :, :]
    nearest = np.argmin(np.einsum("mcd,mcd->mc", gap, gap), axis=1)
    return centres[nearest]


def place_on_walkable(
    site: Site,
    users_xy: np.ndarray,
    redraw: Callable[[np.ndarray], np.ndarray],
    size_x_m: float,
    size_y_m: float,
    tries: int = PLACEMENT_TRIES,
) -> np.ndarray:
    """``users_xy`` (M, 2) with every user on walkable ground (module doc): each user inside a
    building is replaced by ``redraw(indices)`` (new positions (len(indices), 2) from the same
    layout, drawn from the caller's generator: deterministic per seed) until it lands on
    walkable ground, at most ``tries`` rounds, then moved to :func:`nearest_walkable_xy`.
    A new array; users already on walkable ground keep their positions exactly."""
    xy = np.array(users_xy, dtype=float).reshape(-1, 2)
    inside = np.flatnonzero(~walkable_at(site, xy))
    for _ in range(tries):
        if inside.size == 0:
            return xy
        xy[inside] = redraw(inside)
        inside = inside[~walkable_at(site, xy[inside])]
    if inside.size:
        xy[inside] = nearest_walkable_xy(site, xy[inside], size_x_m, size_y_m)
    return xy


def walkable_path(site: Site, start_xy: np.ndarray, end_xy: np.ndarray) -> bool:
    """Whether the straight segment from ``start_xy`` to ``end_xy`` (2,) stays on walkable
    ground: both ends and points at most half a cell apart between them. The ends must lie on
    the site (ValueError otherwise: callers keep users in the area)."""
    x0, y0 = (float(v) for v in start_xy)
    x1, y1 = (float(v) for v in end_xy)
    for x, y in ((x0, y0), (x1, y1)):
        if not (0.0 <= x <= site.size_x_m and 0.0 <= y <= site.size_y_m):
            raise ValueError(f"walkable_path: ({x}, {y}) is off the site")
    return bool(_path_kernel(site.walkable, float(site.cell_m), x0, y0, x1, y1))


@njit(cache=True, nogil=True)
def _path_kernel(
    walkable: np.ndarray, cell_m: float, x0: float, y0: float, x1: float, y1: float
) -> bool:
    """:func:`walkable_path` on the mask: the cells of ``samples`` evenly spaced points."""
    dx, dy = x1 - x0, y1 - y0
    samples = max(2, math.ceil(math.sqrt(dx * dx + dy * dy) / (0.5 * cell_m)) + 1)
    last_x, last_y = walkable.shape[1] - 1, walkable.shape[0] - 1
    for i in range(samples):
        t = i / (samples - 1)
        column = min(int((x0 + t * dx) // cell_m), last_x)
        row = min(int((y0 + t * dy) // cell_m), last_y)
        if not walkable[row, column]:
            return False
    return True
