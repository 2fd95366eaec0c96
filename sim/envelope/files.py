"""Envelope files (JSON, ``"format": "tupa-envelope/1"``), in the area frame (metres)::

    {
      "format": "tupa-envelope/1",
      "inclusion": [[0, 0], [500, 0], [500, 500], [0, 500]],   // optional: the area
      "floor_m": 25, "ceiling_m": 100,                          // optional: the area's band
      "clearance_m": 5,                                         // optional: 0
      "max_speed_mps": 10,                                      // optional: 10
      "exclusions": [                                           // optional: none
        {"name": "hospital helipad", "polygon": [[100, 100], [160, 100], [160, 150], [100, 150]],
         "floor_m": 0, "ceiling_m": 60}
      ]
    }

Polygons are lists of at least three [x, y] corners (closed implicitly), simple (not
self-intersecting). :func:`envelope_from_document` refuses, with one line naming the field, what
cannot be flown: a polygon that is not simple, an inclusion outside the area, a ceiling not above
the floor, an exclusion whose ceiling is not above its floor, exclusions (with the clearance)
that leave no legal point, unknown fields, more than :data:`MAX_EXCLUSION_CORNERS` exclusion
corners in all (routes are planned round every corner: their cost must stay bounded). Over a
site (``environment = site:NAME``) the site's buildings are exclusions too, after the
document's (:mod:`sim.envelope.buildings`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import shapely
from shapely.geometry import Polygon

from sim.config import AreaConfig
from sim.envelope.buildings import area_exclusions
from sim.envelope.volume import Envelope, Exclusion
from sim.errors import InputError

ENVELOPE_FORMAT = "tupa-envelope/1"
MAX_EXCLUSION_CORNERS = 1000
"""The most corners a document's exclusions may have in all (a site's buildings not counted)."""
_TOP_FIELDS = {
    "format",
    "inclusion",
    "floor_m",
    "ceiling_m",
    "clearance_m",
    "max_speed_mps",
    "exclusions",
}
_EXCLUSION_FIELDS = {"name", "polygon", "floor_m", "ceiling_m"}


def load_envelope(path: Path, area: AreaConfig) -> Envelope:
    """The envelope in the file at ``path`` for ``area``; InputError naming the file and the
    field for anything unreadable or unflyable."""
    try:
        document = json.loads(Path(path).read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read the envelope file ({exc.strerror})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not JSON ({exc})") from None
    try:
        return envelope_from_document(document, area)
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None


def area_envelope(area: AreaConfig) -> Envelope:
    """The envelope of a vehicle given none: the area's box and altitude band, and over a site
    its buildings (:mod:`sim.envelope.buildings`)."""
    return envelope_from_document({"format": ENVELOPE_FORMAT}, area)


def envelope_from_document(document: Any, area: AreaConfig) -> Envelope:
    """The envelope a parsed ``tupa-envelope/1`` document describes (see the module docstring),
    over a site with the site's buildings after the document's own exclusions
    (:func:`sim.envelope.buildings.area_exclusions`)."""
    if not isinstance(document, dict):
        raise InputError("not a JSON object")
    if document.get("format") != ENVELOPE_FORMAT:
        raise InputError(f"format: must be {ENVELOPE_FORMAT!r}, got {document.get('format')!r}")
    unknown = sorted(set(document) - _TOP_FIELDS)
    if unknown:
        raise InputError(f"{unknown[0]}: unknown field (known: {', '.join(sorted(_TOP_FIELDS))})")
    box = Polygon([(0, 0), (area.size_x_m, 0), (area.size_x_m, area.size_y_m), (0, area.size_y_m)])
    if "inclusion" in document:
        inclusion = _polygon(document["inclusion"], "inclusion")
        if not box.buffer(1e-6).covers(inclusion):
            raise InputError(
                f"inclusion: extends outside the area "
                f"(0..{area.size_x_m:g} x 0..{area.size_y_m:g} m)"
            )
    else:
        inclusion = box
    floor_m = _number(document, "floor_m", area.z_min_m)
    ceiling_m = _number(document, "ceiling_m", area.z_max_m)
    if ceiling_m <= floor_m:
        raise InputError(f"ceiling_m: {ceiling_m:g} m must be above floor_m {floor_m:g} m")
    clearance_m = _number(document, "clearance_m", 0.0, minimum=0.0)
    max_speed_mps = _number(document, "max_speed_mps", 10.0, minimum=0.0)
    if max_speed_mps <= 0:
        raise InputError("max_speed_mps: must be a positive number")
    raw = document.get("exclusions", [])
    if not isinstance(raw, list):
        raise InputError("exclusions: must be a list")
    corners = sum(
        len(entry["polygon"])
        for entry in raw
        if isinstance(entry, dict) and isinstance(entry.get("polygon"), list)
    )
    if corners > MAX_EXCLUSION_CORNERS:
        raise InputError(
            f"exclusions: {corners} corners in all, at most {MAX_EXCLUSION_CORNERS} "
            "(routes are planned round every corner)"
        )
    exclusions = tuple(_exclusion(entry, f"exclusions[{i}]") for i, entry in enumerate(raw))
    exclusions += area_exclusions(area, floor_m, ceiling_m)
    envelope = Envelope(inclusion, floor_m, ceiling_m, exclusions, clearance_m, max_speed_mps)
    _check_flyable(envelope)
    return envelope


def _number(
    document: dict[str, Any], name: str, default: float, minimum: float | None = None
) -> float:
    value = document.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise InputError(f"{name}: must be a finite number, got {value!r}")
    if minimum is not None and value < minimum:
        raise InputError(f"{name}: must be at least {minimum:g}, got {value!r}")
    return float(value)


def _polygon(raw: Any, where: str) -> Polygon:
    if not isinstance(raw, list) or len(raw) < 3:
        raise InputError(f"{where}: must be a list of at least 3 [x, y] corners")
    corners = []
    for i, corner in enumerate(raw):
        if (
            not isinstance(corner, list)
            or len(corner) != 2
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in corner)
            or not all(math.isfinite(v) for v in corner)
        ):
            raise InputError(f"{where}[{i}]: must be [x, y], two finite numbers, got {corner!r}")
        corners.append((float(corner[0]), float(corner[1])))
    polygon = Polygon(corners)
    if not polygon.is_valid:
        if shapely.area(shapely.convex_hull(polygon)) <= 0:
            raise InputError(f"{where}: has no area (its corners are in a line)")
        raise InputError(f"{where}: not a simple polygon ({shapely.is_valid_reason(polygon)})")
    return polygon


def _exclusion(raw: Any, where: str) -> Exclusion:
    if not isinstance(raw, dict):
        raise InputError(f"{where}: must be an object with polygon, floor_m and ceiling_m")
    unknown = sorted(set(raw) - _EXCLUSION_FIELDS)
    if unknown:
        raise InputError(f"{where}.{unknown[0]}: unknown field")
    name = raw.get("name", "")
    if not isinstance(name, str):
        raise InputError(f"{where}.name: must be a string")
    polygon = _polygon(raw.get("polygon"), f"{where}.polygon")
    floor_m = _number(raw, "floor_m", 0.0)
    if "ceiling_m" not in raw:
        raise InputError(f"{where}.ceiling_m: missing")
    ceiling_m = _number(raw, "ceiling_m", 0.0)
    if ceiling_m <= floor_m:
        raise InputError(f"{where}.ceiling_m: {ceiling_m:g} m must be above floor_m {floor_m:g} m")
    return Exclusion(polygon, floor_m, ceiling_m, name)


def _check_flyable(envelope: Envelope) -> None:
    """Refuse an envelope with no legal point: the inclusion (less the clearance) is empty, or
    exclusions spanning the whole altitude band cover it."""
    allowed = envelope.allowed_footprint
    if allowed.is_empty:
        raise InputError(
            f"clearance_m: {envelope.clearance_m:g} m leaves nothing of the inclusion to fly in"
        )
    covering = [
        i
        for i, (_, low, high) in enumerate(envelope.grown)
        if low < envelope.floor_m and high > envelope.ceiling_m
    ]
    if covering and shapely.union_all([envelope.grown[i][0] for i in covering]).covers(allowed):
        raise InputError(
            f"exclusions[{covering[0]}]: with the clearance, the exclusions cover the whole "
            "inclusion from floor to ceiling: nowhere is left to fly"
        )
