"""A site's buildings as exclusion volumes: what no vehicle flies into over a real district.

Every envelope over an area whose environment is a site (``site:NAME``, :mod:`sim.sites`) holds
the site's buildings as exclusions (:func:`sim.envelope.files.envelope_from_document` adds them
to whatever the document says), so the world's flight, the service's routes and the live map all
keep out of them. Contract of :func:`building_exclusions`:

* A ground cell's building height is the tallest of its sampled downward rays
  (:func:`sim.sites.build.ground_maps`); a cell *matters* when that height plus
  :data:`BUILDING_MARGIN_M` reaches the envelope's floor.
* The cells are stacked in layers :data:`LAYER_STEP_M` apart from the floor down by the margin:
  layer k holds the cells taller than its threshold t_k, each 4-connected group of them one
  exclusion from the ground to ``min(tallest cell of the group, t_{k+1})`` plus the margin. Every
  cell is thus covered up to its own height plus the margin (a layer caps a group only where the
  next layer goes on), never less; a group's lower cells may be covered up to one step higher.
* Each footprint is the union of its cells grown by the margin (square corners), then simplified
  with its corners moved at most :data:`SIMPLIFY_M` outward: the simplified polygon is used only
  when it covers the grown one (checked), so simplifying never gives anything back.

Pure and deterministic; the exclusions are built once per site, area and band
(:func:`area_exclusions`).
"""

from __future__ import annotations

import math
import weakref
from typing import TYPE_CHECKING

import numpy as np
import shapely
from shapely.geometry import Polygon

from sim.envelope.volume import Exclusion

if TYPE_CHECKING:
    from sim.config import AreaConfig
    from sim.sites.format import Site

__all__ = ["BUILDING_MARGIN_M", "LAYER_STEP_M", "area_exclusions", "building_exclusions"]

BUILDING_MARGIN_M = 5.0
"""How far a vehicle keeps from a building, sideways and above its roof (a cell's sampled
height misses a thin part up to a third of a 5 m cell; GNSS position error; the autopilot's
tracking error around a route's corners)."""
LAYER_STEP_M = 12.5
"""Height between two layers of exclusions (the site's traced UAV levels are 12.5 m apart)."""
SIMPLIFY_M = 1.0
"""How far outward a footprint's simplification may move its outline."""

_KEPT: dict[tuple[int, float, float, float, float], tuple[weakref.ref, tuple[Exclusion, ...]]] = {}


def building_exclusions(
    site: Site,
    size_x_m: float,
    size_y_m: float,
    floor_m: float,
    ceiling_m: float,
    margin_m: float = BUILDING_MARGIN_M,
) -> tuple[Exclusion, ...]:
    """The site's buildings over the area ``[0, size_x_m] × [0, size_y_m]`` that reach the band
    from ``floor_m`` (module docstring), lowest layer first, in the area frame."""
    cell_m = float(site.cell_m)
    cells_x = min(site.cells_x, math.ceil(size_x_m / cell_m - 1e-9))
    cells_y = min(site.cells_y, math.ceil(size_y_m / cell_m - 1e-9))
    height = np.asarray(site.building_height_m[:cells_y, :cells_x], dtype=float)
    threshold = floor_m - margin_m
    rows, columns = np.indices(height.shape)
    centres_x, centres_y = (columns + 0.5) * cell_m, (rows + 0.5) * cell_m
    exclusions: list[Exclusion] = []
    while threshold < ceiling_m and (height > threshold).any():
        following = threshold + LAYER_STEP_M
        tall = height > threshold
        x0, y0 = columns[tall] * cell_m, rows[tall] * cell_m
        cells = shapely.union_all(shapely.box(x0, y0, x0 + cell_m, y0 + cell_m))
        for group in shapely.get_parts(cells):  # the 4-connected groups
            inside = tall & shapely.contains_xy(group, centres_x, centres_y)
            tallest = float(height[inside].max())
            top = tallest if following >= ceiling_m else min(tallest, following)
            footprint = _grown(group, margin_m)
            x, y = footprint.centroid.x, footprint.centroid.y
            name = f"building at ({x:.0f}, {y:.0f}) m, {tallest:.0f} m tall"
            exclusions.append(
                Exclusion(footprint, 0.0, top + margin_m, name, on_autopilot_fence=False)
            )
        threshold = following
    return tuple(exclusions)


def _grown(cells: Polygon, margin_m: float) -> Polygon:
    grown = cells.buffer(margin_m, join_style="mitre")
    simpler = grown.buffer(SIMPLIFY_M, join_style="mitre").simplify(SIMPLIFY_M)
    if isinstance(simpler, Polygon) and simpler.is_valid and simpler.covers(grown):
        return simpler
    return grown


def area_exclusions(area: AreaConfig, floor_m: float, ceiling_m: float) -> tuple[Exclusion, ...]:
    """The buildings of the area's site reaching the band ``floor_m``–``ceiling_m``
    (:func:`building_exclusions`); none when the area's environment is not a site. Built once
    per loaded site, area and band. InputError (from :func:`sim.channel.area_site`) for a site
    that is missing, broken or does not cover the area."""
    from sim.channel import area_site

    site = area_site(area)
    if site is None:
        return ()
    key = (id(site), area.size_x_m, area.size_y_m, float(floor_m), float(ceiling_m))
    kept = _KEPT.get(key)
    if kept is not None and kept[0]() is site:
        return kept[1]
    exclusions = building_exclusions(site, area.size_x_m, area.size_y_m, floor_m, ceiling_m)
    _KEPT[key] = (weakref.ref(site, lambda _ref, k=key: _KEPT.pop(k, None)), exclusions)
    return exclusions
