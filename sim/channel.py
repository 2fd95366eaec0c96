"""Radio channel: geometry, Friis path loss, noise, and Rician fast fading."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

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
    """Unit-mean power gains |h|² of a Rician channel with factor K (linear power ratio)."""
    k = 10.0 ** (k_db / 10.0)
    los = np.sqrt(k / (k + 1.0))
    sigma = np.sqrt(1.0 / (2.0 * (k + 1.0)))
    re = los + sigma * rng.standard_normal(size)
    im = sigma * rng.standard_normal(size)
    return re * re + im * im


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
