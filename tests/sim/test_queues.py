"""The delivered packets' wait of :func:`sim.queues.advance_queue` (FIFO rules, module doc)."""

from __future__ import annotations

import numpy as np
import pytest

from sim.queues import advance_queue

MAC_PKTS, MAC_LIFE_S, DISC_PKTS = 500.0, 0.5, 10_240.0
NO_CODEL = (1e9, 0.1)  # a target no sojourn reaches: CoDel never drops


def step(backlog, at_cap_s, arrival, service, step_s=1.0, disc=DISC_PKTS):
    """(dropped, wait, backlog, at_cap_s) of one step without CoDel."""
    dropped, wait, end, _, at_cap = advance_queue(
        backlog, 0.0, at_cap_s, arrival, service, step_s, MAC_PKTS, MAC_LIFE_S, disc, *NO_CODEL
    )
    return dropped, wait, end, at_cap


def test_growing_disc_is_crossed_at_the_arrival_rate():
    """Below the limit every arrival is let in: a leaving packet waited (packets behind it) ÷
    arrival rate in the disc, plus the full MAC queue ÷ service rate."""
    _, wait, end, at_cap = step(5000.0, 0.0, 3000.0, 2000.0)
    assert end == pytest.approx(6000.0) and at_cap == 0.0
    # Mean backlog 5500: 500 in the MAC queue (fed at 2000/s), 5000 in the disc (fed at 3000/s).
    assert wait == pytest.approx(500 / 2000 + 5000 / 3000)


def test_wait_keeps_rising_for_cap_over_service_seconds_after_the_disc_fills():
    """At the limit arrivals are tail-dropped, but the packets leaving during the next
    limit ÷ service seconds were let in while it grew: their wait rises at 1 − service/arrival
    per second from limit ÷ arrival to limit ÷ service, then stays there."""
    cap = MAC_PKTS + DISC_PKTS
    dropped, wait, end, at_cap = step(cap, 0.0, 3000.0, 2000.0)
    assert end == pytest.approx(cap) and dropped == pytest.approx(1000.0)
    assert at_cap == pytest.approx(1.0)
    assert wait == pytest.approx(500 / 2000 + DISC_PKTS / 3000 + 0.5 * (1 - 2000 / 3000))
    # Long after: limit ÷ service, and the clock is held (a fixed point the oracles can see).
    _, wait, _, at_cap = step(cap, 30.0, 3000.0, 2000.0)
    assert wait == pytest.approx(cap / 2000)
    assert at_cap == pytest.approx(DISC_PKTS / 2000)
    assert step(cap, at_cap, 3000.0, 2000.0)[3] == at_cap


@pytest.mark.parametrize("disc", [DISC_PKTS, 0.0])
def test_splitting_a_step_changes_nothing(disc):
    """Eight 1-s steps and thirty-two 0.25-s steps from empty queues give the same mean wait
    per second, through the filling, the cap and the knee (without CoDel)."""
    per_s = []
    for step_s in (1.0, 0.25):
        backlog, at_cap, waits = 0.0, 0.0, []
        for _ in range(round(8 / step_s)):
            _, wait, backlog, at_cap = step(backlog, at_cap, 3000.0, 2000.0, step_s, disc)
            waits.append(wait)
        per_s.append(np.array(waits).reshape(8, -1).mean(axis=1))
    np.testing.assert_allclose(per_s[0], per_s[1], rtol=1e-9)
    assert np.all(np.diff(per_s[0]) >= -1e-12)


def test_mac_queue_at_its_cap_waits_cap_over_service():
    """mac-only: the 500-packet queue (or its 500-ms lifetime) caps the wait."""
    for service_pps in (600.0, 2000.0):  # lifetime-bound (300 packets), then size-bound (500)
        cap = min(MAC_PKTS, service_pps * MAC_LIFE_S)
        _, wait, _, _ = step(cap, 10.0, 3000.0, service_pps, disc=0.0)
        assert wait == pytest.approx(cap / service_pps)
        assert wait <= MAC_LIFE_S + 1e-12


def test_draining_queue_and_an_idle_station():
    """Draining: the packets were let in at the arrival rate; nothing served waits nothing."""
    _, wait, end, at_cap = step(4000.0, 0.0, 1000.0, 3000.0)
    assert end == pytest.approx(2000.0) and at_cap == 0.0
    assert wait == pytest.approx(500 / 3000 + (3000 - 500) / 1000)  # mean backlog 3000
    assert step(0.0, 0.0, 0.0, 0.0)[1] == 0.0
