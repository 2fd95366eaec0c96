"""Configuration dataclasses. Defaults are the paper's Table I and ns-3's defaults for that network.

Every parameter a user might want to change lives here, grouped by layer, frozen so a config can be
shared between environments, the oracle and the service without defensive copies.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np

from sim.errors import InputError

Queueing = Literal["fq-codel", "mac-only"]
ENVIRONMENTS: tuple[str, ...] = ("open", "suburban", "urban", "dense-urban", "highrise-urban")
"""The channel environments (:mod:`sim.channel`): the paper's free space, and ITU-R's urban
classes with the air-to-ground model of Al-Hourani et al. (2014)."""
QUEUEING_CHOICES: tuple[str, ...] = ("fq-codel", "mac-only")
SITE_PREFIX = "site:"
"""``site:NAME`` (a site shipped in the package, :func:`shipped_sites`) or ``site:PATH`` (a site
directory): a ray-traced district (:mod:`sim.sites`) as the channel environment;
:func:`sim.channel.area_site` loads and checks it."""
SHIPPED_SITES_DIR = Path(__file__).parent / "sites" / "data"
"""Where the package's prebuilt sites live, one directory each (``sim/sites/data/NAME/``)."""


def site_path(environment: str) -> str | None:
    """What follows ``site:`` (a shipped site's NAME or a PATH) in a site environment; None for
    a named one (:data:`ENVIRONMENTS`). :func:`site_directory` says where the site is."""
    if isinstance(environment, str) and environment.startswith(SITE_PREFIX):
        return environment[len(SITE_PREFIX) :]
    return None


@lru_cache(maxsize=1)
def shipped_sites() -> tuple[str, ...]:
    """The names of the sites shipped in the package (directories of :data:`SHIPPED_SITES_DIR`
    holding a ``site.json``), sorted; ``site:NAME`` takes one of them."""
    if not SHIPPED_SITES_DIR.is_dir():
        return ()
    return tuple(sorted(p.name for p in SHIPPED_SITES_DIR.iterdir() if (p / "site.json").is_file()))


def is_site_name(text: str) -> bool:
    """Whether ``site:TEXT`` names a shipped site rather than a directory: a bare name, with no
    path separator, not ``.`` or ``..`` and not starting with ``~`` (a directory of your own in
    the working directory is ``site:./NAME``)."""
    separators = {"/", os.sep, *((os.altsep,) if os.altsep else ())}
    return (
        bool(text.strip())
        and not any(sep in text for sep in separators)
        and text not in (".", "..")
        and not text.startswith("~")
    )


def site_directory(environment: str) -> Path | None:
    """The directory of a site environment, not checked: a shipped site's for ``site:NAME``
    (:func:`is_site_name`), PATH (``~`` expanded) for ``site:PATH``; None for a named
    environment. :func:`environment_problem` says whether it is usable."""
    path = site_path(environment)
    if path is None:
        return None
    if is_site_name(path):
        return SHIPPED_SITES_DIR / path
    return Path(path).expanduser()


def environment_problem(value: object, *, on_disk: bool = False) -> str | None:
    """What is wrong with ``value`` as a channel environment, None if nothing: it must be one of
    :data:`ENVIRONMENTS`, ``site:NAME`` with NAME one of :func:`shipped_sites`, or ``site:PATH``
    with a non-empty PATH (:func:`site_directory`); with ``on_disk`` (what a command line asks
    before it starts), PATH must also hold a site's two files (:mod:`sim.sites.format`).
    Loading the site, its hash and whether it covers the area are checked where the channel
    takes it (:func:`sim.channel.area_site`)."""
    path = site_path(value) if isinstance(value, str) else None
    if path is None:
        if value in ENVIRONMENTS:
            return None
        return f"must be one of {', '.join(ENVIRONMENTS)}, site:NAME or site:PATH, got {value!r}"
    if not path.strip():
        return "'site:' needs the site directory's path (site:PATH)"
    if is_site_name(path) and path not in shipped_sites():
        shipped = ", ".join(shipped_sites()) or "none"
        return (
            f"{value!r}: no shipped site {path!r} (shipped: {shipped}); a site directory of "
            f"your own is site:PATH with a path separator, e.g. site:./{path}"
        )
    if on_disk:
        from sim.sites.format import DATA_FILE, META_FILE

        directory = site_directory(value)
        assert directory is not None
        if not all((directory / name).is_file() for name in (META_FILE, DATA_FILE)):
            return f"{value!r}: no site there ({META_FILE} and {DATA_FILE})"
    return None


def check_environment(value: object, where: str = "environment", *, on_disk: bool = False) -> str:
    """``value`` if it is a channel environment (:func:`environment_problem`), else an
    :class:`InputError` of one line naming ``where``, the field or option (``environment``,
    ``--environment``, ``world.environment``): e.g. ``--environment: 'site:/x': no site there
    (site.json and site.npz)``. The one check of an environment's name: the area, the world's
    settings and every command line's ``--environment`` use it."""
    problem = environment_problem(value, on_disk=on_disk)
    if problem is not None:
        raise InputError(f"{where}: {problem}")
    return value  # type: ignore[return-value]  # a str: environment_problem said so


