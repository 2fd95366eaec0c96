"""A fleet agent's observation, built from one report: what training, evaluation and serving
share (:mod:`sim.fleet_env` documents the maps). A module of its own so that serving a fleet
imports neither PettingZoo nor Gymnasium."""

from __future__ import annotations

import numpy as np
from numba import njit

from sim.observation import N_MAPS, UserReports, build_observations
from sim.world import World

__all__ = ["FLEET_MAPS", "fleet_maps", "fleet_observations"]

FLEET_MAPS = N_MAPS + 3
"""Channels of a fleet agent's observation: the six single-UAV maps and three fleet maps."""


def fleet_maps(
    uav_xyz_m: np.ndarray, users_xy_m: np.ndarray, association: np.ndarray, world: World
) -> np.ndarray:
    """The three fleet maps (module doc) of every agent: float32 (K, 3, n_x, n_y)."""
    area = world.area
    uav = np.ascontiguousarray(uav_xyz_m, dtype=float)
    out = np.empty((len(uav), 3, area.n_zones_x, area.n_zones_y), dtype=np.float32)
    _fill_fleet_maps(
        out,
        uav,
        np.ascontiguousarray(users_xy_m, dtype=float),
        np.ascontiguousarray(association, dtype=np.int64),
        area.zone_m,
    )
    return out


def fleet_observations(
    uav_xyz_m: np.ndarray, report: UserReports, association: np.ndarray, world: World
) -> np.ndarray:
    """Every agent's observation (K, 9, n_x, n_y), float32: the six maps of
    :func:`sim.observation.build_observation` at its UAV and the three fleet maps
    (:func:`fleet_maps`), from one report of all users and the AP each user is on (U,). The
    environments and the service build observations with this one function."""
    area = world.area
    uav = np.asarray(uav_xyz_m, dtype=float)
    out = np.empty((len(uav), FLEET_MAPS, area.n_zones_x, area.n_zones_y), dtype=np.float32)
    # One call for every agent: row k is exactly build_observation at UAV k.
    tiled = np.empty((len(report), len(uav), len(report.x_m)))
    for i, values in enumerate(report):
        tiled[i] = values
    out[:, :N_MAPS] = build_observations(uav, *tiled, area, world.utility.delay_ref_s)
    xy = np.column_stack([report.x_m, report.y_m])
    out[:, N_MAPS:] = fleet_maps(uav, xy, association, world)
    return out


@njit(cache=True, nogil=True)
def _fill_fleet_maps(
    out: np.ndarray, uav: np.ndarray, users: np.ndarray, association: np.ndarray, zone_m: float
) -> None:
    k, _, n_x, n_y = out.shape
    counts = np.zeros((k + 1, n_x, n_y))  # users each UAV serves; row k: UAVs per zone
    for u in range(users.shape[0]):
        i = min(max(int(users[u, 0] / zone_m), 0), n_x - 1)
        j = min(max(int(users[u, 1] / zone_m), 0), n_y - 1)
        a = min(max(association[u], 0), k - 1)
        counts[a, i, j] += 1.0
    uav_i = np.empty(k, dtype=np.int64)
    uav_j = np.empty(k, dtype=np.int64)
    for a in range(k):
        uav_i[a] = min(max(int(np.floor(uav[a, 0] / zone_m)), 0), n_x - 1)
        uav_j[a] = min(max(int(np.floor(uav[a, 1] / zone_m)), 0), n_y - 1)
        counts[k, uav_i[a], uav_j[a]] += 1.0
    n_users = max(users.shape[0], 1)
    others = max(k - 1, 1)
    for i in range(n_x):
        for j in range(n_y):
            total = 0.0
            for a in range(k):
                total += counts[a, i, j]
            for a in range(k):
                out[a, 0, i, j] = 1.0 - min(counts[k, i, j] / others, 1.0)
                out[a, 1, i, j] = 1.0 - min(counts[a, i, j] / n_users, 1.0)
                out[a, 2, i, j] = 1.0 - min((total - counts[a, i, j]) / n_users, 1.0)
    for a in range(k):  # the agent itself is no "other UAV"
        i, j = uav_i[a], uav_j[a]
        out[a, 0, i, j] = 1.0 - min((counts[k, i, j] - 1.0) / others, 1.0)
