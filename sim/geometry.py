"""The area's geometry, one home for it: the flight volume, the unit cube of the coordinates
action, the zone grid and the discrete moves. Pure functions shared by the environments, the
baselines, the evaluation and the service (its geofence and its decisions).

**The volume** is ``x in [0, size_x_m]``, ``y in [0, size_y_m]``, ``z in [z_min_m, z_max_m]``
(area frame, metres; :class:`sim.config.AreaConfig`). :func:`clip_to_volume` clips arrays of
points into it; :func:`clamp_point` is the geofence's one-point form, which also refuses
non-finite targets.

**The coordinates action** (DDPG) is a point of ``[0, 1]³`` mapped linearly onto the volume
(:func:`unit_to_m`, inverse :func:`m_to_unit`, which maps every altitude to 0 when the
height range is zero).

**The zone grid**: the area is cut into ``zone_m`` squares (20 × 20 for the paper's 500 m area
and 25 m zones) and ``n_levels_z`` altitude levels ``zone_m`` apart from ``z_min_m``. A grid
index ``(ix, iy, iz)`` stands for the point at the centre of zone ``(ix, iy)``, at altitude
``z_min_m + iz · zone_m``.
The 13 discrete moves (:data:`MOVES`) step the index by ±1 or ±5 along one axis, or stay.

**Actions become targets here** (:func:`move_target`, :func:`unit_to_m`). A discrete move applies
to the zone the vehicle is *in now*, not to the previous target: the policy sees the vehicle where
it is (the observation is built at the vehicle's position), so "east 1" must mean one zone east of
*that*. Each decision replaces the target while the vehicle chases it; a policy that keeps
choosing "east" flies east at full speed, "stay" stops it at the centre of its zone. Under the
paper's protocol the vehicle is always at its target zone's centre, so this is exactly the
paper's move.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from functools import lru_cache

import numpy as np

from sim.config import AreaConfig

# (dx, dy, dz) in zones for each discrete action; index 0 is "stay".
MOVES: np.ndarray = np.array(
    [
        (0, 0, 0),
        (1, 0, 0),
        (-1, 0, 0),
        (0, 1, 0),
        (0, -1, 0),
        (0, 0, 1),
        (0, 0, -1),
        (5, 0, 0),
        (-5, 0, 0),
        (0, 5, 0),
        (0, -5, 0),
        (0, 0, 5),
        (0, 0, -5),
    ],
    dtype=np.int64,
)
_MOVE_STEPS: tuple[tuple[int, int, int], ...] = tuple(map(tuple, MOVES.tolist()))
MOVE_NAMES: tuple[str, ...] = (
    "stay",
    "east 1",
    "west 1",
    "north 1",
    "south 1",
    "up 1",
    "down 1",
    "east 5",
    "west 5",
    "north 5",
    "south 5",
    "up 5",
    "down 5",
)


def grid_shape(area: AreaConfig) -> np.ndarray:
    """``(n_zones_x, n_zones_y, n_levels_z)`` as an int array."""
    return np.array([area.n_zones_x, area.n_zones_y, area.n_levels_z], dtype=np.int64)


def zone_index(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """The grid index of the zone holding ``xyz_m`` (nearest level in z), clipped to the grid."""
    if type(xyz_m) is np.ndarray and xyz_m.dtype == np.float64 and xyz_m.shape == (3,):
        index = _zone_tuple(*xyz_m.tolist(), area)
        if index is not None:
            return np.array(index, dtype=np.int64)
    raw = np.array(
        [
            np.floor(xyz_m[0] / area.zone_m),
            np.floor(xyz_m[1] / area.zone_m),
            np.rint((xyz_m[2] - area.z_min_m) / area.zone_m),
        ]
    ).astype(np.int64)
    return np.clip(raw, 0, grid_shape(area) - 1)


def _zone_tuple(x: float, y: float, z: float, area: AreaConfig) -> tuple[int, int, int] | None:
    """:func:`zone_index` on Python floats (the same arithmetic as numpy's, less overhead);
    None for coordinates that are not finite or too large for int64 (the array way has them)."""
    qx, qy, qz = x / area.zone_m, y / area.zone_m, (z - area.z_min_m) / area.zone_m
    if not abs(qx) + abs(qy) + abs(qz) < _EXACT:
        return None
    n_x, n_y, n_z = _grid_dims(area)
    ix, iy, iz = math.floor(qx), math.floor(qy), round(qz)  # round: half to even
    return min(max(ix, 0), n_x - 1), min(max(iy, 0), n_y - 1), min(max(iz, 0), n_z - 1)


def zone_position(index: np.ndarray, area: AreaConfig) -> np.ndarray:
    """The point a grid index stands for (zone centre, level altitude), metres."""
    if type(index) is np.ndarray and index.ndim == 1 and index.dtype.kind in "iu":
        index = index.tolist()  # Python ints: the same arithmetic, less overhead
    return np.array(
        [
            (index[0] + 0.5) * area.zone_m,
            (index[1] + 0.5) * area.zone_m,
            area.z_min_m + index[2] * area.zone_m,
        ]
    )


def move_mask(index: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Boolean (13,): the moves from ``index`` that stay on the grid (``stay`` always)."""
    if type(index) is np.ndarray and index.shape == (3,) and index.dtype.kind == "i":
        ix, iy, iz = index.tolist()
        n_x, n_y, n_z = _grid_dims(area)
        if 0 <= ix < n_x and 0 <= iy < n_y and 0 <= iz < n_z:
            return _mask_table(area)[ix, iy, iz].copy()
    landing = np.asarray(index) + MOVES
    return np.all((landing >= 0) & (landing < grid_shape(area)), axis=1)


# Grid coordinates below this (sum of magnitudes) floor and round the same in Python and numpy.
_EXACT = 2.0**52
# Up to this many rows (a fleet), the functions of many vehicles work on Python floats and ints
# with the scalar functions' arithmetic: numpy's per-call cost is more than the work.
SCALAR_ROWS = 8


@lru_cache(maxsize=16)
def _grid_dims(area: AreaConfig) -> tuple[int, int, int]:
    return area.n_zones_x, area.n_zones_y, area.n_levels_z


@lru_cache(maxsize=8)
def _mask_table(area: AreaConfig) -> np.ndarray:
    """Bool (n_x, n_y, n_z, 13): the moves that stay on the grid from every zone index."""
    shape = grid_shape(area)
    index = np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), axis=-1)
    landing = index[..., None, :] + MOVES
    table = np.all((landing >= 0) & (landing < shape), axis=-1)
    table.setflags(write=False)  # cached: callers get copies
    return table