@dataclass(frozen=True)
class AreaConfig:
    """The coverage area (paper §II): a rectangle of square zones, and the UAV's altitude band.

    Area frame: origin at the south-west corner, x east, y north, z up, metres.
    Altitude levels are spaced one zone apart (25, 50, 75, 100 m by default), the grid the discrete
    actions move on. ``environment`` is what stands on the ground (:data:`ENVIRONMENTS`): the
    paper's ``open`` field, or one of ITU-R's urban classes, whose buildings block the line of
    sight (:mod:`sim.channel`), or ``site:PATH``, a ray-traced district (:mod:`sim.sites`; only
    its syntax is checked here, the site when the channel loads it).
    """

    size_x_m: float = 500.0
    size_y_m: float = 500.0
    zone_m: float = 25.0
    z_min_m: float = 25.0
    z_max_m: float = 100.0
    user_height_m: float = 1.5
    environment: str = "open"

    def __post_init__(self) -> None:
        check_environment(self.environment)
        for name in ("size_x_m", "size_y_m", "zone_m"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"area.{name}: must be a positive number, got {value!r}")
        for name, size in (("size_x_m", self.size_x_m), ("size_y_m", self.size_y_m)):
            ratio = size / self.zone_m
            if abs(ratio - round(ratio)) > 1e-9:
                raise ValueError(
                    f"area.{name}: {size} m is not a multiple of zone_m ({self.zone_m} m)"
                )
        if not (np.isfinite(self.z_min_m) and np.isfinite(self.z_max_m)):
            raise ValueError("area.z_min_m/z_max_m: must be finite")
        if not 0 < self.z_min_m <= self.z_max_m:
            raise ValueError(
                f"area.z_min_m/z_max_m: need 0 < z_min_m <= z_max_m, "
                f"got {self.z_min_m} and {self.z_max_m}"
            )
        ratio_z = (self.z_max_m - self.z_min_m) / self.zone_m
        if abs(ratio_z - round(ratio_z)) > 1e-9:
            raise ValueError(
                f"area.z_max_m: altitude band {self.z_min_m}-{self.z_max_m} m is not a multiple "
                f"of zone_m ({self.zone_m} m)"
            )

    @property
    def n_zones_x(self) -> int:
        return round(self.size_x_m / self.zone_m)

    @property
    def n_zones_y(self) -> int:
        return round(self.size_y_m / self.zone_m)

    @property
    def n_levels_z(self) -> int:
        return round((self.z_max_m - self.z_min_m) / self.zone_m) + 1

    @property
    def diagonal_m(self) -> float:
        return float(np.hypot(self.size_x_m, self.size_y_m))

    def zone_centres_x_m(self) -> np.ndarray:
        return (np.arange(self.n_zones_x) + 0.5) * self.zone_m

    def zone_centres_y_m(self) -> np.ndarray:
        return (np.arange(self.n_zones_y) + 0.5) * self.zone_m

    def altitude_levels_m(self) -> np.ndarray:
        return self.z_min_m + np.arange(self.n_levels_z) * self.zone_m

    def grid_positions_m(self) -> np.ndarray:
        """Every zone centre at every altitude level, shape (n_x * n_y * n_z, 3), x-major order."""
        gx, gy, gz = np.meshgrid(
            self.zone_centres_x_m(),
            self.zone_centres_y_m(),
            self.altitude_levels_m(),
            indexing="ij",
        )
        return np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)

    def to_dict(self) -> dict[str, float]:
        return {
            "size_x_m": self.size_x_m,
            "size_y_m": self.size_y_m,
            "zone_m": self.zone_m,
            "z_min_m": self.z_min_m,
            "z_max_m": self.z_max_m,
        }


@dataclass(frozen=True)
class RadioConfig:
    """Channel: path loss (Friis in the paper's ``open`` environment, the air-to-ground model of
    :mod:`sim.channel` in the area's urban ones), Rician fast fading (Rayleigh on
    non-line-of-sight links), thermal noise plus a receiver noise figure."""

    frequency_hz: float = 5.18e9  # channel 36
    bandwidth_hz: float = 20e6
    tx_power_dbm: float = 20.0
    noise_figure_db: float = 7.0  # ns-3 YansWifiPhy default
    rician_k_db: float = 13.0
    min_rssi_dbm: float = -90.0  # minimum preamble RSSI: below it a user cannot associate

    @property
    def noise_dbm(self) -> float:
        thermal_dbm = 10.0 * np.log10(1.380649e-23 * 290.0 * self.bandwidth_hz) + 30.0
        return float(thermal_dbm + self.noise_figure_db)


