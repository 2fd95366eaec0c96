"""What the operator view draws of a site (``environment`` ``site:PATH``, :mod:`sim.sites`).

Pure functions on a loaded :class:`~sim.sites.format.Site` and the service's area; numpy only:

* :func:`buildings_layer`: the buildings as a coarse height map over the area (the tallest
  building in each ``cell_m`` square, 0 where none), built once per service;
* :func:`coverage_layer`: the mean path loss from one UAV position to the centre of every
  ``cell_m`` square of the area (the site's lookup, :func:`sim.sites.lookup.path_loss_db`), None
  where no ray reaches it: what a vehicle covers from where it is, for each frame.

Both are flat row-major lists, the first row the southernmost (``y`` up), ``nx`` by ``ny``
squares from the area's south-west corner.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.config import AreaConfig
from sim.sites.format import Site
from sim.sites.lookup import path_loss_db

BUILDINGS_CELL_M = 10.0
"""The operator view's building squares: 2,500 over the default 500 m area."""
COVERAGE_CELL_M = 20.0
"""The coverage squares: 625 lookups a vehicle and frame over the default area."""


def _squares(area: AreaConfig, cell_m: float) -> tuple[int, int]:
    return max(1, round(area.size_x_m / cell_m)), max(1, round(area.size_y_m / cell_m))


def buildings_layer(
    site: Site, area: AreaConfig, cell_m: float = BUILDINGS_CELL_M
) -> dict[str, Any]:
    """``{"cell_m", "nx", "ny", "heights_m": [...]}``: the tallest building (metres, 0: none) in
    each ``cell_m`` square of the area (module doc)."""
    nx, ny = _squares(area, cell_m)
    heights = site.building_height_m  # (cells_y, cells_x), row 0 the southernmost
    per = max(1, round(cell_m / site.cell_m))
    out = np.zeros((ny, nx))
    for j in range(ny):
        for i in range(nx):
            block = heights[j * per : (j + 1) * per, i * per : (i + 1) * per]
            out[j, i] = float(block.max()) if block.size else 0.0
    return {
        "cell_m": cell_m,
        "nx": nx,
        "ny": ny,
        "heights_m": [round(float(h), 1) for h in out.ravel()],
    }


def coverage_layer(
    site: Site,
    area: AreaConfig,
    position_m: tuple[float, float, float],
    cell_m: float = COVERAGE_CELL_M,
) -> dict[str, Any]:
    """``{"cell_m", "nx", "ny", "loss_db": [... or None]}``: the mean path loss from a UAV at
    ``position_m`` (area frame, inside the site's UAV grid after clamping into it) to the
    centre of each ``cell_m`` square, None where no path (module doc)."""
    nx, ny = _squares(area, cell_m)
    xs = (np.arange(nx) + 0.5) * cell_m
    ys = (np.arange(ny) + 0.5) * cell_m
    gx, gy = np.meshgrid(xs, ys)  # row j: y = ys[j]
    centres = np.stack([gx.ravel(), gy.ravel()], axis=1)
    uav = np.array(
        [
            min(max(position_m[0], site.uav_x_m[0]), site.uav_x_m[-1]),
            min(max(position_m[1], site.uav_y_m[0]), site.uav_y_m[-1]),
            min(max(position_m[2], site.uav_z_m[0]), site.uav_z_m[-1]),
        ]
    )
    loss = path_loss_db(site, uav, centres)
    return {
        "cell_m": cell_m,
        "nx": nx,
        "ny": ny,
        "loss_db": [round(float(v), 1) if np.isfinite(v) else None for v in loss],
    }
