"""Backoff stalls: why a light station in a busy cell loses packets while its delay stays low.

ns-3's drop traces (``sim/calibration``: ``response_timeouts``, ``backoff_long_draws``,
``expired_unsent``, ``max_tx_gap_s``) show the mechanism. In a cell of many stations, a large
share of transmissions get no Block Ack (a collision, or a fade that takes the whole PPDU), and
every failure doubles the station's contention window, up to CWmax = 1023. The backoff counter
only counts down in *idle* slots, and a busy cell has few of them: with 20 stations there are
about 2,000 idle slots a second, so a window of 1,023 takes ~0.25 s to count down, and a run of
failures stalls the station for 0.4–1.3 s. Packets that arrive early in a stall wait longer than
the MAC queue's lifetime (``WifiMacQueue`` MaxDelay, 500 ms) and expire before they are ever
sent. The packets that do get through waited at most the lifetime, so the mean delay stays low.
The fluid model's mean rates cannot show this: it is a tail effect of the gap between a
station's successful transmit opportunities.

The gap model: after a success the station starts again at stage 0. Each attempt fails with
probability ``q``, independently, so the number of failures before the next success is
geometric; after ``k`` failures the gap is the sum of ``k + 1`` uniform backoffs (window
``CW_j = min((CWmin + 1)·2^j, CWmax + 1) − 1`` at stage j, each slot lasting ``slot_time_s`` of
real time) and of the station's own ``k + 1`` transmissions. Each gap is approximated by a
normal with the same mean and variance. Arrivals are spread evenly in time, so a gap ``G``
expires the arrivals of its first ``(G − L)⁺`` seconds and delivers the rest, which waited
``min(G, L)/2`` on average.

The network model calls this for every station, position and sharing pass, so it reads a table
(:func:`stall_table`, built once per configuration) over the failure probability and the log
of the slot time, interpolated bilinearly; :func:`backoff_stall` is the exact computation the
table is built from. The station's own airtime per attempt is left out of the table: a few
hundred microseconds per attempt against stalls of hundreds of milliseconds.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numba import njit

# Failures in a row computed one by one; the rest of the geometric tail (beyond the last window
# doubling, so each further failure adds the same CWmax backoff) is added in closed form.
MAX_FAILURES = 32
_SQRT_2PI = math.sqrt(2.0 * math.pi)


@njit(cache=True, nogil=True)
def _excess_over(mean_s: float, std_s: float, limit_s: float) -> float:
    """E[(G − limit)⁺] for G normal with ``mean_s`` and ``std_s``."""
    if std_s <= 0.0:
        return max(mean_s - limit_s, 0.0)
    z = (limit_s - mean_s) / std_s
    tail = 0.5 * math.erfc(z / math.sqrt(2.0))
    return std_s * math.exp(-0.5 * z * z) / _SQRT_2PI + (mean_s - limit_s) * tail


@njit(cache=True, nogil=True)
def mean_backoff_slots(failure_prob: float, cw_min: int, cw_max: int) -> float:
    """Mean backoff slots drawn per attempt by a station whose attempts fail with this
    probability: the attempt after k failures in a row (probability ∝ q^k) draws CW_k / 2."""
    q = min(max(failure_prob, 0.0), 0.999)
    total = 0.0
    weight = 1.0 - q
    for k in range(MAX_FAILURES + 1):
        window = min((cw_min + 1) * 2.0**k, cw_max + 1.0) - 1.0
        total += weight * 0.5 * window
        weight *= q
    return total


@njit(cache=True, nogil=True)
def backoff_stall(
    failure_prob: float,
    slot_time_s: float,
    transmission_s: float,
    lifetime_s: float,
    cw_min: int,
    cw_max: int,
) -> tuple[float, float]:
    """(fraction of arrivals that expire, mean wait of the delivered ones in s) for one station.

    ``failure_prob`` is the chance an attempt gets no Block Ack, ``slot_time_s`` the real time one
    backoff slot takes to count down (the inverse of the cell's idle slots per second),
    ``transmission_s`` the station's own time on air per attempt, ``lifetime_s`` the MAC queue's
    MaxDelay.
    """
    q = min(max(failure_prob, 0.0), 0.999)
    mean_s = 0.0
    var_s2 = 0.0
    prob = 1.0 - q  # P(k failures before the success), k = 0
    gap_sum = 0.0
    expired_sum = 0.0
    wait_sum = 0.0
    delivered_sum = 0.0
    for k in range(MAX_FAILURES + 1):
        window = min((cw_min + 1) * 2.0**k, cw_max + 1.0) - 1.0
        mean_s += 0.5 * window * slot_time_s + transmission_s
        var_s2 += ((window + 1.0) ** 2 - 1.0) / 12.0 * slot_time_s * slot_time_s
        excess = _excess_over(mean_s, math.sqrt(var_s2), lifetime_s)
        delivered = mean_s - excess  # E[min(G, L)]
        gap_sum += prob * mean_s
        expired_sum += prob * excess
        delivered_sum += prob * delivered
        wait_sum += prob * 0.5 * delivered * delivered
        prob *= q
    # More than MAX_FAILURES failures (probability ``prob`` now): on average 1 / (1 − q) more
    # attempts at CWmax; such gaps are long, so their spread is left out.
    window = cw_max + 0.0
    tail_mean_s = mean_s + (0.5 * window * slot_time_s + transmission_s) / (1.0 - q)
    tail_delivered = min(tail_mean_s, lifetime_s)
    gap_sum += prob * tail_mean_s
    expired_sum += prob * (tail_mean_s - tail_delivered)
    delivered_sum += prob * tail_delivered
    wait_sum += prob * 0.5 * tail_delivered * tail_delivered
    if gap_sum <= 0.0:
        return 0.0, 0.0
    return expired_sum / gap_sum, wait_sum / max(delivered_sum, 1e-300)


# Table grid: failure probability 0..Q_MAX, log10 of the slot time LOG_SLOT_MIN..LOG_SLOT_MAX s.
Q_MAX = 0.99
Q_POINTS = 100
LOG_SLOT_MIN = -5.5  # 3 us: shorter than any real slot (9 us), nothing stalls
LOG_SLOT_MAX = -1.0  # 0.1 s per slot: even stage 0 outlasts the lifetime
LOG_SLOT_POINTS = 226


@lru_cache(maxsize=8)
def stall_table(lifetime_s: float, cw_min: int, cw_max: int) -> np.ndarray:
    """(2, Q_POINTS, LOG_SLOT_POINTS): expired fraction and mean wait over the table grid."""
    q_grid = np.linspace(0.0, Q_MAX, Q_POINTS)
    slot_grid = 10.0 ** np.linspace(LOG_SLOT_MIN, LOG_SLOT_MAX, LOG_SLOT_POINTS)
    table = np.empty((2, Q_POINTS, LOG_SLOT_POINTS))
    for i, q in enumerate(q_grid):
        for j, slot_s in enumerate(slot_grid):
            table[:, i, j] = backoff_stall(q, slot_s, 0.0, lifetime_s, cw_min, cw_max)
    table.setflags(write=False)
    return table


@njit(cache=True, nogil=True)
def stall_lookup(table: np.ndarray, failure_prob: float, slot_time_s: float) -> tuple[float, float]:
    """:func:`backoff_stall` (no own airtime) interpolated in ``table`` (:func:`stall_table`)."""
    fq = min(max(failure_prob, 0.0), Q_MAX) / Q_MAX * (Q_POINTS - 1)
    log_slot = math.log10(max(slot_time_s, 1e-12))
    fs = (
        (min(max(log_slot, LOG_SLOT_MIN), LOG_SLOT_MAX) - LOG_SLOT_MIN)
        / (LOG_SLOT_MAX - LOG_SLOT_MIN)
        * (LOG_SLOT_POINTS - 1)
    )
    i = min(int(fq), Q_POINTS - 2)
    j = min(int(fs), LOG_SLOT_POINTS - 2)
    a = fq - i
    b = fs - j
    return _bilinear(table[0], i, j, a, b), _bilinear(table[1], i, j, a, b)


@njit(cache=True, nogil=True)
def _bilinear(grid: np.ndarray, i: int, j: int, a: float, b: float) -> float:
    return (
        (1.0 - a) * (1.0 - b) * grid[i, j]
        + a * (1.0 - b) * grid[i + 1, j]
        + (1.0 - a) * b * grid[i, j + 1]
        + a * b * grid[i + 1, j + 1]
    )
