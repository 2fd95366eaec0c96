"""Radio channel: geometry, Friis path loss, noise, and Rician fast fading."""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from sim.config import RadioConfig

SPEED_OF_LIGHT_MPS = 299_792_458.0


def distances_m(uav_xyz_m: np.ndarray, users_xy_m: np.ndarray, user_height_m: float) -> np.ndarray:
    """3-D distances between each UAV position (B, 3) and each ground user (U, 2): shape (B, U)."""
    dx = uav_xyz_m[:, None, 0] - users_xy_m[None, :, 0]
    dy = uav_xyz_m[:, None, 1] - users_xy_m[None, :, 1]
    dz = uav_xyz_m[:, None, 2] - user_height_m
    return np.sqrt(dx * dx + dy * dy + dz * dz)


def friis_path_loss_db(distance_m: np.ndarray, frequency_hz: float) -> np.ndarray:
    """Free-space path loss; distances under 1 m count as 1 m (the near field is not modelled)."""
    d = np.maximum(distance_m, 1.0)
    return 20.0 * np.log10(4.0 * np.pi * d * frequency_hz / SPEED_OF_LIGHT_MPS)


def mean_rssi_dbm(distance_m: np.ndarray, radio: RadioConfig) -> np.ndarray:
    """Received power before fading (the average over Rician fading is the Friis value)."""
    return radio.tx_power_dbm - friis_path_loss_db(distance_m, radio.frequency_hz)


def rician_power_gain(rng: np.random.Generator, k_db: float, size: tuple[int, ...]) -> np.ndarray:
    """Unit-mean power gains |h|² of a Rician channel with factor K (linear power ratio).

    Draw order: ``size`` standard normals for the real parts (C order), then ``size`` for the
    imaginary parts, from one ``standard_normal`` call of shape ``(2, *size)`` (the same numbers
    two calls of ``size`` would give).
    """
    los, sigma = _rician_parameters(k_db)
    if type(size) is not tuple:
        size = () if size is None else tuple(np.atleast_1d(size))  # an int, a list, None
    draws = rng.standard_normal((2, *size))
    _combine_parts(draws.reshape(2, -1), los, sigma)
    return draws[0]


@njit(cache=True)
def _combine_parts(draws: np.ndarray, los: float, sigma: float) -> None:
    """``draws[0] = (los + sigma·draws[0])² + (sigma·draws[1])²`` in place, (2, N)."""
    for i in range(draws.shape[1]):
        re = los + sigma * draws[0, i]
        im = sigma * draws[1, i]
        draws[0, i] = re * re + im * im


@lru_cache(maxsize=8)
def _rician_parameters(k_db: float) -> tuple[float, float]:
    """(line-of-sight amplitude, scatter standard deviation per component) for K in dB."""
    k = 10.0 ** (k_db / 10.0)
    return float(np.sqrt(k / (k + 1.0))), float(np.sqrt(1.0 / (2.0 * (k + 1.0))))


@lru_cache(maxsize=8)
def rician_quadrature_db(k_db: float, n_points: int = 32) -> np.ndarray:
    """Deterministic equal-probability quadrature of the Rician power gain, in dB.

    Point i is the mean gain of the i-th of ``n_points`` equally likely slices of the
    distribution, estimated once from 2**18 draws with a fixed seed; averaging a function over
    these points approximates its expectation over the fading (used by the expected mode).
    """
    rng = np.random.default_rng(20240601)
    samples = np.sort(rician_power_gain(rng, k_db, (2**18,)))
    gains_db = 10.0 * np.log10(samples.reshape(n_points, -1).mean(axis=1))
    gains_db.setflags(write=False)  # cached: shared by every caller
    return gains_db
