"""Several UAVs, one access point each: the network model of a fleet (K = 1..8 APs).

Each UAV carries one Wi-Fi AP; every user associates with one of them (:mod:`sim.association`:
the strongest by mean received power, with hysteresis) and re-associates as UAVs and users move.
A step of the fleet is the single-cell model (:class:`sim.network.NetworkModel`) run once per
*contention domain*, each with the users associated with its APs:

``distinct`` channels (the default)
    The APs use distinct non-overlapping 20 MHz channels of the 5 GHz band (36, 40, 44, 48,
    52, 56, 60, 64 for K = 1..8): each cell is its own contention domain and no cell hears
    another. The K cells of B fleets go through :meth:`NetworkModel.step_many` as B·K rows of
    one call, row (b, k) holding the users associated with AP k (padded to the fullest cell
    with users that offer nothing and so take no airtime; they are not read back). Path loss
    is computed at the configured carrier (channel 36's 5180 MHz) for every cell: channel 64
    (5320 MHz) would lose 0.23 dB more in free space, which the model ignores. Channels 52–64
    need DFS in most regulatory domains; that is outside the model.

``shared`` channel
    Every AP is on channel 36. Two APs whose mean AP-to-AP received power (free space: the
    UAVs see each other in the air) is at or above ``cca_threshold_dbm`` (−82 dBm, ns-3's
    ``WifiPhy::CcaSensitivity`` default, the carrier-sense level for Wi-Fi frames) defer to one
    another; the connected components of that "hears" relation are the contention domains.
    A domain's users share one EDCA airtime budget: they are stepped as **one cell**, each
    user's link being to its own AP (per-link path loss into the model's kernel). Domains out
    of carrier-sense range of each other transmit at once: each AP's receiver sees the other
    domains' active APs (those with a user offering traffic) as co-channel interference added
    to its noise, the SINR replacing the SNR (interference in dB lowers every link of that AP,
    its rate and its preamble detection alike). This mode builds each link's channel with
    :meth:`sim.network.NetworkModel.link_channel_at` (the single model's, in every environment,
    a site's included: from the link's two ends), adds the interference, and steps the rows
    with :meth:`~sim.network.NetworkModel.step_links`.

**Sites** (``site:PATH``): association hears each AP's mean received power from the site's
lookup at the AP's exact position (no path: :data:`sim.channel.NO_LINK_LOSS_DB`, never heard);
the cells' links are the single model's on the site. AP-to-AP carrier sense stays free space
(the UAVs see each other in the air).

What this abstraction leaves out (its limits): carrier sense is judged AP to AP, standing in
for the stations that actually transmit uplink, so hidden and exposed stations are not
modelled; an interfering domain is taken as always on air while it has traffic (full buffer:
pessimistic for a lightly loaded neighbour) and located at its AP; interference does not
cause collisions of its own, only a lower SINR; domains are recomputed every step from where
the UAVs are.

**Handovers**: a user that moves from one AP to another in a step loses
``handover_outage_s`` of that step (50 ms by default): its throughput is scaled by
``1 − outage_s / step_s`` and the packets of the outage count as lost. Its queues (uplink: in
the user's own device) move with it to the new cell. The value: Mishra, Shin and Arbaugh
("An empirical analysis of the IEEE 802.11 MAC layer handoff process", ACM SIGCOMM CCR 33(2),
2003) measured 53–420 ms for a handoff that scans for the next AP, almost all of it the
probe phase; re-authentication and reassociation alone took a few ms. A station that roams
on a known target (802.11k neighbour reports, 802.11r fast transition, whose design target
is under 50 ms) skips the scan: we take the 50 ms of that target.

**Outputs** (:class:`FleetStepResult`): per user what the single model gives (throughput,
delay, loss, SNR or SINR, connected), its AP and whether it handed over; per UAV the network
utility of its own users; over all users the network utility (:func:`sim.utility.
network_utility`), the served-user fraction (connected users receiving at least
``served_ratio`` of their offered load), Jain's fairness index of per-user throughput and the
minimum user throughput.

**K = 1 is the single-UAV model**: one AP, every user on it, no handover: the same
``step_many`` call the single environment's ``step`` amounts to, bit for bit (tested).

Minimum separation between UAVs is a constraint on the positions the caller gives
(:func:`sim.geometry.enforce_separation`, :func:`sim.geometry.hold_separation`); the model
itself simulates any positions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from numba import njit

from sim.association import NOT_ASSOCIATED, associate, received_power_dbm
from sim.channel import NO_LINK_LOSS_DB, friis_path_loss_db
from sim.config import AreaConfig, NetworkConfig, UtilityConfig
from sim.errors import InputError
from sim.network import NetworkModel, QueueState, StepResult
from sim.utility import network_utility

__all__ = [
    "CHANNELS_5GHZ",
    "CHANNEL_MODES",
    "MAX_UAVS",
    "FleetConfig",
    "FleetModel",
    "FleetState",
    "FleetStepResult",
    "jain_index",
]

MAX_UAVS = 8
CHANNELS_5GHZ: tuple[int, ...] = (36, 40, 44, 48, 52, 56, 60, 64)
"""The non-overlapping 20 MHz channels the APs of a ``distinct`` fleet use, in order."""
CHANNEL_MODES: tuple[str, ...] = ("distinct", "shared")


@dataclass(frozen=True)
class FleetConfig:
    """How many UAVs, how their APs share the spectrum, and the fleet's rules.

    ``n_uavs`` 1..8; ``channel_mode`` ``distinct`` or ``shared`` (module doc);
    ``hysteresis_db`` the roaming margin; ``separation_m`` the minimum 3-D distance between two
    UAVs (> 0); ``handover_outage_s`` what a handover costs; ``cca_threshold_dbm`` the
    carrier-sense level of the shared channel; ``served_ratio`` the share of its offered load a
    user must get to count as served. Bad values raise :class:`InputError` naming the field.
    """

    n_uavs: int = 3
    channel_mode: str = "distinct"
    hysteresis_db: float = 3.0
    separation_m: float = 10.0
    handover_outage_s: float = 0.05
    cca_threshold_dbm: float = -82.0
    served_ratio: float = 0.9

    def __post_init__(self) -> None:
        k = self.n_uavs
        if isinstance(k, bool) or not isinstance(k, int | np.integer) or not 1 <= k <= MAX_UAVS:
            raise InputError(f"n_uavs: must be an integer in 1..{MAX_UAVS}, got {k!r}")
        object.__setattr__(self, "n_uavs", int(k))
        if self.channel_mode not in CHANNEL_MODES:
            raise InputError(
                f"channel_mode: must be one of {', '.join(CHANNEL_MODES)}, "
                f"got {self.channel_mode!r}"
            )
        for name, low, strict in (
            ("separation_m", 0.0, True),
            ("hysteresis_db", 0.0, False),
            ("handover_outage_s", 0.0, False),
        ):
            value = getattr(self, name)
            ok = isinstance(value, int | float) and math.isfinite(value)
            ok = ok and (value > low if strict else value >= low)
            if not ok:
                raise InputError(f"{name}: must be {'>' if strict else '>='} 0, got {value!r}")
        if not math.isfinite(self.cca_threshold_dbm):
            raise InputError(f"cca_threshold_dbm: must be finite, got {self.cca_threshold_dbm!r}")
        if not 0.0 <= self.served_ratio <= 1.0:
            raise InputError(f"served_ratio: must lie in [0, 1], got {self.served_ratio!r}")

    @property
    def channels(self) -> tuple[int, ...]:
        """Each AP's 5 GHz channel number."""
        if self.channel_mode == "shared":
            return (CHANNELS_5GHZ[0],) * self.n_uavs
        return CHANNELS_5GHZ[: self.n_uavs]


