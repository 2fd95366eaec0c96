"""Per-station queues over one step, as a fluid: backlog, drops, and the mean backlog for delay.

Every user is a station with its own queues (uplink traffic). Within a step the backlog changes
linearly at ``arrival − service`` until it reaches the queue's capacity, then stays there and the
excess is dropped. Two variants, as ns-3 runs them:

- ``mac-only``: the 500-packet Wi-Fi MAC queue alone. Packets that wait longer than 500 ms are
  dropped (``WifiMacQueue`` MaxDelay), so a station never holds more than ``0.5 s × service``.
- ``fq-codel``: ns-3's default queue disc above the MAC queue (10,240 packets). CoDel drops at
  dequeue once the disc's sojourn time stays above 5 ms, at a rate growing with the square root
  of its drop count — far too slowly to stop an overloaded UDP flow, so the backlog and the delay
  keep growing towards the disc's limit over many seconds (what ns-3 shows: ~0.5 s mean over
  the first 2 s of overload, ~1.2 s over 8 s). The drop count carries over between steps.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def advance_queue(
    backlog_pkts: float,
    codel_count: float,
    arrival_pps: float,
    service_pps: float,
    step_s: float,
    mac_queue_packets: float,
    mac_max_delay_s: float,
    qdisc_limit_packets: float,
    codel_target_s: float,
    codel_interval_s: float,
) -> tuple[float, float, float, float]:
    """Advance one station's queues by ``step_s``: (dropped, mean backlog, backlog, codel count).

    ``qdisc_limit_packets`` is 0 for ``mac-only``. ``service_pps`` must not exceed
    ``arrival_pps + backlog_pkts / step_s`` (what there is to serve).
    """
    mac_cap = min(mac_queue_packets, service_pps * mac_max_delay_s)
    cap = mac_cap + qdisc_limit_packets
    start = min(backlog_pkts, cap)
    dropped = backlog_pkts - start  # service fell since the last step: stale packets expire
    growth = arrival_pps - service_pps
    if growth > 0.0:
        t_full = min(max((cap - start) / growth, 0.0), step_s)
        end = min(start + growth * step_s, cap)
        dropped += growth * (step_s - t_full)
        # Backlog integral: linear up to t_full, flat at the cap after it.
        area = 0.5 * (start + min(start + growth * t_full, cap)) * t_full + cap * (step_s - t_full)
    else:
        end = max(start + growth * step_s, 0.0)
        area = 0.5 * (start + end) * step_s
    if qdisc_limit_packets <= 0.0:
        return dropped, area / step_s, end, 0.0

    # CoDel: the disc's sojourn exceeds the target once the backlog passes this level.
    threshold = mac_cap + service_pps * codel_target_s
    t_cross = min(max((threshold - start) / growth, 0.0), step_s) if growth != 0.0 else 0.0
    if start > threshold and end > threshold:
        t_above = step_s
    elif end > threshold:
        t_above = step_s - t_cross
    elif start > threshold:
        t_above = t_cross
    else:
        t_above = 0.0
    # A fresh dropping state starts one interval after the sojourn first exceeds the target.
    t_dropping = t_above if codel_count > 0.0 else max(t_above - codel_interval_s, 0.0)
    drops = 0.0
    if t_dropping > 0.0:
        first = max(codel_count, 1.0)
        root = np.sqrt(first) + t_dropping / (2.0 * codel_interval_s)
        drops = min(root * root - first + 1.0, max(end - threshold, 0.0))
    new_count = codel_count + drops if end > threshold else 0.0
    # Drops are spread over the dropping time: on average they shorten the queue by half.
    area -= 0.5 * drops * t_dropping
    return dropped + drops, area / step_s, end - drops, new_count
