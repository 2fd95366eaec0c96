"""The flight-safety envelope of one vehicle, and whether a point or a straight segment is in it.

An :class:`Envelope` is, in the area frame (x east, y north, z up, metres):

* an **inclusion** polygon (the vehicle never leaves it; by default the area's rectangle),
* **exclusion volumes**: polygons with a floor and a ceiling height (no-fly zones; over a site,
  the buildings), the vehicle never enters,
* an altitude **floor** and **ceiling**,
* a **clearance**: the least distance kept from the inclusion's boundary and from every
  exclusion volume (horizontally from its footprint within its height band widened by the
  clearance, and vertically from its floor and ceiling above or below the footprint),
* a **maximum speed** (what the flight model and the autopilot are told; not a geometric test).

A point is *legal* when it is inside the inclusion shrunk by the clearance, within the altitude
band, and outside every exclusion grown by the clearance. A segment is legal when every point of
it is (:meth:`Envelope.segment_violation` decides it exactly, without sampling); a *leg* is
legal when every path an autopilot may fly between its ends is (:meth:`Envelope.leg_violation`:
height and position are reached at separate speeds). Geometry is
shapely's; the checks are pure and thread-safe.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import shapely
from shapely.geometry import LineString, Point, Polygon
from shapely.prepared import PreparedGeometry, prep

from sim.config import AreaConfig

Vec3 = tuple[float, float, float]

EDGE_EPS_M = 1e-6
"""Tolerance of the legality tests, always on the safe side of an exclusion: a point this close
to a grown exclusion footprint (within its band) counts as inside it. The inclusion and the
altitude band allow it (a target on the area's edge is legal)."""


@dataclass(frozen=True)
class Exclusion:
    """A volume the vehicle never enters: a footprint between two heights (area frame)."""

    footprint: Polygon
    floor_m: float
    ceiling_m: float
    name: str = ""
    on_autopilot_fence: bool = True
    """Whether ``--autopilot-fence`` puts it on the autopilot (as a full-height column). A
    site's buildings are not: dozens of polygons an autopilot may not hold, every one a column
    where the service's routes fly over the low ones; the routes keep out of them at their
    heights."""

    def band_m(self, clearance_m: float) -> tuple[float, float]:
        """The heights in which the footprint grown by ``clearance_m`` is forbidden."""
        return self.floor_m - clearance_m, self.ceiling_m + clearance_m


@dataclass(frozen=True)
class Envelope:
    """One vehicle's envelope (see the module docstring). Build it with :meth:`for_area` or
    :func:`sim.envelope.files.load_envelope`; the constructor checks only what geometry needs."""

    inclusion: Polygon
    floor_m: float
    ceiling_m: float
    exclusions: tuple[Exclusion, ...] = ()
    clearance_m: float = 0.0
    max_speed_mps: float = 10.0
    _unions: dict[tuple[int, ...], shapely.Geometry] = field(
        default_factory=dict, compare=False, repr=False
    )
    _trees: dict[tuple[int, ...], shapely.STRtree] = field(
        default_factory=dict, compare=False, repr=False
    )
    _free: dict[tuple[tuple[int, ...], float], shapely.Geometry] = field(
        default_factory=dict, compare=False, repr=False
    )
    graphs: dict[tuple[tuple[int, ...], float], object] = field(
        default_factory=dict, compare=False, repr=False
    )
    """Kept by :mod:`sim.envelope.paths`: the corners' visibility graph per set of exclusions."""

    @classmethod
    def for_area(
        cls,
        area: AreaConfig,
        exclusions: Sequence[Exclusion] = (),
        clearance_m: float = 0.0,
        max_speed_mps: float = 10.0,
    ) -> Envelope:
        """The area's rectangle and altitude band, with ``exclusions``."""
        box = Polygon(
            [(0, 0), (area.size_x_m, 0), (area.size_x_m, area.size_y_m), (0, area.size_y_m)]
        )
        return cls(box, area.z_min_m, area.z_max_m, tuple(exclusions), clearance_m, max_speed_mps)

    # ------------------------------------------------------------------ derived geometry

    @cached_property
    def allowed_footprint(self) -> Polygon:
        """The inclusion shrunk by the clearance: where the vehicle's x, y may be."""
        if not self.clearance_m:
            return self.inclusion
        return self.inclusion.buffer(-self.clearance_m, join_style="mitre")

    @cached_property
    def _allowed_prepared(self) -> PreparedGeometry:
        return prep(self.allowed_footprint.buffer(EDGE_EPS_M))

    @cached_property
    def grown(self) -> tuple[tuple[Polygon, float, float], ...]:
        """Each exclusion's footprint grown by the clearance, with its widened height band. The
        corners stay square (mitred): at a convex corner a little more than the clearance is
        kept, never less, and the footprint keeps its few corners (the paths' graph nodes)."""
        c = self.clearance_m
        return tuple(
            (e.footprint.buffer(c, join_style="mitre") if c else e.footprint, *e.band_m(c))
            for e in self.exclusions
        )

    @cached_property
    def _grown_prepared(self) -> tuple[PreparedGeometry, ...]:
        # Grown by the tolerance: a point on (or just off) a grown footprint is inside it.
        return tuple(prep(g.buffer(EDGE_EPS_M, join_style="mitre")) for g, _, _ in self.grown)

    @cached_property
    def _raw_prepared(self) -> tuple[PreparedGeometry, ...]:
        return tuple(prep(e.footprint) for e in self.exclusions)

    # ------------------------------------------------------------------ checks

    def violation(self, xyz_m: Sequence[float]) -> str | None:
        """Why the point is not legal (one line naming what it breaks), or None."""
        x_m, y_m, z_m = (float(v) for v in xyz_m)
        if not all(math.isfinite(v) for v in (x_m, y_m, z_m)):
            return "not a finite point"
        if z_m < self.floor_m - EDGE_EPS_M:
            return f"z {z_m:.1f} m below the floor {self.floor_m:.1f} m"
        if z_m > self.ceiling_m + EDGE_EPS_M:
            return f"z {z_m:.1f} m above the ceiling {self.ceiling_m:.1f} m"
        point = Point(x_m, y_m)
        if not self._allowed_prepared.covers(point):
            return f"({x_m:.1f}, {y_m:.1f}) outside the inclusion (less {self.clearance_m:g} m)"
        for (_, low, high), prepared, exclusion in zip(
            self.grown, self._grown_prepared, self.exclusions, strict=True
        ):
            if low < z_m < high and prepared.intersects(point):
                return (
                    f"inside exclusion {_label(exclusion)} (with {self.clearance_m:g} m clearance)"
                )
        return None

    def segment_violation(self, start_m: Sequence[float], end_m: Sequence[float]) -> str | None:
        """Why the straight flight from ``start_m`` to ``end_m`` is not legal, or None. Exact:
        z is linear along the segment, so each exclusion forbids one sub-segment's footprint."""
        for end in (start_m, end_m):
            if (why := self.violation(end)) is not None:
                return f"end {tuple(round(float(v), 1) for v in end)}: {why}"
        a = tuple(float(v) for v in start_m)
        b = tuple(float(v) for v in end_m)
        if (a[0], a[1]) != (b[0], b[1]):
            line = LineString([(a[0], a[1]), (b[0], b[1])])
            if not self._allowed_prepared.covers(line):
                return "leaves the inclusion (less its clearance) on the way"
        for (_, low, high), prepared, exclusion in zip(
            self.grown, self._grown_prepared, self.exclusions, strict=True
        ):
            piece = _within_band(a, b, low, high)
            if piece is None:
                continue
            p, q = piece
            geometry = Point(p) if p == q else LineString([p, q])
            if prepared.intersects(geometry):
                return f"crosses exclusion {_label(exclusion)} on the way"
        return None

    def leg_violation(self, start_m: Sequence[float], end_m: Sequence[float]) -> str | None:
        """Why flying from ``start_m`` to ``end_m`` *as an autopilot flies it* is not legal, or
        None: :meth:`segment_violation`, and :meth:`wall_crossing` (a multirotor's position
        controller caps horizontal and vertical speed separately, so a leg that climbs or
        descends while it moves may reach its height first or its position first)."""
        if (why := self.segment_violation(start_m, end_m)) is not None:
            return why
        return self.wall_crossing(start_m, end_m)

    def wall_crossing(
        self, start_m: Sequence[float], end_m: Sequence[float], clearance: bool = True
    ) -> str | None:
        """Which exclusion the vertical *wall* over the leg's footprint, between its two
        heights, meets (every path an autopilot flies between the ends lies in it), or None.
        The ends themselves are not checked (a vehicle just outside its envelope may use it to
        find its way back in); ``clearance=False``: the exclusions themselves, not grown by the
        clearance (the way out of a clearance zone)."""
        a = tuple(float(v) for v in start_m)
        b = tuple(float(v) for v in end_m)
        low_z, high_z = min(a[2], b[2]), max(a[2], b[2])
        if (a[0], a[1]) == (b[0], b[1]):
            footprint: shapely.Geometry = Point(a[0], a[1])
        else:
            footprint = LineString([(a[0], a[1]), (b[0], b[1])])
        bands = (
            self.grown
            if clearance
            else tuple((e.footprint, e.floor_m, e.ceiling_m) for e in self.exclusions)
        )
        solids = self._grown_prepared if clearance else self._raw_prepared
        for (_, low, high), prepared, exclusion in zip(bands, solids, self.exclusions, strict=True):
            overlaps = low < high_z and high > low_z if high_z > low_z else low < low_z < high
            if overlaps and prepared.intersects(footprint):
                return (
                    f"may cross exclusion {_label(exclusion)} on the way (the autopilot climbs "
                    "or descends and moves at separate speeds)"
                )
        return None

    def region_violation(
        self, footprint: shapely.Geometry, low_z_m: float, high_z_m: float
    ) -> str | None:
        """Why the column over ``footprint`` (area frame) between ``low_z_m`` and ``high_z_m`` is
        not all legal, or None: it leaves the allowed footprint, leaves the altitude band, or
        meets an exclusion grown by the clearance whose band overlaps its heights."""
        if low_z_m < self.floor_m - EDGE_EPS_M or high_z_m > self.ceiling_m + EDGE_EPS_M:
            return f"heights {low_z_m:.1f}-{high_z_m:.1f} m leave the altitude band"
        if not self._allowed_prepared.covers(footprint):
            return "leaves the inclusion (less its clearance)"
        for (_, low, high), prepared, exclusion in zip(
            self.grown, self._grown_prepared, self.exclusions, strict=True
        ):
            if low < high_z_m and high > low_z_m and prepared.intersects(footprint):
                return f"meets exclusion {_label(exclusion)}"
        return None

    def blocking(self, start_m: Sequence[float], end_m: Sequence[float]) -> list[int]:
        """The indices of the exclusions the straight segment crosses (see
        :meth:`segment_violation`)."""
        a = tuple(float(v) for v in start_m)
        b = tuple(float(v) for v in end_m)
        found = []
        for i, ((_, low, high), prepared) in enumerate(
            zip(self.grown, self._grown_prepared, strict=True)
        ):
            piece = _within_band(a, b, low, high)
            if piece is None:
                continue
            p, q = piece
            if prepared.intersects(Point(p) if p == q else LineString([p, q])):
                found.append(i)
        return found

    def obstacles_at(self, z_m: float) -> list[int]:
        """The exclusions whose (widened) height band contains ``z_m``."""
        return [i for i, (_, low, high) in enumerate(self.grown) if low < z_m < high]

    @cached_property
    def room(self) -> shapely.Geometry:
        """The allowed footprint, by the tolerance wider, prepared (for vectorised tests)."""
        room = self.allowed_footprint.buffer(EDGE_EPS_M, join_style="mitre")
        shapely.prepare(room)
        return room

    def solid_tree(self, active: tuple[int, ...]) -> shapely.STRtree:
        """A spatial index of the ``active`` exclusions' grown footprints, by the tolerance
        wider (as the point test has them), kept per set of exclusions."""
        if active not in self._trees:
            solids = [self.grown[i][0].buffer(EDGE_EPS_M, join_style="mitre") for i in active]
            self._trees[active] = shapely.STRtree(solids)
        return self._trees[active]

    def union_at(self, z_m: float) -> shapely.Geometry:
        """The grown footprints forbidden at height ``z_m``, as one geometry (maybe empty);
        kept per set of exclusions (as many as there are distinct height bands, at most)."""
        key = tuple(self.obstacles_at(z_m))
        if key not in self._unions:
            parts = [self.grown[i][0] for i in key]
            self._unions[key] = shapely.union_all(parts) if parts else Polygon()
        return self._unions[key]

    def tops_at(self, point: Point, z_m: float) -> list[float]:
        """The tops (the clearance-widened bands' highs) of the exclusions that forbid ``point``
        (x, y) at height ``z_m``, as :meth:`violation` finds them."""
        return [
            high
            for (_, low, high), prepared in zip(self.grown, self._grown_prepared, strict=True)
            if low < z_m < high and prepared.intersects(point)
        ]

    def free_at(self, z_m: float, margin_m: float) -> shapely.Geometry:
        """The allowed footprint less every grown footprint forbidden at height ``z_m`` widened
        by ``margin_m`` (square corners): where a point at that height may go sideways; kept
        per set of exclusions and margin."""
        key = (tuple(self.obstacles_at(z_m)), margin_m)
        if key not in self._free:
            solid = self.union_at(z_m)
            if not solid.is_empty:
                solid = solid.buffer(margin_m, join_style="mitre")
            self._free[key] = self.allowed_footprint.difference(solid)
        return self._free[key]


def home_violation(envelope: Envelope, home_xy_m: Sequence[float]) -> str | None:
    """Why a vehicle cannot take off from ``home_xy_m`` (area frame): its take-off climbs
    straight up through an exclusion volume (grown by the clearance) below the ceiling; None
    when it can."""
    x_m, y_m = (float(v) for v in home_xy_m)
    point = Point(x_m, y_m)
    for (_, low, _high), prepared, exclusion in zip(
        envelope.grown, envelope._grown_prepared, envelope.exclusions, strict=True
    ):
        if low < envelope.ceiling_m and prepared.intersects(point):
            return (
                f"home ({x_m:.1f}, {y_m:.1f}) is inside exclusion {_label(exclusion)} "
                f"(with {envelope.clearance_m:g} m clearance): the take-off would climb through it"
            )
    return None


def _label(exclusion: Exclusion) -> str:
    return repr(exclusion.name) if exclusion.name else "(unnamed)"


def _within_band(
    a: Vec3, b: Vec3, low: float, high: float
) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The x, y of the part of segment ``a``-``b`` whose z lies strictly inside (low, high),
    as its two ends (equal for a single point), or None when no part does."""
    za, zb = a[2], b[2]
    if za == zb:
        if not low < za < high:
            return None
        return (a[0], a[1]), (b[0], b[1])
    t_low = (low - za) / (zb - za)
    t_high = (high - za) / (zb - za)
    t0, t1 = max(0.0, min(t_low, t_high)), min(1.0, max(t_low, t_high))
    if t0 >= t1:
        return None

    def at(t: float) -> tuple[float, float]:
        return (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t)

    return at(t0), at(t1)
