"""Per-station queues over one step, as a fluid: backlog, drops, and the queueing delay.

Every user is a station with its own queues (uplink traffic). Within a step the backlog changes
linearly at ``arrival − service`` until it reaches the queue's capacity, then stays there and the
excess is dropped. Two variants, as ns-3 runs them:

- ``mac-only``: the 500-packet Wi-Fi MAC queue alone. Packets that wait longer than 500 ms are
  dropped (``WifiMacQueue`` MaxDelay), so a station never holds more than ``0.5 s × service``.
- ``fq-codel``: ns-3's default queue disc above the MAC queue (10,240 packets). CoDel drops at
  dequeue once the disc's sojourn time stays above 5 ms, at a rate growing with the square root
  of its drop count — far too slowly to stop an overloaded UDP flow, so the backlog and the delay
  keep growing towards the disc's limit over several seconds. The drop count carries over
  between steps.

The delay is that of the packets *delivered* in the step, as ns-3's FlowMonitor measures it. A
packet leaving a FIFO queue has behind it exactly the packets let in while it waited, so its
wait is the backlog over the rate packets are *let in*, not over the rate they leave (that would
be the wait of a packet arriving now: under a growing queue 1.4–2 times longer).

- While the backlog grows below its cap, every arrival is let in: backlog ÷ arrival rate. CoDel's
  drops are taken from the head, so they never shorten the line behind a leaving packet. With a
  queue disc, the MAC queue under it is full and fed at the service rate: its part is backlog ÷
  service rate.
- At the cap, arrivals are tail-dropped (the MAC queue's 500 packets; with FqCoDel the flow's own
  CoDel queue, which ns-3 gives the disc's limit, so it drops an arriving packet before the
  disc's head-drop of the fat flow ever runs) or expire after ``mac_max_delay_s``: packets are
  let in at the rate they leave. A packet let in at the cap waits cap ÷ service rate, but the
  packets leaving during the first cap ÷ service seconds at the cap were let in before it, while
  the queue still grew: their wait keeps rising at ``1 − service/arrival`` per second until it
  reaches cap ÷ service. The time spent at the cap (``at_cap_s``, carried between steps and held
  once it no longer matters) is what tells the two apart.
- While the backlog drains (arrival below service), its packets were let in at about the
  arrival rate: backlog ÷ arrival rate, never more than cap ÷ service rate.

ns-3 3.44, one saturated user at 450 m under FqCoDel from empty queues: the delivered packets'
delay grows by about 0.3 s per second (0.15, 0.46, 0.75, 1.05, 1.33 s over its first five
seconds), then stays at about 1.5 s (``benchmarks/queue_delay_ns3.py``; docs/network-model.md).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def advance_queue(
    backlog_pkts: float,
    codel_count: float,
    at_cap_s: float,
    arrival_pps: float,
    service_pps: float,
    step_s: float,
    mac_queue_packets: float,
    mac_max_delay_s: float,
    qdisc_limit_packets: float,
    codel_target_s: float,
    codel_interval_s: float,
) -> tuple[float, float, float, float, float]:
    """Advance one station's queues by ``step_s``.

    Returns (dropped, queue wait, backlog, CoDel count, time at the cap). The queue wait (s) is
    the mean time the packets delivered in the step spent in the queues (module doc); 0 when
    nothing is served. ``at_cap_s`` is how long the queue has been full (0 when it is not),
    held at cap ÷ service once the delivered packets' wait stops depending on it.

    ``qdisc_limit_packets`` is 0 for ``mac-only``. ``service_pps`` must not exceed
    ``arrival_pps + backlog_pkts / step_s`` (what there is to serve).
    """
    mac_cap = min(mac_queue_packets, service_pps * mac_max_delay_s)
    cap = mac_cap + qdisc_limit_packets
    # With a disc the full MAC queue is fed at the service rate; the rest is the queue whose
    # entry rate sets the wait (the disc, or the MAC queue alone without one).
    mac_fed = mac_cap if qdisc_limit_packets > 0.0 else 0.0
    own_cap = cap - mac_fed
    start = min(backlog_pkts, cap)
    dropped = backlog_pkts - start  # service fell since the last step: stale packets expire
    growth = arrival_pps - service_pps
    tau_end = 0.0
    if growth > 0.0:
        t_full = min(max((cap - start) / growth, 0.0), step_s)
        end = min(start + growth * step_s, cap)
        dropped += growth * (step_s - t_full)
        if t_full < step_s and at_cap_s > 0.0:
            # Full at the end of the last step too (CoDel's head drops may have opened a little
            # room since): the time at the cap runs on through the whole step.
            t_below, tau_start = 0.0, at_cap_s
        else:
            t_below, tau_start = t_full, 0.0
        area_below = 0.5 * (start + min(start + growth * t_below, cap)) * t_below
        if t_full < step_s:
            tau_end = tau_start + (step_s - t_below)
    else:
        end = max(start + growth * step_s, 0.0)
        t_below, tau_start = step_s, 0.0
        area_below = 0.5 * (start + end) * step_s
    area_at_cap = cap * (step_s - t_below)

    drops = 0.0
    t_dropping = 0.0
    new_count = 0.0
    if qdisc_limit_packets > 0.0:
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
        if t_dropping > 0.0:
            first = max(codel_count, 1.0)
            root = np.sqrt(first) + t_dropping / (2.0 * codel_interval_s)
            drops = min(root * root - first + 1.0, max(end - threshold, 0.0))
        new_count = codel_count + drops if end > threshold else 0.0
        # Drops are spread over the dropping time: on average they shorten the queue by half.
        area = area_below + area_at_cap
        if area > 0.0:
            area_below *= max(area - 0.5 * drops * t_dropping, 0.0) / area

    if service_pps <= 0.0:
        return dropped + drops, 0.0, end - drops, new_count, 0.0
    # Wait below the cap: backlog ÷ arrival rate, except that the MAC queue under a disc, once
    # full, is fed at the service rate (exact for the linear backlog).
    let_in_pps = arrival_pps if arrival_pps > 0.0 else service_pps
    waited = area_below / let_in_pps
    if mac_fed > 0.0 and t_below > 0.0:
        b_end = start + growth * t_below
        if b_end != start:
            share = (max(start, b_end) - mac_fed) / abs(b_end - start)
            above_mac_s = t_below * min(max(share, 0.0), 1.0)
        else:
            above_mac_s = t_below if start > mac_fed else 0.0
        waited += mac_fed * (1.0 / service_pps - 1.0 / let_in_pps) * above_mac_s
    waited = min(waited, cap / service_pps * t_below)
    if step_s > t_below:
        waited += mac_fed / service_pps * (step_s - t_below) + _at_cap_wait_integral(
            own_cap, arrival_pps, service_pps, tau_start, tau_end
        )
    held = min(tau_end, own_cap / service_pps)
    return dropped + drops, waited / step_s, end - drops, new_count, held


@njit(cache=True, nogil=True)
def _at_cap_wait_integral(
    cap_pkts: float, arrival_pps: float, service_pps: float, tau_a_s: float, tau_b_s: float
) -> float:
    """∫ wait dτ over τ in [tau_a, tau_b] seconds at the cap (module doc): the wait of the
    leaving packet is cap/arrival + τ·(1 − service/arrival) until it reaches cap/service."""
    flat = cap_pkts / service_pps
    slope = 1.0 - service_pps / arrival_pps
    knee = min(max(flat - cap_pkts / arrival_pps, 0.0) / slope, tau_b_s) if slope > 0.0 else 0.0
    total = 0.0
    if knee > tau_a_s:
        total += cap_pkts / arrival_pps * (knee - tau_a_s) + 0.5 * slope * (
            knee * knee - tau_a_s * tau_a_s
        )
    return total + flat * (tau_b_s - max(knee, tau_a_s))
