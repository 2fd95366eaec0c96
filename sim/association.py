"""Which access point each user is on: Wi-Fi association among a fleet's UAVs.

A station associates with the access point it hears best and stays with it until another is
clearly better, as Wi-Fi stations' roaming logic does: a new user (or one whose AP it can no
longer hear, below the minimum preamble RSSI) joins the strongest AP; an associated user moves
only when another AP is received more than ``hysteresis_db`` above its own (3 dB by default,
a common roaming delta: it stops a user half-way between two UAVs from flapping between them
as either moves a little). Received power is the **mean** one: transmit power less the
environment's mean path loss (:func:`sim.channel.mean_path_loss_db`), not a faded sample, since
stations average beacons' RSSI before roaming. Ties go to the lowest AP index.

On a site (``site:PATH``, :mod:`sim.sites`) the mean loss is the site's, looked up at each AP's
exact position (:func:`sim.sites.lookup.path_loss_db`, what :class:`sim.fleet.FleetModel`'s
association hears too); an AP with no path to a user gets :data:`sim.channel.NO_LINK_LOSS_DB`,
far below the minimum preamble RSSI, so that user never hears it. The open field and the towns
are computed as before, bit for bit.

Arrays: received powers (B, K, U) for B fleets of K UAVs and U users; associations (B, U) as
AP indices, ``-1`` for a user not associated yet.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from sim.channel import NO_LINK_LOSS_DB, area_site, friis_path_loss_db, mean_path_loss_db
from sim.config import AreaConfig, RadioConfig

__all__ = ["NOT_ASSOCIATED", "associate", "associate_at", "received_power_dbm"]

NOT_ASSOCIATED = -1


def received_power_dbm(
    uav_xyz_m: np.ndarray, users_xy_m: np.ndarray, area: AreaConfig, radio: RadioConfig
) -> np.ndarray:
    """Mean received power (dBm) of each UAV's AP at each user: (B, K, U) for UAVs (B, K, 3)
    and users (U, 2); the area's environment sets the path loss (Friis in the open, the
    statistical mean in a town, the site's lookup at the AP's exact position on a site, where
    no path gives ``tx_power_dbm − NO_LINK_LOSS_DB``: never heard). On a site the users must
    stand on it (InputError naming the first one off it)."""
    uav = np.asarray(uav_xyz_m, dtype=float)
    users = np.asarray(users_xy_m, dtype=float)
    if area.environment == "open":
        out = np.empty((*uav.shape[:-1], users.shape[0]))
        _open_power(uav.reshape(-1, 3), users, area.user_height_m, radio.tx_power_dbm,
                    _loss_1m_db(radio.frequency_hz), out.reshape(-1, users.shape[0]))  # fmt: skip
        return out
    site = area_site(area)
    if site is not None:
        from sim.sites.lookup import path_loss_db

        loss = path_loss_db(site, uav.reshape(-1, 3), users).reshape(
            *uav.shape[:-1], users.shape[0]
        )
        return radio.tx_power_dbm - np.minimum(loss, NO_LINK_LOSS_DB)
    ground = np.hypot(uav[..., 0, None] - users[:, 0], uav[..., 1, None] - users[:, 1])  # (B, K, U)
    height = np.maximum(uav[..., 2, None] - area.user_height_m, 0.0)
    loss = mean_path_loss_db(area.environment, ground, height, radio.frequency_hz)
    return radio.tx_power_dbm - loss


@lru_cache(maxsize=8)
def _loss_1m_db(frequency_hz: float) -> float:
    """Free-space loss at 1 m (dB): the Friis constant of the carrier."""
    return float(friis_path_loss_db(np.ones(1), frequency_hz)[0])


def associate(
    received_dbm: np.ndarray,
    current: np.ndarray | None,
    hysteresis_db: float,
    min_rssi_dbm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The new associations (B, U) and which users handed over (B, U) bool.

    ``current`` (B, U) is the previous association (``None``: nobody associated yet). A user
    keeps its AP while it still hears it (at or above ``min_rssi_dbm``) and no AP is received
    more than ``hysteresis_db`` above it, or while it hears no AP at all; otherwise it joins
    the strongest. Joining for the first time is not a handover; moving from one AP to another
    is.
    """
    rx = np.ascontiguousarray(received_dbm, dtype=float)
    batch, _, n_users = rx.shape
    if current is None:
        current = np.full((batch, n_users), NOT_ASSOCIATED, dtype=np.int64)
    new = np.empty((batch, n_users), dtype=np.int64)
    handover = np.empty((batch, n_users), dtype=np.bool_)
    _associate(
        rx,
        np.ascontiguousarray(current, dtype=np.int64),
        float(hysteresis_db),
        float(min_rssi_dbm),
        new,
        handover,
    )
    return new, handover