@dataclass(frozen=True)
class PhyConfig:
    """IEEE 802.11ac, 20 MHz, one spatial stream, long guard interval, VHT MCS 0-8.

    ``ideal_threshold_db`` is the SNR at which ns-3's IdealWifiManager starts using each MCS;
    ``per_mid_snr_db`` the SNR at which a 512-byte-payload MPDU fails half the time, and
    ``per_slope_per_db`` the steepness of that waterfall. These three are fitted to ns-3
    (``sim/calibration/fitted.json``: the hand-set values of ``sim.calibration.fit.HAND_SET``
    shifted as a whole; a test keeps the two equal); everything else is from the standard.
    """

    rates_bps: tuple[float, ...] = (6.5e6, 13e6, 19.5e6, 26e6, 39e6, 52e6, 58.5e6, 65e6, 78e6)
    # Highest mandatory non-HT rate not above the data rate: the rate of the Block Ack reply.
    control_rates_bps: tuple[float, ...] = (6e6, 12e6, 12e6, 24e6, 24e6, 24e6, 24e6, 24e6, 24e6)
    ideal_threshold_db: tuple[float, ...] = (1.0, 4.0, 6.5, 10.0, 13.0, 17.5, 19.0, 20.5, 24.5)
    per_mid_snr_db: tuple[float, ...] = (
        -1.25, 1.75, 4.25, 7.75, 10.75, 15.25, 16.75, 18.25, 22.25,
    )  # fmt: skip
    per_slope_per_db: float = 1.0
    symbol_s: float = 4e-6
    vht_preamble_s: float = 40e-6  # L-STF, L-LTF, L-SIG, VHT-SIG-A, VHT-STF, one VHT-LTF, VHT-SIG-B
    legacy_preamble_s: float = 20e-6
    service_tail_bits: int = 22
    max_ppdu_s: float = 5.484e-3

    @property
    def n_mcs(self) -> int:
        return len(self.rates_bps)


@dataclass(frozen=True)
class MacConfig:
    """EDCA best effort, A-MPDU with Block Ack, no RTS/CTS, 802.11ac timing."""

    slot_s: float = 9e-6
    sifs_s: float = 16e-6
    aifsn: int = 3
    cw_min: int = 15
    cw_max: int = 1023
    # The model's contention abstraction (mean idle backoff per TXOP, Bianchi's collision
    # probability) reads this instead of cw_min: it stands in for ns-3's slot-by-slot EDCA and is
    # a fitted constant (sim/calibration/fit.py), while cw_min/cw_max stay ns-3's EDCA settings
    # (the backoff stalls of sim/stalls.py walk that real window ladder).
    contention_cw_min: int = 25
    retry_limit: int = 7
    # Model the expiry of packets during long backoff stalls (sim/stalls.py).
    backoff_stalls: bool = True
    ba_window: int = 64
    max_ampdu_bytes: int = 65535
    block_ack_bytes: int = 32
    mac_overhead_bytes: int = 26 + 4  # QoS data header + FCS
    llc_ip_udp_bytes: int = 8 + 20 + 8
    ampdu_delimiter_bytes: int = 4

    @property
    def aifs_s(self) -> float:
        return self.sifs_s + self.aifsn * self.slot_s


@dataclass(frozen=True)
class QueueConfig:
    """Each station's queues: the Wi-Fi MAC queue and, with ``fq-codel``, the queue disc above."""

    queueing: Queueing = "fq-codel"
    mac_queue_packets: int = 500
    mac_max_delay_s: float = 0.5
    qdisc_limit_packets: int = 10240
    codel_target_s: float = 0.005
    codel_interval_s: float = 0.1
    # Delay reported for a user with traffic that got nothing through in a step.
    unserved_delay_s: float = 1.0

    def __post_init__(self) -> None:
        if self.queueing not in QUEUEING_CHOICES:
            raise ValueError(
                f"queueing: must be one of {', '.join(QUEUEING_CHOICES)}, got {self.queueing!r}"
            )


@dataclass(frozen=True)
class TrafficConfig:
    """Uplink UDP constant bit rate from every user to the UAV."""

    packet_bytes: int = 512
    total_load_bps: float = 40e6


@dataclass(frozen=True)
class UtilityConfig:
    """Paper eq. 1. ``delay_ref_s`` normalises the mean delay (docs/network-model.md: why 1 s)."""

    weight_throughput: float = 0.6
    weight_delay: float = 0.3
    weight_loss: float = 0.1
    delay_ref_s: float = 1.0


@dataclass(frozen=True)
class NetworkConfig:
    """Everything the network model needs, the paper's values by default."""

    radio: RadioConfig = field(default_factory=RadioConfig)
    phy: PhyConfig = field(default_factory=PhyConfig)
    mac: MacConfig = field(default_factory=MacConfig)
    queue: QueueConfig = field(default_factory=QueueConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)

    def with_queueing(self, queueing: Queueing) -> NetworkConfig:
        from dataclasses import replace

        return replace(self, queue=replace(self.queue, queueing=queueing))
