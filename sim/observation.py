"""The observation builder (paper §III-A): six zone maps from the UAV position and user reports.

One pure function, used by the Gymnasium environments for training and by the service when it
serves: both must see identical inputs. Maps, shape (6, n_zones_x, n_zones_y), float32 in [0, 1],
indexed ``[map, ix, iy]`` with ``ix`` along x (east) and ``iy`` along y (north):

0. distance from the UAV to each zone's centre (on the ground), over the longest possible distance;
1. users in the zone, over the number of users;
2. offered load of the zone's users, over the total offered load;
3. throughput of the zone's users, over the total offered load;
4. mean delay of the zone's users, over ``delay_ref_s`` (clipped at 1);
5. mean packet loss ratio of the zone's users.

Every map but the distance is complemented (1 − value), so the maps are dense, as in the paper.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np
from numba import njit

from sim.config import AreaConfig, UtilityConfig

N_MAPS = 6
MAP_NAMES: tuple[str, ...] = ("distance", "users", "offered", "throughput", "delay", "loss")


class UserReports(NamedTuple):
    """What the network says about its users, arrays (U,): the service gets them over REST.

    A named tuple, so that Gymnasium's checks compare it (in ``info``) field by field."""

    x_m: np.ndarray
    y_m: np.ndarray
    offered_bps: np.ndarray
    throughput_bps: np.ndarray
    delay_s: np.ndarray
    plr: np.ndarray

    @classmethod
    def from_metrics(
        cls,
        users_xy_m: np.ndarray,
        offered_bps: np.ndarray,
        throughput_bps: np.ndarray,
        delay_s: np.ndarray,
        plr: np.ndarray,
    ) -> UserReports:
        return cls(users_xy_m[:, 0], users_xy_m[:, 1], offered_bps, throughput_bps, delay_s, plr)


def observation_shape(area: AreaConfig) -> tuple[int, int, int]:
    return (N_MAPS, area.n_zones_x, area.n_zones_y)


def build_observation(
    uav_xyz_m: np.ndarray,
    reports: UserReports,
    area: AreaConfig,
    delay_ref_s: float = UtilityConfig.delay_ref_s,
) -> np.ndarray:
    """The six normalised zone maps for a UAV at ``uav_xyz_m`` (3,), float32 (6, n_x, n_y)."""
    centres_x, centres_y, max_distance_m = _zone_geometry(area)
    out = np.empty((N_MAPS, *centres_x.shape), dtype=np.float32)
    _fill_maps(
        out,
        float(uav_xyz_m[0]),
        float(uav_xyz_m[1]),
        float(uav_xyz_m[2]) - area.user_height_m,
        centres_x,
        centres_y,
        max_distance_m,
        area.zone_m,
        np.asarray(reports.x_m, dtype=float),
        np.asarray(reports.y_m, dtype=float),
        np.asarray(reports.offered_bps, dtype=float),
        np.asarray(reports.throughput_bps, dtype=float),
        np.asarray(reports.delay_s, dtype=float),
        np.asarray(reports.plr, dtype=float),
        delay_ref_s,
    )
    return out


def build_observations(
    uav_xyz_m: np.ndarray,
    x_m: np.ndarray,
    y_m: np.ndarray,
    offered_bps: np.ndarray,
    throughput_bps: np.ndarray,
    delay_s: np.ndarray,
    plr: np.ndarray,
    area: AreaConfig,
    delay_ref_s: float = UtilityConfig.delay_ref_s,
) -> np.ndarray:
    """:func:`build_observation` for E environments at once, float32 (E, 6, n_x, n_y).

    ``uav_xyz_m`` is (E, 3), the reports (E, U): row e is exactly ``build_observation(
    uav_xyz_m[e], UserReports(x_m[e], y_m[e], ...), area, delay_ref_s)``.
    """
    uav = np.asarray(uav_xyz_m, dtype=float)
    if uav.ndim != 2 or uav.shape[1] != 3:
        raise ValueError(f"uav_xyz_m: must be (E, 3) positions, got shape {uav.shape}")
    reports = [
        np.asarray(values, dtype=float)
        for values in (x_m, y_m, offered_bps, throughput_bps, delay_s, plr)
    ]
    for name, values in zip(UserReports._fields, reports, strict=True):
        if values.ndim != 2 or values.shape != reports[0].shape or len(values) != len(uav):
            raise ValueError(f"{name}: must be ({len(uav)}, U) like x_m, got shape {values.shape}")
    centres_x, centres_y, max_distance_m = _zone_geometry(area)
    out = np.empty((len(uav), N_MAPS, *centres_x.shape), dtype=np.float32)
    _fill_maps_many(
        out,
        uav,
        area.user_height_m,
        centres_x,
        centres_y,
        max_distance_m,
        area.zone_m,
        *reports,
        delay_ref_s,
    )
    return out


