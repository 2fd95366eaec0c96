"""Network utility (paper eq. 1) and the heterogeneity index of a scenario (paper eq. 3)."""

from __future__ import annotations

import numpy as np

from sim.config import AreaConfig, UtilityConfig

_DEFAULT_UTILITY = UtilityConfig()


def network_utility(
    throughput_bps: np.ndarray,
    delay_s: np.ndarray,
    plr: np.ndarray,
    offered_bps: np.ndarray,
    config: UtilityConfig = _DEFAULT_UTILITY,
) -> np.ndarray:
    """Utility ``0.6·T + 0.3·(1 − D) + 0.1·(1 − P)`` of one step, over the last (user) axis.

    T is the aggregate throughput over the total offered load, D the users' mean delay over
    ``config.delay_ref_s``, P the users' mean packet loss ratio. T and D are clipped to [0, 1]
    so the utility stays in [0, 1]: T can pass 1 for a step that drains an old backlog, and D
    passes 1 only where the UAV is so badly placed that the exact delay no longer matters.

    Inputs (..., U) give utilities (...): one per position or environment of a batch.
    """
    if (
        _float_vector(throughput_bps)
        and _float_vector(delay_s)
        and _float_vector(plr)
        and _float_vector(offered_bps)
        and config.delay_ref_s != 0.0  # numpy's inf, not Python's ZeroDivisionError
    ):
        # One step of one cell, the training loop's case: the same operations on Python
        # floats (numpy's own sums), without numpy's per-call overhead on 0-d results.
        total = max(float(_sum(offered_bps)), 1e-12)
        t = min(float(_sum(throughput_bps)) / total, 1.0)
        d = min(float(_sum(delay_s)) / delay_s.size / config.delay_ref_s, 1.0)
        p = min(float(_sum(plr)) / plr.size, 1.0)
        return np.float64(
            config.weight_throughput * max(t, 0.0)
            + config.weight_delay * (1.0 - max(d, 0.0))
            + config.weight_loss * (1.0 - max(p, 0.0))
        )
    offered = np.maximum(np.sum(offered_bps, axis=-1), 1e-12)
    t_norm = np.minimum(np.sum(throughput_bps, axis=-1) / offered, 1.0)
    d_norm = np.minimum(np.mean(delay_s, axis=-1) / config.delay_ref_s, 1.0)
    p_norm = np.minimum(np.mean(plr, axis=-1), 1.0)
    return (
        config.weight_throughput * np.maximum(t_norm, 0.0)
        + config.weight_delay * (1.0 - np.maximum(d_norm, 0.0))
        + config.weight_loss * (1.0 - np.maximum(p_norm, 0.0))
    )


_sum = np.add.reduce


def _float_vector(values: object) -> bool:
    """A non-empty 1-D float64 array (what the fast path of :func:`network_utility` takes)."""
    return (
        type(values) is np.ndarray
        and values.ndim == 1
        and values.size > 0
        and values.dtype == np.float64
    )


def heterogeneity_index(users_xy_m: np.ndarray, load_bps: np.ndarray, area: AreaConfig) -> float:
    """Heterogeneity index H in [0, 1] (paper eq. 3).

    Half of it is one minus Jain's fairness index of the loads, half the mean pairwise distance
    between users normalised by the area's diagonal. With U users, the load half is at most
    (1 − 1/U)/2, so H cannot reach 1 with few users (about 0.68 with 3).
    """
    loads = np.asarray(load_bps, dtype=float)
    xy = np.asarray(users_xy_m, dtype=float)
    n = loads.shape[0]
    if n == 0:
        raise ValueError("users: a scenario needs at least one user")
    sum_sq = float(np.sum(loads**2))
    jain = float(np.sum(loads) ** 2 / (n * sum_sq)) if sum_sq > 0 else 1.0
    if n < 2:
        mean_distance = 0.0
    else:
        diff = xy[:, None, :] - xy[None, :, :]
        dist = np.sqrt(np.sum(diff**2, axis=-1))
        mean_distance = float(np.sum(dist) / (n * (n - 1)))
    return 0.5 * (1.0 - jain) + 0.5 * mean_distance / area.diagonal_m
