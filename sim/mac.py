"""802.11 EDCA airtime sharing: who gets how many transmit opportunities, solved exactly.

DCF/EDCA gives every station with a backlog the same number of transmit opportunities (TXOPs),
whatever its rate. A station that has more packets than fit in one A-MPDU per TXOP is
*saturated*; one whose arrivals fit is *aggregating*; one whose packets arrive slower than the
fair TXOP rate sends each packet in its own TXOP (*light*). With ``nu`` the TXOP rate every
backlogged station gets, a user's share of the channel's time is a piecewise-linear,
non-decreasing function of ``nu``:

- light (``r <= nu``):                ``r · (overhead + mpdu)``
- aggregating (``r/max <= nu < r``):   ``nu · overhead + r · mpdu``
- saturated (``nu < r/max``):          ``nu · (overhead + max · mpdu)``

with ``r`` its packet (attempt) rate. The channel is shared when these shares add up to 1; that
equation is solved exactly by sorting the 2U breakpoints — no iteration. If even ``nu = ∞`` leaves
the sum below 1, the channel is not saturated and everyone is served as offered. A slow, far
station takes long TXOPs at the same TXOP rate as everybody else, which is how it drags the whole
cell down (the 802.11 performance anomaly).

Contention is folded into each TXOP's fixed airtime: the mean idle backoff shrinks with the number
of contenders, and collisions (Bianchi's model) inflate the airtime by 1 / (1 − p).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit

from sim.config import MacConfig

_MAX_CONTENDERS = 1024


@njit(cache=True, nogil=True)
def fair_txop_rate(
    attempt_rate: np.ndarray, overhead_s: np.ndarray, mpdu_s: np.ndarray, max_mpdus: np.ndarray
) -> float:
    """TXOPs per second each backlogged station gets (``inf`` when the channel is not saturated).

    Solves ``sum_u share_u(nu) = 1`` exactly: walk the sorted breakpoints, keeping the slope and
    intercept of the piecewise-linear sum, and interpolate in the segment where it reaches 1.
    """
    n_users = attempt_rate.size
    points = np.empty(2 * n_users)
    d_slope = np.empty(2 * n_users)
    d_intercept = np.empty(2 * n_users)
    slope = 0.0
    for u in range(n_users):
        r = attempt_rate[u]
        points[u] = r / max_mpdus[u]  # below: saturated
        points[n_users + u] = r  # above: light
        d_slope[u] = -max_mpdus[u] * mpdu_s[u]
        d_slope[n_users + u] = -overhead_s[u]
        d_intercept[u] = r * mpdu_s[u]
        d_intercept[n_users + u] = r * overhead_s[u]
        slope += overhead_s[u] + max_mpdus[u] * mpdu_s[u]
    intercept = 0.0
    for k in np.argsort(points):
        if intercept + slope * points[k] >= 1.0:
            return (1.0 - intercept) / slope
        slope += d_slope[k]
        intercept += d_intercept[k]
    return np.inf


@njit(cache=True, nogil=True)
def effective_contenders(attempt_rate: np.ndarray, nu: float) -> float:
    """Stations contending for a typical TXOP: backlogged ones count 1, light ones r / nu."""
    total = 0.0
    for r in attempt_rate:
        total += min(r / nu, 1.0)
    return max(total, 1.0)


@njit(cache=True, nogil=True)
def contention_overhead(
    n_contenders: float, collision_table: np.ndarray, slot_s: float, cw_min: int
) -> tuple[float, float]:
    """(idle backoff per TXOP in s, collision inflation 1/(1 − p)) with ``n_contenders`` stations.

    The first of n uniform backoffs over [0, CWmin] expires after about CWmin / (n + 1) slots;
    p is Bianchi's collision probability, interpolated in ``collision_table``.
    """
    n = min(max(n_contenders, 1.0), collision_table.size - 1.001)
    lower = int(n)
    p = collision_table[lower] + (collision_table[lower + 1] - collision_table[lower]) * (n - lower)
    return slot_s * cw_min / (n + 1.0), 1.0 / (1.0 - p)


@njit(cache=True, nogil=True)
def idle_slots_per_transmission(n_contenders: float, collision_prob: float, cw_min: int) -> float:
    """Mean idle slots between two transmissions in Bianchi's model, ``n_contenders`` stations.

    Each station transmits in a slot with probability tau, tied to the collision probability by
    ``p = 1 − (1 − tau)^(n − 1)``; a slot is idle with probability ``(1 − tau)^n``.
    """
    n = max(n_contenders, 1.0)
    if n < 1.0 + 1e-6 or collision_prob <= 0.0:
        tau = 2.0 / (cw_min + 2.0)
    else:
        tau = 1.0 - (1.0 - collision_prob) ** (1.0 / (n - 1.0))
    idle = (1.0 - tau) ** n
    return idle / max(1.0 - idle, 1e-12)


def collision_table(mac: MacConfig) -> np.ndarray:
    """Bianchi's saturated collision probability p(n), indexed by the number of stations n."""
    return _collision_probability_table(mac.contention_cw_min, mac.cw_max)


@lru_cache(maxsize=4)
def _collision_probability_table(cw_min: int, cw_max: int) -> np.ndarray:
    """Bianchi's saturated collision probability p(n) for n = 0.._MAX_CONTENDERS − 1 stations."""
    w = cw_min + 1
    m = round(float(np.log2((cw_max + 1) / w)))
    n = np.arange(_MAX_CONTENDERS, dtype=float)
    lo = np.zeros_like(n)
    hi = np.full_like(n, 0.999)
    # p = 1 − (1 − tau(p))^(n − 1) has one root in [0, 1): bisect all n at once (import time only).
    for _ in range(60):
        p = 0.5 * (lo + hi)
        q = 1.0 - 2.0 * p
        tau = 2.0 * q / (q * (w + 1) + p * w * (1.0 - (2.0 * p) ** m))
        residual = 1.0 - (1.0 - tau) ** np.maximum(n - 1.0, 0.0) - p
        lo = np.where(residual > 0, p, lo)
        hi = np.where(residual > 0, hi, p)
    table = 0.5 * (lo + hi)
    table[:2] = 0.0
    table.setflags(write=False)
    return table