# --------------------------------------------------------------------------------------------
# The volume


def volume_bounds(area: AreaConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(lower, upper)`` corners of the UAV's volume of ``area``, metres."""
    return (
        np.array([0.0, 0.0, area.z_min_m]),
        np.array([area.size_x_m, area.size_y_m, area.z_max_m]),
    )


def clip_to_volume(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """``xyz_m`` (…, 3) clipped into the UAV's volume of ``area``."""
    lower, upper = volume_bounds(area)
    return np.clip(np.asarray(xyz_m, dtype=float), lower, upper)


def clamp_point(
    target_m: Sequence[float], area: AreaConfig
) -> tuple[tuple[float, float, float], bool]:
    """The geofence: an area-frame target ``(x_m, y_m, z_m)`` clamped into the volume.

    Returns ``(clamped, was_clamped)``. Raises ValueError for a target that is not three finite
    numbers (it has no nearest point inside).
    """
    if len(target_m) != 3:
        raise ValueError(f"target must be (x_m, y_m, z_m), got {target_m!r}")
    x_m, y_m, z_m = (float(v) for v in target_m)
    if not all(math.isfinite(v) for v in (x_m, y_m, z_m)):
        raise ValueError(f"target must be finite, got {(x_m, y_m, z_m)!r}")
    clamped = (
        min(max(x_m, 0.0), area.size_x_m),
        min(max(y_m, 0.0), area.size_y_m),
        min(max(z_m, area.z_min_m), area.z_max_m),
    )
    return clamped, clamped != (x_m, y_m, z_m)


# --------------------------------------------------------------------------------------------
# The coordinates action and the discrete moves: actions become targets


def move_target(
    move: int, vehicle_xyz_m: np.ndarray, area: AreaConfig, index: np.ndarray | None = None
) -> tuple[np.ndarray, bool]:
    """The target of discrete ``move`` taken where the vehicle is: ``(target, refused)``.

    The move steps the index of the zone holding the vehicle (:func:`zone_index`;
    ``index`` when the caller has it already); a move that would leave the volume is refused
    and the target is that zone's centre (as "stay"). See the module doc for why moves apply to the
    vehicle's zone.
    """
    if index is None:
        index = zone_index(np.asarray(vehicle_xyz_m, dtype=float), area)
    refused = not bool(move_mask(index, area)[move])
    if refused:
        return zone_position(index, area), True
    return zone_position(index + MOVES[move], area), False


def valid_moves(vehicle_xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Boolean (13,): the moves :func:`move_target` accepts from where the vehicle is."""
    return move_mask(zone_index(np.asarray(vehicle_xyz_m, dtype=float), area), area)


def unit_to_m(action: np.ndarray, area: AreaConfig) -> np.ndarray:
    """The target of an absolute-coordinates action (x, y, z) in [0, 1]³, metres."""
    a = np.clip(np.asarray(action, dtype=float).reshape(3), 0.0, 1.0)
    return np.array(
        [
            a[0] * area.size_x_m,
            a[1] * area.size_y_m,
            area.z_min_m + a[2] * (area.z_max_m - area.z_min_m),
        ]
    )


def m_to_unit(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Inverse of :func:`unit_to_m` (float64, clipped to [0, 1])."""
    span_z = area.z_max_m - area.z_min_m
    action = np.array(
        [
            xyz_m[0] / area.size_x_m,
            xyz_m[1] / area.size_y_m,
            (xyz_m[2] - area.z_min_m) / span_z if span_z > 0 else 0.0,
        ]
    )
    return np.clip(action, 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# The same over (E, 3) arrays, for the vectorised environment: row e is the scalar function's
# result exactly


def zone_indices(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """:func:`zone_index` of each row of ``xyz_m`` (E, 3): int64 (E, 3)."""
    xyz = np.asarray(xyz_m, dtype=float)
    if xyz.ndim == 2 and len(xyz) <= SCALAR_ROWS:  # a fleet: Python floats, one array
        rows = [_zone_tuple(x, y, z, area) for x, y, z in xyz.tolist()]
        if None not in rows:
            return np.array(rows, dtype=np.int64).reshape(len(xyz), 3)
    raw = np.empty(xyz.shape, dtype=np.int64)
    raw[:, 0] = np.floor(xyz[:, 0] / area.zone_m)
    raw[:, 1] = np.floor(xyz[:, 1] / area.zone_m)
    raw[:, 2] = np.rint((xyz[:, 2] - area.z_min_m) / area.zone_m)  # half to even, as round()
    return np.clip(raw, 0, grid_shape(area) - 1)


def zone_positions(index: np.ndarray, area: AreaConfig) -> np.ndarray:
    """:func:`zone_position` of each row of ``index`` (E, 3): metres (E, 3)."""
    out = np.empty(index.shape, dtype=float)
    out[:, 0] = (index[:, 0] + 0.5) * area.zone_m
    out[:, 1] = (index[:, 1] + 0.5) * area.zone_m
    out[:, 2] = area.z_min_m + index[:, 2] * area.zone_m
    return out


def move_masks(index: np.ndarray, area: AreaConfig) -> np.ndarray:
    """Bool (E, 13) move masks of zone indices (E, 3), looked up in the grid's table."""
    return _mask_table(area)[index[:, 0], index[:, 1], index[:, 2]]


def valid_moves_many(xyz_m: np.ndarray, area: AreaConfig) -> np.ndarray:
    """:func:`valid_moves` of each row of ``xyz_m`` (E, 3): bool (E, 13)."""
    return move_masks(zone_indices(xyz_m, area), area)


def move_targets(
    moves: np.ndarray, xyz_m: np.ndarray, area: AreaConfig, index: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`move_target` of each environment: targets (E, 3), refused (E,).

    ``moves`` (E,) are valid move numbers; ``index`` the vehicles' zone indices when known."""
    if index is None:
        index = zone_indices(xyz_m, area)
    if len(index) <= SCALAR_ROWS:  # a fleet: move_target's arithmetic on Python ints
        table, zone_m, z_min_m = _mask_table(area), area.zone_m, area.z_min_m
        targets, refused = [], []
        for (ix, iy, iz), move in zip(index.tolist(), np.asarray(moves).tolist(), strict=True):
            allowed = bool(table[ix, iy, iz, move])
            if allowed:
                dx, dy, dz = _MOVE_STEPS[move]
                ix, iy, iz = ix + dx, iy + dy, iz + dz
            targets.append(((ix + 0.5) * zone_m, (iy + 0.5) * zone_m, z_min_m + iz * zone_m))
            refused.append(not allowed)
        return np.array(targets, dtype=float).reshape(len(index), 3), np.array(refused, dtype=bool)
    landing = index + MOVES[moves]
    allowed = np.all((landing >= 0) & (landing < grid_shape(area)), axis=1)
    landing[~allowed] = index[~allowed]
    return zone_positions(landing, area), ~allowed


def unit_to_m_many(actions: np.ndarray, area: AreaConfig) -> np.ndarray:
    """:func:`unit_to_m` of each row of ``actions`` (E, 3): metres (E, 3)."""
    a = np.clip(np.asarray(actions, dtype=float), 0.0, 1.0)
    out = np.empty(a.shape)
    out[:, 0] = a[:, 0] * area.size_x_m
    out[:, 1] = a[:, 1] * area.size_y_m
    out[:, 2] = area.z_min_m + a[:, 2] * (area.z_max_m - area.z_min_m)
    return out


# --------------------------------------------------------------------------------------------
# Several vehicles: the minimum separation between them, a hard constraint on every set of
# targets (and on where a fleet's vehicles end a decision period)

# Pushes aim this much past the separation, so that rounding never leaves a pair just short.
_SEPARATION_MARGIN = 1.0 + 1e-9
# Directions tried around a conflicting point, in this order: the 26 of a 3 × 3 × 3 cube.
_PUSH_DIRECTIONS = np.array(
    [
        (dx, dy, dz)
        for dz in (1, 0, -1)
        for dy in (0, 1, -1)
        for dx in (0, 1, -1)
        if (dx, dy, dz) != (0, 0, 0)
    ],
    dtype=float,
)
_PUSH_DIRECTIONS /= np.linalg.norm(_PUSH_DIRECTIONS, axis=1, keepdims=True)


def min_pairwise_distance_m(xyz_m: np.ndarray) -> float:
    """The smallest 3-D distance between two rows of ``xyz_m`` (K, 3); ``inf`` for K < 2."""
    return _min_distance(np.asarray(xyz_m, dtype=float).reshape(-1, 3).tolist())


def _min_distance(points: list[list[float]]) -> float:
    """:func:`min_pairwise_distance_m` of points as lists of floats (K is small, a fleet:
    plain floats beat numpy here)."""
    closest = math.inf
    for i, p in enumerate(points):
        for q in points[i + 1 :]:
            closest = min(closest, math.dist(p, q))
    return closest


@lru_cache(maxsize=8)
def _permutations(k: int) -> np.ndarray:
    return np.array(list(itertools.permutations(range(k))), dtype=np.intp).reshape(-1, k)


def assign_targets(positions_m: np.ndarray, targets_m: np.ndarray) -> np.ndarray:
    """``targets_m`` (K, 3) reordered so that row i is vehicle i's: the order with the least
    total 3-D flight distance from ``positions_m`` (K, 3); ties go to the first permutation in
    lexicographic order (so the identity wins among equals). Exact: K! orders, K <= 8."""
    positions = np.asarray(positions_m, dtype=float)
    targets = np.asarray(targets_m, dtype=float)
    if positions.shape != targets.shape or positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions_m and targets_m: must both be (K, 3), got "
                         f"{positions.shape} and {targets.shape}")  # fmt: skip
    k = len(targets)
    if k <= 1:
        return targets.copy()
    if k > 8:
        raise ValueError(f"positions_m: at most 8 vehicles, got {k}")
    cost = np.linalg.norm(positions[:, None, :] - targets[None, :, :], axis=-1)  # vehicle × target
    orders = _permutations(k)
    totals = cost[np.arange(k), orders].sum(axis=1)
    return targets[orders[int(np.argmin(totals))]]


def enforce_separation(targets_m: np.ndarray, separation_m: float, area: AreaConfig) -> np.ndarray:
    """Targets (K, 3) moved as little as this simple rule allows so that every two are at
    least ``separation_m`` apart in 3-D, all inside the volume of ``area``.

    Deterministic, in index order: target 0 is kept (clipped into the volume); each next
    target is kept if it is far enough from every target already settled, otherwise it moves
    to the nearest point (to where it wanted to be) among candidates that are: on the sphere
    of radius ``separation_m`` around each settled target it conflicts with, in its own
    direction and in 26 fixed directions, and, failing those, on a lattice of spacing
    ``separation_m`` around it; every candidate is clipped into the volume before it is
    checked, so no target ever leaves the volume. Lower indices have priority: a fleet lists
    its vehicles in a fixed order. Raises ``ValueError`` when the volume cannot hold the
    targets that far apart, and for non-finite targets or a separation that is not > 0.
    """
    if not (math.isfinite(separation_m) and separation_m > 0):
        raise ValueError(f"separation_m: must be > 0, got {separation_m!r}")
    targets = np.asarray(targets_m, dtype=float)
    points = targets.tolist() if targets.ndim == 2 and targets.shape[1] == 3 else None
    if points is None or not all(map(math.isfinite, itertools.chain.from_iterable(points))):
        raise ValueError(f"targets_m: must be (K, 3) finite positions, got shape {targets.shape}")
    # K is small (a fleet): the common case, already inside and apart, on Python floats.
    low_z, high_x, high_y, high_z = area.z_min_m, area.size_x_m, area.size_y_m, area.z_max_m
    if all(0.0 <= x <= high_x and 0.0 <= y <= high_y and low_z <= z <= high_z
           for x, y, z in points):  # fmt: skip
        wanted = targets.copy()
        if _min_distance(points) >= separation_m:
            return wanted
    else:
        wanted = clip_to_volume(targets, area)
        if min_pairwise_distance_m(wanted) >= separation_m:
            return wanted
    out = wanted.copy()
    reach = separation_m * _SEPARATION_MARGIN
    for k in range(1, len(out)):
        settled = out[:k]
        if _far_enough(wanted[k], settled, separation_m):
            continue
        gap = wanted[k] - settled
        distance = np.sqrt(np.sum(gap * gap, axis=1))
        conflicts = settled[distance < separation_m]
        candidates = []
        for centre in conflicts:
            own = wanted[k] - centre
            norm = float(np.sqrt(own @ own))
            directions = (
                _PUSH_DIRECTIONS if norm == 0.0 else np.vstack([own / norm, _PUSH_DIRECTIONS])
            )
            candidates.append(centre + reach * directions)
        point = _nearest_free(wanted[k], np.concatenate(candidates), settled, separation_m, area)
        if point is None:
            point = _lattice_free(wanted[k], settled, separation_m, area, len(out))
        if point is None:
            raise ValueError(
                f"separation_m: the volume cannot hold {len(out)} vehicles {separation_m} m apart"
            )
        out[k] = point
    return out


def _far_enough(point: np.ndarray, others: np.ndarray, separation_m: float) -> bool:
    gap = others - point
    return bool(np.all(np.sum(gap * gap, axis=1) >= separation_m * separation_m))


def _nearest_free(
    wanted: np.ndarray,
    candidates: np.ndarray,
    settled: np.ndarray,
    separation_m: float,
    area: AreaConfig,
) -> np.ndarray | None:
    """The candidate (clipped into the volume) nearest ``wanted`` that is at least
    ``separation_m`` from every settled point; None if none is. Ties: the first."""
    points = clip_to_volume(candidates, area)
    gap = points[:, None, :] - settled[None, :, :]
    free = np.all(np.sum(gap * gap, axis=-1) >= separation_m * separation_m, axis=1)
    if not free.any():
        return None
    points = points[free]
    cost = np.sum((points - wanted) ** 2, axis=1)
    return points[int(np.argmin(cost))].copy()


def _lattice_free(
    wanted: np.ndarray, settled: np.ndarray, separation_m: float, area: AreaConfig, n: int
) -> np.ndarray | None:
    """A free point on a lattice of spacing ``separation_m`` around ``wanted``, growing rings
    up to what ``n`` vehicles can need; None if the volume has none."""
    lower, upper = volume_bounds(area)
    span = float(np.max(upper - lower))
    rings = max(n + 1, 2)
    step = separation_m * _SEPARATION_MARGIN
    rings = min(rings, int(span / step) + 2)
    for radius in range(1, rings + 1):
        axis = np.arange(-radius, radius + 1, dtype=float)
        grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
        point = _nearest_free(wanted, wanted + step * grid, settled, separation_m, area)
        if point is not None:
            return point
    return None


# A held vehicle's detours, tried in this order: its step turned about the vertical by these
# angles (the same length: the same speed).
_DETOUR_TURNS = tuple((math.cos(a), math.sin(a)) for a in map(math.radians, (45, -45, 90, -90)))


def hold_separation(
    previous_m: np.ndarray,
    proposed_m: np.ndarray,
    separation_m: float,
    area: AreaConfig | None = None,
) -> np.ndarray:
    """Where K vehicles end a decision period: ``proposed_m`` (K, 3), except where a vehicle
    would end closer than ``separation_m`` to another.

    Flying straight toward separated targets can still bring two vehicles together on the way
    (crossing paths, or a path past a vehicle that hovers). Such a vehicle is first held at
    ``previous_m``, until no pair is too close (at most K rounds: each round holds at least one
    more vehicle; ``previous_m`` must itself be separated, so holding every vehicle always
    satisfies it). Then each held vehicle, in index order, takes the first detour that keeps
    clear of every other vehicle where it ends: its step turned by 45°, −45°, 90° or −90° about
    the vertical (inside ``area``'s volume when given), so that it goes round the other rather
    than wait behind it for ever; with none clear it stays held. A stand-in for the autopilots'
    own avoidance, not a planner.
    """
    previous = np.asarray(previous_m, dtype=float)
    proposed = np.asarray(proposed_m, dtype=float)
    out = proposed.copy()
    if min_pairwise_distance_m(out) >= separation_m:
        return out
    held = np.zeros(len(out), dtype=bool)
    limit = separation_m * separation_m
    for _ in range(len(out)):
        gap = out[:, None, :] - out[None, :, :]
        close = np.sum(gap * gap, axis=-1) < limit
        np.fill_diagonal(close, False)
        movers = close.any(axis=1) & ~held
        if not close.any() or not movers.any():
            break
        out[movers] = previous[movers]
        held |= movers
    for k in np.flatnonzero(held):
        dx, dy, dz = (proposed[k] - previous[k]).tolist()
        if dx == 0.0 and dy == 0.0:
            continue
        others = np.delete(out, k, axis=0)
        for cos_a, sin_a in _DETOUR_TURNS:
            candidate = previous[k] + (dx * cos_a - dy * sin_a, dx * sin_a + dy * cos_a, dz)
            if area is not None:
                candidate = clip_to_volume(candidate, area)
            gap = others - candidate
            if np.all(np.sum(gap * gap, axis=1) >= limit):
                out[k] = candidate
                break
    return out