@njit(cache=True, nogil=True)
def _associate(
    rx: np.ndarray,
    current: np.ndarray,
    hysteresis_db: float,
    min_rssi_dbm: float,
    new: np.ndarray,
    handover: np.ndarray,
) -> None:
    batch, k, n_users = rx.shape
    for b in range(batch):
        for u in range(n_users):
            best = 0
            for a in range(1, k):
                if rx[b, a, u] > rx[b, best, u]:
                    best = a  # strictly greater: ties keep the lowest index
            own = current[b, u]
            # Stay while the own AP is heard and none is clearly better, or while no AP is
            # heard at all (roaming to another AP it cannot hear gains nothing).
            keep = own >= 0 and (
                rx[b, best, u] < min_rssi_dbm
                or (
                    rx[b, own, u] >= min_rssi_dbm
                    and rx[b, best, u] - rx[b, own, u] <= hysteresis_db
                )
            )
            new[b, u] = own if keep else best
            handover[b, u] = own >= 0 and new[b, u] != own


@njit(cache=True, nogil=True)
def _open_power(
    uav: np.ndarray,
    users: np.ndarray,
    user_height_m: float,
    tx_power_dbm: float,
    loss_1m_db: float,
    out: np.ndarray,
) -> None:
    """Friis received power (dBm), rows of ``uav`` (N, 3) by users (U, 2), into ``out``."""
    for i in range(uav.shape[0]):
        for u in range(users.shape[0]):
            dx = uav[i, 0] - users[u, 0]
            dy = uav[i, 1] - users[u, 1]
            dz = uav[i, 2] - user_height_m
            distance = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1.0)
            out[i, u] = tx_power_dbm - loss_1m_db - 20.0 * np.log10(distance)


def associate_at(
    uav_xyz_m: np.ndarray,
    users_xy_m: np.ndarray,
    area: AreaConfig,
    radio: RadioConfig,
    current: np.ndarray | None,
    hysteresis_db: float,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`associate` on :func:`received_power_dbm` of UAVs (B, K, 3) and users (U, 2), the
    minimum RSSI the radio's (on a site: the site's loss at each AP's position, an AP with no
    path never heard); in the open environment one compiled pass does both."""
    uav = np.ascontiguousarray(uav_xyz_m, dtype=float)
    users = np.ascontiguousarray(users_xy_m, dtype=float)
    if area.environment != "open":
        rx = received_power_dbm(uav, users, area, radio)
        return associate(rx, current, hysteresis_db, radio.min_rssi_dbm)
    batch, k = uav.shape[0], uav.shape[1]
    n_users = users.shape[0]
    if current is None:
        current = np.full((batch, n_users), NOT_ASSOCIATED, dtype=np.int64)
    rx = np.empty((batch, k, n_users))
    _open_power(uav.reshape(-1, 3), users, area.user_height_m, radio.tx_power_dbm,
                _loss_1m_db(radio.frequency_hz), rx.reshape(-1, n_users))  # fmt: skip
    new = np.empty((batch, n_users), dtype=np.int64)
    handover = np.empty((batch, n_users), dtype=np.bool_)
    _associate(rx, current, float(hysteresis_db), radio.min_rssi_dbm, new, handover)
    return new, handover
