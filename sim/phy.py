"""802.11ac PHY: per-MCS frame timing and error rates, and the link parameters they give a user.

A user's link, for the MAC model, is four numbers (all per transmit opportunity, TXOP):

- ``overhead_s``: the fixed airtime of a TXOP besides the MPDUs (preamble, SIFS, Block Ack);
- ``mpdu_s``: the airtime of one A-MPDU subframe (one 512-byte packet with its headers);
- ``max_mpdus``: how many subframes fit in one A-MPDU (Block Ack window, 65,535 bytes, PPDU time);
- ``success``: the chance that a subframe gets through (failed ones are retransmitted).

The rate manager picks the MCS from the mean SNR (its estimate averages many frames), and each
subframe then sees its own Rician fading draw, so throughput falls off gradually with distance
within an MCS. Expected mode averages the subframe success over a deterministic quadrature of
the fading, tabulated on a fine SNR grid once; stochastic mode draws a few fading samples per
user and step instead (:func:`sampled_link`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from sim.channel import rician_quadrature_db
from sim.config import MacConfig, PhyConfig, RadioConfig, TrafficConfig

SNR_GRID_MIN_DB = -20.0
SNR_GRID_MAX_DB = 70.0
SNR_GRID_STEP_DB = 0.05


@dataclass(frozen=True)
class McsTable:
    """Per-MCS constants (arrays indexed by MCS 0..8)."""

    rate_bps: np.ndarray
    overhead_s: np.ndarray
    mpdu_s: np.ndarray
    max_mpdus: np.ndarray
    threshold_db: np.ndarray
    per_mid_db: np.ndarray
    per_slope: float

    @classmethod
    def build(cls, phy: PhyConfig, mac: MacConfig, traffic: TrafficConfig) -> McsTable:
        rate = np.asarray(phy.rates_bps, dtype=float)
        control = np.asarray(phy.control_rates_bps, dtype=float)
        mpdu_bytes = traffic.packet_bytes + mac.llc_ip_udp_bytes + mac.mac_overhead_bytes
        subframe_bytes = 4 * int(np.ceil((mpdu_bytes + mac.ampdu_delimiter_bytes) / 4))
        mpdu_s = subframe_bytes * 8 / rate
        header_s = phy.vht_preamble_s + phy.service_tail_bits / rate
        ba_bits = 16 + mac.block_ack_bytes * 8 + 6
        ba_s = phy.legacy_preamble_s + np.ceil(ba_bits / (control * phy.symbol_s)) * phy.symbol_s
        max_by_time = np.floor((phy.max_ppdu_s - header_s) / mpdu_s)
        max_mpdus = np.minimum(
            np.minimum(mac.ba_window, mac.max_ampdu_bytes // subframe_bytes), max_by_time
        )
        return cls(
            rate_bps=rate,
            overhead_s=header_s + mac.sifs_s + ba_s,
            mpdu_s=mpdu_s,
            max_mpdus=max_mpdus.astype(float),
            threshold_db=np.asarray(phy.ideal_threshold_db, dtype=float),
            per_mid_db=np.asarray(phy.per_mid_snr_db, dtype=float),
            per_slope=phy.per_slope_per_db,
        )

    def select_mcs(self, snr_db: np.ndarray) -> np.ndarray:
        """Ideal rate selection: the fastest MCS whose threshold the SNR meets (MCS 0 at worst)."""
        return np.maximum(np.searchsorted(self.threshold_db, snr_db, side="right") - 1, 0)

    def subframe_error_rate(self, snr_db: np.ndarray) -> np.ndarray:
        """Error rate of one subframe at each MCS, shape snr_db.shape + (n_mcs,)."""
        x = self.per_slope * (np.asarray(snr_db)[..., None] - self.per_mid_db)
        return 1.0 / (1.0 + np.exp(np.clip(x, -60.0, 60.0)))


@dataclass(frozen=True)
class LinkTable:
    """Link parameters tabulated over mean SNR (dB), for fast lookups in both modes.

    ``expected`` (grid, 4) holds (overhead_s, mpdu_s, max_mpdus, success) at the MCS the rate
    manager picks, the subframe success averaged over fading: the expected-mode link.
    """

    mcs: McsTable
    expected: np.ndarray

    @classmethod
    def build(
        cls, radio: RadioConfig, phy: PhyConfig, mac: MacConfig, traffic: TrafficConfig
    ) -> LinkTable:
        mcs = McsTable.build(phy, mac, traffic)
        grid = snr_grid_db()
        fading_db = rician_quadrature_db(radio.rician_k_db)
        # Success of a subframe at each MCS, averaged over the per-packet fading draw.
        per = mcs.subframe_error_rate(grid[:, None] + fading_db[None, :])  # (G, Q, n_mcs)
        success_by_mcs = 1.0 - per.mean(axis=1)
        # The rate manager's choice follows the mean SNR (its estimate averages many frames).
        chosen = mcs.select_mcs(grid)
        rows = np.arange(grid.size)
        expected = np.stack(
            [
                mcs.overhead_s[chosen],
                mcs.mpdu_s[chosen],
                mcs.max_mpdus[chosen],
                success_by_mcs[rows, chosen],
            ],
            axis=-1,
        )
        expected.setflags(write=False)
        return cls(mcs, expected)


@njit(cache=True, nogil=True)
def expected_link(expected: np.ndarray, snr_db: float) -> tuple[float, float, float, float]:
    """Expected-mode link (overhead_s, mpdu_s, max_mpdus, success) at a mean SNR, interpolated."""
    position = (min(max(snr_db, SNR_GRID_MIN_DB), SNR_GRID_MAX_DB) - SNR_GRID_MIN_DB) / (
        SNR_GRID_STEP_DB
    )
    lower = min(int(position), expected.shape[0] - 2)
    w = position - lower
    row_a = expected[lower]
    row_b = expected[lower + 1]
    return (
        row_a[0] * (1.0 - w) + row_b[0] * w,
        row_a[1] * (1.0 - w) + row_b[1] * w,
        row_a[2] * (1.0 - w) + row_b[2] * w,
        row_a[3] * (1.0 - w) + row_b[3] * w,
    )


@njit(cache=True, nogil=True)
def sampled_link(
    expected: np.ndarray,
    per_mid_db: np.ndarray,
    per_slope: float,
    threshold_db: np.ndarray,
    snr_db: float,
    gains_db: np.ndarray,
) -> tuple[float, float, float, float]:
    """Stochastic-mode link: the subframe success drawn over the fading samples ``gains_db``.

    The MCS is the expected mode's; its success is the mean over the draws instead of the
    exact average, so the step's throughput fluctuates around the expected value.
    """
    overhead_s, mpdu_s, max_mpdus, _ = expected_link(expected, snr_db)
    m = 0
    while m + 1 < threshold_db.size and snr_db >= threshold_db[m + 1]:
        m += 1
    total = 0.0
    for g in gains_db:
        x = min(max(per_slope * (snr_db + g - per_mid_db[m]), -60.0), 60.0)
        total += 1.0 - 1.0 / (1.0 + np.exp(x))
    return overhead_s, mpdu_s, max_mpdus, total / gains_db.size


def snr_grid_db() -> np.ndarray:
    n = round((SNR_GRID_MAX_DB - SNR_GRID_MIN_DB) / SNR_GRID_STEP_DB) + 1
    return SNR_GRID_MIN_DB + SNR_GRID_STEP_DB * np.arange(n)