@dataclass(frozen=True)
class FleetState:
    """What carries over between steps, for B fleets and U users: each user's queues (B, U)
    (they move with the user), its AP (B, U) (``-1``: none yet), handovers so far (B,)."""

    queues: QueueState
    association: np.ndarray
    handovers: np.ndarray

    @classmethod
    def empty(cls, batch: int, n_users: int) -> FleetState:
        return cls(
            QueueState.empty(batch, n_users),
            np.full((batch, n_users), NOT_ASSOCIATED, dtype=np.int64),
            np.zeros(batch, dtype=np.int64),
        )


@dataclass(frozen=True)
class FleetStepResult:
    """One step of B fleets: per user (B, U), per UAV (B, K), per fleet (B,)."""

    throughput_bps: np.ndarray
    delay_s: np.ndarray
    plr: np.ndarray
    snr_db: np.ndarray  # the SINR on a shared channel with interference
    connected: np.ndarray
    association: np.ndarray
    handover: np.ndarray
    served: np.ndarray
    state: FleetState
    uav_utility: np.ndarray  # 0 for a UAV that serves nobody
    utility: np.ndarray
    served_fraction: np.ndarray
    jain_fairness: np.ndarray
    min_throughput_bps: np.ndarray
    domain: np.ndarray  # (B, K): the lowest AP index of each AP's contention domain
    interference_dbm: np.ndarray  # (B, K): co-channel interference at each AP (-inf: none)

    @property
    def handovers(self) -> np.ndarray:
        """Handovers so far (B,), this step's included."""
        return self.state.handovers