@njit(cache=True, nogil=True)
def _fill_maps_many(
    out: np.ndarray,
    uav: np.ndarray,
    user_height_m: float,
    centres_x: np.ndarray,
    centres_y: np.ndarray,
    max_distance_m: float,
    zone_m: float,
    x_m: np.ndarray,
    y_m: np.ndarray,
    offered_bps: np.ndarray,
    throughput_bps: np.ndarray,
    delay_s: np.ndarray,
    plr: np.ndarray,
    delay_ref_s: float,
) -> None:
    for e in range(out.shape[0]):
        _fill_maps(
            out[e],
            uav[e, 0],
            uav[e, 1],
            uav[e, 2] - user_height_m,
            centres_x,
            centres_y,
            max_distance_m,
            zone_m,
            x_m[e],
            y_m[e],
            offered_bps[e],
            throughput_bps[e],
            delay_s[e],
            plr[e],
            delay_ref_s,
        )


@njit(cache=True, nogil=True)
def _fill_maps(
    out: np.ndarray,
    uav_x_m: float,
    uav_y_m: float,
    height_m: float,
    centres_x: np.ndarray,
    centres_y: np.ndarray,
    max_distance_m: float,
    zone_m: float,
    x_m: np.ndarray,
    y_m: np.ndarray,
    offered_bps: np.ndarray,
    throughput_bps: np.ndarray,
    delay_s: np.ndarray,
    plr: np.ndarray,
    delay_ref_s: float,
) -> None:
    n_x, n_y = out.shape[1], out.shape[2]
    for i in range(n_x):
        for j in range(n_y):
            dx = centres_x[i, j] - uav_x_m
            dy = centres_y[i, j] - uav_y_m
            out[0, i, j] = np.sqrt(dx * dx + dy * dy + height_m * height_m) / max_distance_m
    out[1:] = 1.0  # zones without users: every sum 0, complemented
    n_users = x_m.size
    total_offered = 0.0
    for u in range(n_users):
        total_offered += offered_bps[u]
    total_offered = max(total_offered, 1e-12)
    # Sums over the zones that hold users only (every other zone stays at 1).
    zone_i = np.empty(n_users, dtype=np.int64)
    zone_j = np.empty(n_users, dtype=np.int64)
    sums = np.empty((5, n_x, n_y))
    for u in range(n_users):
        i = min(max(int(x_m[u] / zone_m), 0), n_x - 1)
        j = min(max(int(y_m[u] / zone_m), 0), n_y - 1)
        zone_i[u], zone_j[u] = i, j
        for k in range(5):
            sums[k, i, j] = 0.0
    for u in range(n_users):
        i, j = zone_i[u], zone_j[u]
        sums[0, i, j] += 1.0 / n_users
        sums[1, i, j] += offered_bps[u] / total_offered
        sums[2, i, j] += throughput_bps[u] / total_offered
        sums[3, i, j] += min(max(delay_s[u] / delay_ref_s, 0.0), 1.0)
        sums[4, i, j] += min(max(plr[u], 0.0), 1.0)
    for u in range(n_users):
        i, j = zone_i[u], zone_j[u]
        in_zone = sums[0, i, j] * n_users
        for k in range(5):
            value = sums[k, i, j]
            if k >= 3 and in_zone > 0.0:
                value /= in_zone  # delay and loss: means over the zone's users
            out[k + 1, i, j] = 1.0 - min(max(value, 0.0), 1.0)


@lru_cache(maxsize=8)
def _zone_geometry(area: AreaConfig) -> tuple[np.ndarray, np.ndarray, float]:
    centres_x, centres_y = np.meshgrid(
        area.zone_centres_x_m(), area.zone_centres_y_m(), indexing="ij"
    )
    max_distance_m = float(
        np.sqrt(area.size_x_m**2 + area.size_y_m**2 + (area.z_max_m - area.user_height_m) ** 2)
    )
    for array in (centres_x, centres_y):
        array.setflags(write=False)
    return centres_x, centres_y, max_distance_m
