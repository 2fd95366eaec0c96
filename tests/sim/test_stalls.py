"""Backoff stalls (sim/stalls.py) and what they do to the cell (sim/network.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from sim.config import NetworkConfig
from sim.network import NetworkModel
from sim.stalls import backoff_stall, mean_backoff_slots

CW_MIN, CW_MAX, LIFETIME_S = 15, 1023, 0.5


def _monte_carlo(q: float, slot_time_s: float, tx_s: float, n: int = 200_000):
    """The gap process itself: geometric failures, uniform backoffs on the window ladder."""
    rng = np.random.default_rng(7)
    failures = rng.geometric(1.0 - q, n) - 1
    gaps = np.zeros(n)
    for k in range(failures.max() + 1):
        window = min((CW_MIN + 1) * 2**k, CW_MAX + 1) - 1
        active = failures >= k
        gaps[active] += rng.integers(0, window + 1, active.sum()) * slot_time_s + tx_s
    expired = np.maximum(gaps - LIFETIME_S, 0.0)
    delivered = gaps - expired
    return expired.sum() / gaps.sum(), (0.5 * delivered**2).sum() / delivered.sum()


@pytest.mark.parametrize(
    "q, slot_time_s", [(0.5, 0.5e-3), (0.6, 0.5e-3), (0.45, 1.0e-3), (0.9, 2e-4)]
)
def test_expiry_and_wait_match_a_simulation_of_the_gap_process(q, slot_time_s):
    expired, wait_s = backoff_stall(q, slot_time_s, 2e-4, LIFETIME_S, CW_MIN, CW_MAX)
    mc_expired, mc_wait_s = _monte_carlo(q, slot_time_s, 2e-4)
    assert mc_expired > 0.005  # the cases are ones where stalls matter
    assert expired == pytest.approx(mc_expired, rel=0.25)
    assert wait_s == pytest.approx(mc_wait_s, rel=0.25)


def test_nothing_expires_without_failures_or_in_an_idle_cell():
    assert backoff_stall(0.0, 0.5e-3, 2e-4, LIFETIME_S, CW_MIN, CW_MAX)[0] < 1e-9
    # Alone in the cell a slot is 9 us: even CW 1023 counts down in under 10 ms.
    assert backoff_stall(0.9, 9e-6, 2e-4, LIFETIME_S, CW_MIN, CW_MAX)[0] < 1e-6


def test_expiry_grows_with_failures_and_with_the_slot_time():
    def expired(q: float, slot_time_s: float) -> float:
        return backoff_stall(q, slot_time_s, 2e-4, LIFETIME_S, CW_MIN, CW_MAX)[0]

    by_q = [expired(q, 0.5e-3) for q in (0.3, 0.5, 0.7)]
    by_slot = [expired(0.5, v) for v in (2e-4, 5e-4, 1e-3)]
    assert by_q == sorted(by_q) and by_q[0] < by_q[-1]
    assert by_slot == sorted(by_slot) and by_slot[0] < by_slot[-1]


def test_mean_backoff_per_attempt_doubles_with_each_failure_stage():
    assert mean_backoff_slots(0.0, CW_MIN, CW_MAX) == pytest.approx(7.5)
    # q = 0.5: ns-3 counted 14-40 slots per backoff draw in its 20-station cells.
    assert 25.0 < mean_backoff_slots(0.5, CW_MIN, CW_MAX) < 45.0


def _busy_cell():
    """19 stations sharing 40 Mbit/s around a UAV at 50 m, and one light station (200 kbit/s)."""
    rng = np.random.default_rng(3)
    angles = rng.uniform(0, 2 * np.pi, 20)
    radii = rng.uniform(50, 150, 20)
    users = np.stack([250 + radii * np.cos(angles), 250 + radii * np.sin(angles)], axis=1)
    load = np.full(20, 39.8e6 / 19)
    load[0] = 0.2e6
    return np.array([[250.0, 250.0, 50.0]]), users, load


@pytest.mark.parametrize("queueing", ["fq-codel", "mac-only"])
def test_a_light_station_in_a_busy_cell_loses_packets_but_not_delay(queueing):
    uav, users, load = _busy_cell()
    config = NetworkConfig().with_queueing(queueing)
    with_stalls = NetworkModel(config).step(uav, users, load, step_s=2.0)
    without = NetworkModel(replace(config, mac=replace(config.mac, backoff_stalls=False))).step(
        uav, users, load, step_s=2.0
    )
    assert without.plr[0, 0] < 0.005
    assert with_stalls.plr[0, 0] > 0.05  # ns-3: 10-40 % for such stations
    assert with_stalls.delay_s[0, 0] < LIFETIME_S  # the delivered packets waited less than that
    # The airtime the stalled stations do not use goes to the others.
    assert with_stalls.throughput_bps[0, 1:].sum() > 0.9 * without.throughput_bps[0, 1:].sum()


def test_a_station_alone_in_the_cell_never_stalls():
    uav = np.array([[0.0, 0.0, 25.0], [0.0, 0.0, 100.0]])
    users = np.array([[450.0 / np.sqrt(2), 450.0 / np.sqrt(2)]])
    config = NetworkConfig()
    off = replace(config, mac=replace(config.mac, backoff_stalls=False))
    for load_bps in (1e6, 40e6):
        on_step = NetworkModel(config).step(uav, users, np.array([load_bps]), step_s=2.0)
        off_step = NetworkModel(off).step(uav, users, np.array([load_bps]), step_s=2.0)
        np.testing.assert_allclose(on_step.throughput_bps, off_step.throughput_bps, rtol=1e-3)
        np.testing.assert_allclose(on_step.plr, off_step.plr, atol=1e-3)