def jain_index(values: np.ndarray) -> np.ndarray:
    """Jain's fairness index over the last axis, ``(Σx)² / (n·Σx²)``; 1 when every value is 0
    (equal shares, the convention :func:`sim.utility.heterogeneity_index` uses for loads)."""
    x = np.asarray(values, dtype=float)
    total = x.sum(axis=-1)
    squares = (x * x).sum(axis=-1)
    n = x.shape[-1]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(squares > 0, total * total / (n * np.where(squares > 0, squares, 1.0)), 1.0)


@dataclass
class FleetModel:
    """The fleet's model for one configuration; :meth:`step` is pure (state in, state out)."""

    fleet: FleetConfig = field(default_factory=FleetConfig)
    config: NetworkConfig = field(default_factory=NetworkConfig)
    area: AreaConfig = field(default_factory=AreaConfig)
    utility: UtilityConfig = field(default_factory=UtilityConfig)
    model: NetworkModel | None = None

    def __post_init__(self) -> None:
        if self.model is None:
            self.model = NetworkModel(self.config, self.area)
        elif self.model.config != self.config or self.model.area != self.area:
            raise ValueError("model: must be built for this fleet's network config and area")
        radio = self.config.radio
        self._noise_mw = 10.0 ** (radio.noise_dbm / 10.0)
        self._outage = self.fleet.handover_outage_s

    @property
    def n_uavs(self) -> int:
        return self.fleet.n_uavs

    def initial_state(self, batch: int, n_users: int) -> FleetState:
        return FleetState.empty(batch, n_users)

    def step(
        self,
        uav_xyz_m: np.ndarray,
        users_xy_m: np.ndarray,
        load_bps: np.ndarray,
        state: FleetState | None = None,
        rng: np.random.Generator | None = None,
        step_s: float = 1.0,
    ) -> FleetStepResult:
        """Simulate ``step_s`` seconds of B fleets placed at ``uav_xyz_m`` (B, K, 3), or one
        fleet (K, 3), over the same users ``users_xy_m`` (U, 2) offering ``load_bps`` (U,).

        Users (re-)associate first (from ``state``'s associations), then each contention
        domain is simulated; ``rng`` as in :meth:`NetworkModel.step` (``None``: expected mode).
        Bad shapes or values raise :class:`InputError` naming the argument.
        """
        uav, users, load = self._check(uav_xyz_m, users_xy_m, load_bps, step_s)
        batch, k, n_users = uav.shape[0], uav.shape[1], users.shape[0]
        if state is None:
            state = FleetState.empty(batch, n_users)
        elif state.association.shape != (batch, n_users) or state.queues.backlog_pkts.shape != (
            batch,
            n_users,
        ):
            raise InputError(
                f"state: arrays must be ({batch}, {n_users}) for {batch} fleets and {n_users} "
                f"users, got {state.association.shape}"
            )
        radio = self.config.radio
        rx = self._received_power_dbm(uav, users)
        previous = state.association
        assoc, handover = associate(
            rx,
            previous,
            self.fleet.hysteresis_db,
            radio.min_rssi_dbm,
        )
        queues = state.queues
        if self.fleet.channel_mode == "shared" and k > 1:
            per_user, domain, interference = self._step_shared(
                uav, users, load, queues, assoc, rng, step_s
            )
        else:
            per_user = self._step_distinct(uav, users, load, queues, assoc, rng, step_s)
            domain, interference = _separate_domains(batch, k)
        throughput, delay, plr, queues_out, snr, connected = per_user
        c = self.utility
        # Throughput and loss are fresh arrays: the handover outage is applied in place.
        uav_utility, served, served_fraction, jain, min_throughput, handovers = _fleet_metrics(
            throughput, delay, plr, load, connected, assoc, handover,
            min(self._outage / step_s, 1.0), k, self.fleet.served_ratio,
            c.weight_throughput, c.weight_delay, c.weight_loss, c.delay_ref_s,
        )  # fmt: skip
        new_state = FleetState(queues_out, assoc, state.handovers + handovers)
        return FleetStepResult(
            throughput_bps=throughput,
            delay_s=delay,
            plr=plr,
            snr_db=snr,
            connected=connected,
            association=assoc,
            handover=handover,
            served=served,
            state=new_state,
            uav_utility=uav_utility,
            utility=self._utility(throughput, delay, plr, load),
            served_fraction=served_fraction,
            jain_fairness=jain,
            min_throughput_bps=min_throughput,
            domain=domain,
            interference_dbm=interference,
        )

    # -- the two channel modes --------------------------------------------------------------
    def _step_distinct(
        self,
        uav: np.ndarray,
        users: np.ndarray,
        load: np.ndarray,
        queues: QueueState,
        assoc: np.ndarray,
        rng: np.random.Generator | None,
        step_s: float,
    ) -> tuple[np.ndarray, ...]:
        """Each cell its own domain: the cells of every fleet as the rows of one
        :meth:`NetworkModel.step_many` call, each row holding its own users only."""
        batch, k, _ = uav.shape
        assert self.model is not None
        if k == 1:
            # Every user is on the one AP: the inputs as they are (bit-identical to the single
            # model's step, the same fading draws).
            n_users = users.shape[0]
            result = self.model.step_many(
                uav.reshape(batch, 3),
                np.broadcast_to(users, (batch, n_users, 2)),
                np.broadcast_to(load, (batch, n_users)),
                queues,
                rng,
                step_s,
            )
            return (
                result.throughput_bps,
                result.delay_s,
                result.plr,
                result.state,
                result.snr_db,
                result.connected,
            )
        index = _row_index(assoc, k)
        rows_users, rows_load, rows_queues = _gather_cells(users, load, *queues.arrays, index, k)
        result = self.model.step_many(
            uav.reshape(batch * k, 3), rows_users, rows_load, QueueState(*rows_queues), rng, step_s
        )
        return _scatter_result(index, batch, users.shape[0], result)

    def _step_shared(
        self,
        uav: np.ndarray,
        users: np.ndarray,
        load: np.ndarray,
        queues: QueueState,
        assoc: np.ndarray,
        rng: np.random.Generator | None,
        step_s: float,
    ) -> tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray]:
        """One channel: domains of APs in carrier-sense range stepped as one cell each, the
        other domains' active APs added to each AP's noise."""
        batch, k, _ = uav.shape
        n_users = users.shape[0]
        member = assoc[:, None, :] == np.arange(k)[None, :, None]  # (B, K, U)
        radio = self.config.radio
        # AP-to-AP mean received power: free space between two UAVs in the air.
        gap = uav[:, :, None, :] - uav[:, None, :, :]
        ap_rx = radio.tx_power_dbm - friis_path_loss_db(
            np.sqrt(np.sum(gap * gap, axis=-1)), radio.frequency_hz
        )
        hears = ap_rx >= self.fleet.cca_threshold_dbm
        hears |= np.eye(k, dtype=bool)
        domain = _components(hears)  # (B, K)
        active = np.any(
            member & ((load > 0) | (queues.backlog_pkts > 0))[:, None, :], axis=2
        )  # (B, K)
        other = domain[:, :, None] != domain[:, None, :]  # [b, i, j]: j interferes at i
        power_mw = np.where(other & active[:, None, :], 10.0 ** (ap_rx / 10.0), 0.0)
        interference_mw = power_mw.sum(axis=2)  # (B, K)
        with np.errstate(divide="ignore"):
            interference_dbm = 10.0 * np.log10(interference_mw)
        penalty_db = 10.0 * np.log10(1.0 + interference_mw / self._noise_mw)

        # Each user's link to its own AP, then the rows: row (b, d) holds the users whose AP
        # is in domain d (d an AP index; rows of indices that are no domain's lowest are empty).
        own = np.take_along_axis(uav, assoc[:, :, None], axis=1)  # (B, U, 3)
        index = _row_index(np.take_along_axis(domain, assoc, axis=1), k)
        # Padding: an AP 1 m above a user at the origin (what the kernel never reads back).
        pad_xyz = (0.0, 0.0, self.area.user_height_m + 1.0)
        rows_ap = np.stack(
            [_gather(np.ascontiguousarray(own[..., i]), index, k, pad_xyz[i]) for i in range(3)],
            axis=-1,
        )
        rows_penalty = _gather(np.take_along_axis(penalty_db, assoc, axis=1), index, k, 0.0)
        rows_users, rows_load, rows_queues = _gather_cells(users, load, *queues.arrays, index, k)
        assert self.model is not None
        loss, gains = self.model.link_channel_at(rows_ap, rows_users, rng)
        result = self.model.step_links(
            loss + rows_penalty, gains, rows_users, rows_load, QueueState(*rows_queues), step_s
        )
        return _scatter_result(index, batch, n_users, result), domain, interference_dbm

    def _received_power_dbm(self, uav: np.ndarray, users: np.ndarray) -> np.ndarray:
        """Each AP's mean received power at each user (B, K, U), what association hears:
        :func:`sim.association.received_power_dbm`, or on a site the site's mean loss at the
        AP's exact position (no path: :data:`~sim.channel.NO_LINK_LOSS_DB`)."""
        radio = self.config.radio
        assert self.model is not None
        site = self.model.site
        if site is None:
            return received_power_dbm(uav, users, self.area, radio)
        from sim.sites.lookup import path_loss_db

        loss = path_loss_db(site, uav.reshape(-1, 3), users).reshape(*uav.shape[:2], -1)
        return radio.tx_power_dbm - np.minimum(loss, NO_LINK_LOSS_DB)

    # -- metrics ----------------------------------------------------------------------------
    def _utility(
        self, throughput: np.ndarray, delay: np.ndarray, plr: np.ndarray, load: np.ndarray
    ) -> np.ndarray:
        if throughput.shape[0] == 1:
            # One fleet: the single environment's own (1-D) path, the same floats.
            value = network_utility(throughput[0], delay[0], plr[0], load, self.utility)
            return np.array([float(value)])
        return network_utility(throughput, delay, plr, load, self.utility)

    # -- input checks -----------------------------------------------------------------------
    def _check(
        self, uav_xyz_m: np.ndarray, users_xy_m: np.ndarray, load_bps: np.ndarray, step_s: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        k = self.fleet.n_uavs
        uav = np.asarray(uav_xyz_m, dtype=float)
        if uav.ndim == 2:
            uav = uav[None]
        if uav.ndim != 3 or uav.shape[1:] != (k, 3):
            raise InputError(
                f"uav_xyz_m: must be ({k}, 3) or (B, {k}, 3) positions for {k} UAVs, "
                f"got shape {np.shape(uav_xyz_m)}"
            )
        users = np.asarray(users_xy_m, dtype=float)
        if users.ndim != 2 or users.shape[1] != 2 or users.shape[0] < 1:
            raise InputError(f"users_xy_m: must be (U, 2) positions, got shape {users.shape}")
        load = np.asarray(load_bps, dtype=float)
        if load.shape != (users.shape[0],):
            raise InputError(
                f"load_bps: must hold one load per user ({users.shape[0]}), got shape {load.shape}"
            )
        if not NetworkModel.values_ok(uav, users, load):  # the single model's one-pass check
            for name, values in (("uav_xyz_m", uav), ("users_xy_m", users), ("load_bps", load)):
                if not np.all(np.isfinite(values)):
                    raise InputError(f"{name}: must be finite")
            if load.min() < 0:
                raise InputError("load_bps: loads must be non-negative")
            raise InputError("uav_xyz_m, users_xy_m, load_bps: values too large to simulate")
        if not (math.isfinite(step_s) and step_s > 0):
            raise InputError(f"step_s: must be a positive number, got {step_s!r}")
        return uav, users, load


@lru_cache(maxsize=64)
def _separate_domain_arrays(batch: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    domain = np.broadcast_to(np.arange(k), (batch, k)).copy()
    interference = np.full((batch, k), -np.inf)
    for array in (domain, interference):
        array.setflags(write=False)  # cached: shared by every result with this shape
    return domain, interference


def _separate_domains(batch: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Distinct channels: every AP its own domain (B, K), no interference (B, K) of -inf
    (read-only arrays, shared between results)."""
    return _separate_domain_arrays(batch, k)


def _components(hears: np.ndarray) -> np.ndarray:
    """Connected components of a symmetric "hears" relation (B, K, K), as the lowest index of
    each node's component (B, K): transitive closure by repeated squaring."""
    reach = hears.astype(np.int64)
    for _ in range(max(1, math.ceil(math.log2(max(hears.shape[-1], 2))))):
        reach = (reach @ reach > 0).astype(np.int64)
    return np.argmax(reach > 0, axis=2)


@njit(cache=True, nogil=True)
def _row_index(row_of_user: np.ndarray, k: int) -> np.ndarray:
    """Rows of the fleets' cells (B·K, n): row b·K + r lists, in user order, the users u with
    ``row_of_user[b, u] == r``, padded with -1 to the fullest row's count n."""
    batch, n_users = row_of_user.shape
    counts = np.zeros((batch, k), dtype=np.int64)
    for b in range(batch):
        for u in range(n_users):
            counts[b, row_of_user[b, u]] += 1
    width = max(counts.max(), 1)
    index = np.full((batch * k, width), -1, dtype=np.int64)
    fill = np.zeros((batch, k), dtype=np.int64)
    for b in range(batch):
        for u in range(n_users):
            r = row_of_user[b, u]
            index[b * k + r, fill[b, r]] = u
            fill[b, r] += 1
    return index


@njit(cache=True, nogil=True)
def _gather(values: np.ndarray, index: np.ndarray, k: int, pad: float) -> np.ndarray:
    """Per-user values (B, U) laid out in rows (B·K, n), ``pad`` where a row has no user."""
    out = np.full(index.shape, pad)
    for r in range(index.shape[0]):
        b = r // k
        for j in range(index.shape[1]):
            u = index[r, j]
            if u >= 0:
                out[r, j] = values[b, u]
    return out


@njit(cache=True, nogil=True)
def _gather_cells(
    users: np.ndarray,
    load: np.ndarray,
    backlog: np.ndarray,
    codel: np.ndarray,
    at_cap: np.ndarray,
    index: np.ndarray,
    k: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a cell's row needs, laid out in rows (B·K, n) by ``index``: the users' positions
    (B·K, n, 2) from (U, 2), their offered load from (U,), and the three queue arrays (3,
    B·K, n) from (B, U) each. Padding offers nothing, at the origin, with empty queues (where
    it stands does not matter). One pass: a compiled call per array cost more than the work."""
    rows, width = index.shape
    xy = np.zeros((rows, width, 2))
    offered = np.zeros((rows, width))
    queues = np.zeros((3, rows, width))
    for r in range(rows):
        b = r // k
        for j in range(width):
            u = index[r, j]
            if u >= 0:
                xy[r, j, 0] = users[u, 0]
                xy[r, j, 1] = users[u, 1]
                offered[r, j] = load[u]
                queues[0, r, j] = backlog[b, u]
                queues[1, r, j] = codel[b, u]
                queues[2, r, j] = at_cap[b, u]
    return xy, offered, queues


@njit(cache=True, nogil=True)
def _scatter_cells(
    index: np.ndarray,
    k: int,
    n_users: int,
    throughput: np.ndarray,
    delay: np.ndarray,
    plr: np.ndarray,
    backlog: np.ndarray,
    codel: np.ndarray,
    at_cap: np.ndarray,
    snr: np.ndarray,
    connected: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The rows' outputs (B·K, n) back to per-user arrays: one block (7, B, U) in the order
    of the arguments, and connected (B, U). Every user is in exactly one row."""
    batch = index.shape[0] // k
    out = np.empty((7, batch, n_users))
    linked = np.empty((batch, n_users), dtype=np.bool_)
    for r in range(index.shape[0]):
        b = r // k
        for j in range(index.shape[1]):
            u = index[r, j]
            if u >= 0:
                out[0, b, u] = throughput[r, j]
                out[1, b, u] = delay[r, j]
                out[2, b, u] = plr[r, j]
                out[3, b, u] = backlog[r, j]
                out[4, b, u] = codel[r, j]
                out[5, b, u] = at_cap[r, j]
                out[6, b, u] = snr[r, j]
                linked[b, u] = connected[r, j]
    return out, linked


def _scatter_result(
    index: np.ndarray, batch: int, n_users: int, result: StepResult
) -> tuple[np.ndarray | QueueState, ...]:
    """The rows' step (B·K, n) back to per-user arrays (B, U): throughput, delay, loss, the
    queue state, SNR and connected, in that order (fresh arrays: views of one new block)."""
    k = index.shape[0] // batch
    out, connected = _scatter_cells(
        index,
        k,
        n_users,
        result.throughput_bps,
        result.delay_s,
        result.plr,
        *result.state.arrays,
        result.snr_db,
        result.connected,
    )
    throughput, delay, plr, backlog, codel, at_cap, snr = out
    return throughput, delay, plr, QueueState(backlog, codel, at_cap), snr, connected


@njit(cache=True, nogil=True)
def _fleet_metrics(
    throughput: np.ndarray,
    delay: np.ndarray,
    plr: np.ndarray,
    load: np.ndarray,
    connected: np.ndarray,
    assoc: np.ndarray,
    handover: np.ndarray,
    outage: float,
    k: int,
    served_ratio: float,
    weight_throughput: float,
    weight_delay: float,
    weight_loss: float,
    delay_ref_s: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """First the handover outage (a user that handed over loses ``outage`` of the step: its
    throughput scaled by 1 − outage, the outage's packets lost), in place; then per UAV the
    network utility of its users (0 for none), per fleet who is served, the served fraction,
    Jain's index of throughput (1 when all are 0), the minimum, and the handovers (B,)."""
    batch, n_users = throughput.shape
    handovers = np.zeros(batch, dtype=np.int64)
    for b in range(batch):
        for u in range(n_users):
            if handover[b, u]:
                handovers[b] += 1
                if outage > 0.0:
                    throughput[b, u] *= 1.0 - outage
                    plr[b, u] += (1.0 - plr[b, u]) * outage
    uav_utility = np.zeros((batch, k))
    served = np.empty((batch, n_users), dtype=np.bool_)
    served_fraction = np.empty(batch)
    jain = np.empty(batch)
    minimum = np.empty(batch)
    sums = np.zeros((k, 5))  # count, offered, throughput, delay, loss
    for b in range(batch):
        sums[:] = 0.0
        total = 0.0
        squares = 0.0
        n_served = 0
        low = np.inf
        for u in range(n_users):
            x = throughput[b, u]
            served[b, u] = connected[b, u] and x >= served_ratio * load[u]
            n_served += 1 if served[b, u] else 0
            total += x
            squares += x * x
            low = min(low, x)
            a = assoc[b, u]
            sums[a, 0] += 1.0
            sums[a, 1] += load[u]
            sums[a, 2] += x
            sums[a, 3] += delay[b, u]
            sums[a, 4] += plr[b, u]
        for a in range(k):
            count = sums[a, 0]
            if count > 0:
                t = min(sums[a, 2] / max(sums[a, 1], 1e-12), 1.0)
                d = min(sums[a, 3] / count / delay_ref_s, 1.0)
                p = min(sums[a, 4] / count, 1.0)
                uav_utility[b, a] = (
                    weight_throughput * max(t, 0.0)
                    + weight_delay * (1.0 - max(d, 0.0))
                    + weight_loss * (1.0 - max(p, 0.0))
                )
        served_fraction[b] = n_served / n_users
        jain[b] = total * total / (n_users * squares) if squares > 0 else 1.0
        minimum[b] = low
    return uav_utility, served, served_fraction, jain, minimum, handovers
