"""The embedded network model: one step of the FAP's Wi-Fi cell for a batch of UAV positions.

``NetworkModel.step`` takes B candidate UAV positions and one scenario (U users with their
offered loads) and returns each user's throughput, mean delay and packet loss over the step, for
every position at once. For each position and user the pipeline is:

1. ``channel``: 3-D distance, path loss (Friis in the ``open`` environment; free space plus the
   air-to-ground excess loss of a line-of-sight or non-line-of-sight link in the urban ones;
   on a site, ``site:PATH``, the ray-traced loss at the UAV's exact position, :mod:`sim.channel`),
   noise → SNR; users under the minimum preamble RSSI are disconnected and lose everything they
   send. A site's link with no path at all is out of coverage: its loss enters the kernel as
   :data:`~sim.channel.NO_LINK_LOSS_DB` (finite, so the SNR stays a number; the user is
   disconnected and gets no throughput).
2. ``phy``: ideal rate selection under fast fading → the user's link (TXOP overhead, subframe
   airtime, A-MPDU size limit, subframe success).
3. ``mac``: fair sharing of transmit opportunities among stations with traffic, solved exactly,
   with contention and collisions folded into the TXOP overhead (two passes: the number of
   contenders depends on who turns out to be backlogged).
4. ``queues``: each station's backlog over the step, its drops, and its delivered packets'
   wait (for the delay).

The per-position work is one compiled (numba) kernel: a step of 3 users costs microseconds, so
training needs no lookup tables or approximations beyond the model itself. Expected mode
(``rng=None``) is deterministic; with a ``numpy.random.Generator`` the rate manager's fading draws
are sampled each step. Queue state carries over between steps: pass the previous ``state`` back.

``NetworkModel.step_many`` runs E independent cells (each its own users and loads, one UAV
position each) through the same kernel in one call: the model side of a vectorised environment.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numba import njit

from sim.channel import (
    MAX_FREQUENCY_HZ,
    MIN_FREQUENCY_HZ,
    NO_LINK_LOSS_DB,
    SPEED_OF_LIGHT_MPS,
    air_to_ground,
    area_site,
    draw_link_channel,
    elevation_deg,
    friis_path_loss_db,
    los_probability,
    mean_path_loss_db,
    rician_power_gain,
    site_link_channel,
)
from sim.config import AreaConfig, NetworkConfig
from sim.errors import InputError
from sim.mac import (
    collision_table,
    contention_overhead,
    effective_contenders,
    fair_txop_rate,
    idle_slots_per_transmission,
)
from sim.phy import LinkTable, expected_link, sampled_link
from sim.queues import advance_queue
from sim.stalls import mean_backoff_slots, stall_lookup, stall_table

if TYPE_CHECKING:
    from sim.sites.format import Site

# Fading draws of the rate manager per user and step in stochastic mode.
RATE_DRAWS_PER_STEP = 8
# Sharing passes with backoff stalls, and how far each pass moves the stall estimate.
STALL_PASSES = 6
STALL_DAMPING = 0.5
STALL_TOLERANCE = 1e-2


@dataclass(frozen=True)
class QueueState:
    """What carries over between steps, arrays (B, U): packets queued, CoDel's drop count, and
    how long each queue has been full (:mod:`sim.queues`: it sets the delivered packets' wait)."""

    backlog_pkts: np.ndarray
    codel_count: np.ndarray
    at_cap_s: np.ndarray

    @classmethod
    def empty(cls, batch: int, n_users: int) -> QueueState:
        return cls(
            np.zeros((batch, n_users)), np.zeros((batch, n_users)), np.zeros((batch, n_users))
        )

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The three arrays, in field order."""
        return self.backlog_pkts, self.codel_count, self.at_cap_s

    def map(self, f: Callable[[np.ndarray], np.ndarray]) -> QueueState:
        """The same state with ``f`` applied to every array (a selection, a gather ...)."""
        return QueueState(*(f(a) for a in self.arrays))

    def same_as(self, other: QueueState) -> np.ndarray:
        """Per row (B,): whether every queue of the row is exactly as in ``other``."""
        return np.all(
            [np.all(a == b, axis=1) for a, b in zip(self.arrays, other.arrays, strict=True)],
            axis=0,
        )


@dataclass(frozen=True)
class StepResult:
    """Per-user metrics of one step, arrays (B, U), and the queue state to carry over."""

    throughput_bps: np.ndarray
    delay_s: np.ndarray
    plr: np.ndarray
    state: QueueState
    snr_db: np.ndarray
    connected: np.ndarray


class _Constants(NamedTuple):
    """Everything the compiled kernel needs, flattened from the configuration."""

    tx_power_dbm: float
    path_loss_1m_db: float
    noise_dbm: float
    min_rssi_dbm: float
    user_height_m: float
    expected: np.ndarray
    per_mid_db: np.ndarray
    per_slope: float
    threshold_db: np.ndarray
    collision_table: np.ndarray
    slot_s: float
    contention_cw_min: int
    cw_min: int
    cw_max: int
    backoff_stalls: bool
    stall_table: np.ndarray
    sharing_passes: int
    aifs_s: float
    transmissions: int
    mac_queue_packets: float
    mac_max_delay_s: float
    qdisc_limit_packets: float
    codel_target_s: float
    codel_interval_s: float
    unserved_delay_s: float


@dataclass
class NetworkModel:
    """The cell's model for one configuration: tables are built once, ``step`` is pure.

    On a site (``area.environment`` ``site:PATH``) the site is loaded and checked once, here
    (:func:`sim.channel.area_site`: InputError naming ``environment`` for a missing, broken or
    too small site), and every link's channel comes from it (:func:`sim.channel.
    site_link_channel`): the mean loss in expected mode, the loss and fading by line of sight
    otherwise."""

    config: NetworkConfig = field(default_factory=NetworkConfig)
    area: AreaConfig = field(default_factory=AreaConfig)

    def __post_init__(self) -> None:
        c = self.config
        self.links = LinkTable.build(c.radio, c.phy, c.mac, c.traffic)
        mcs = self.links.mcs
        self._packet_bits = 8.0 * c.traffic.packet_bytes
        self._k = _Constants(
            tx_power_dbm=c.radio.tx_power_dbm,
            path_loss_1m_db=float(
                20.0 * np.log10(4.0 * np.pi * c.radio.frequency_hz / SPEED_OF_LIGHT_MPS)
            ),
            noise_dbm=c.radio.noise_dbm,
            min_rssi_dbm=c.radio.min_rssi_dbm,
            user_height_m=self.area.user_height_m,
            expected=np.ascontiguousarray(self.links.expected),
            per_mid_db=mcs.per_mid_db,
            per_slope=mcs.per_slope,
            threshold_db=mcs.threshold_db,
            collision_table=collision_table(c.mac),
            slot_s=c.mac.slot_s,
            contention_cw_min=c.mac.contention_cw_min,
            cw_min=c.mac.cw_min,
            cw_max=c.mac.cw_max,
            backoff_stalls=c.mac.backoff_stalls,
            stall_table=stall_table(c.queue.mac_max_delay_s, c.mac.cw_min, c.mac.cw_max),
            sharing_passes=STALL_PASSES if c.mac.backoff_stalls else 2,
            aifs_s=c.mac.aifs_s,
            transmissions=c.mac.retry_limit + 1,
            mac_queue_packets=float(c.queue.mac_queue_packets),
            mac_max_delay_s=c.queue.mac_max_delay_s,
            qdisc_limit_packets=(
                float(c.queue.qdisc_limit_packets) if c.queue.queueing == "fq-codel" else 0.0
            ),
            codel_target_s=c.queue.codel_target_s,
            codel_interval_s=c.queue.codel_interval_s,
            unserved_delay_s=c.queue.unserved_delay_s,
        )
        # The kernel takes a plain tuple: numba types it much faster than a named tuple.
        self._kt = tuple(self._k)
        self._site = area_site(self.area)
        params = None if self._site is not None else air_to_ground(self.area.environment)
        self._urban = params is not None
        # An urban link's excess loss (dB) in each LoS state, at this carrier: fixed per model.
        self._excess_db = params.excess_db(c.radio.frequency_hz) if params is not None else None
        if self._urban and not (MIN_FREQUENCY_HZ <= c.radio.frequency_hz <= MAX_FREQUENCY_HZ):
            raise InputError(
                f"frequency_hz: the urban environments' model covers 1–7 GHz, got "
                f"{c.radio.frequency_hz!r}"
            )

    @property
    def site(self) -> Site | None:
        """The area's site (``site:PATH``), or None in a statistical environment."""
        return self._site

    def initial_state(self, batch: int, n_users: int) -> QueueState:
        return QueueState.empty(batch, n_users)

    def step(
        self,
        uav_xyz_m: np.ndarray,
        users_xy_m: np.ndarray,
        load_bps: np.ndarray,
        state: QueueState | None = None,
        rng: np.random.Generator | None = None,
        step_s: float = 1.0,
    ) -> StepResult:
        """Simulate ``step_s`` seconds for each of the B positions in ``uav_xyz_m`` (B, 3).

        ``users_xy_m`` is (U, 2), ``load_bps`` (U,), ``state`` (if given) holds (B, U) arrays.
        Shapes and values are checked here, once per call, before anything is drawn from
        ``rng``: a mismatch, a non-finite position or load, a negative load or a non-positive
        ``step_s`` raises :class:`~sim.errors.InputError` naming the argument. With ``rng``, the
        step draws :func:`~sim.channel.rician_power_gain` of shape (B, U,
        :data:`RATE_DRAWS_PER_STEP`): every position sees the same scenario, its own draws.
        """
        uav = np.asarray(uav_xyz_m, dtype=float)
        if uav.ndim < 2:
            uav = uav.reshape(1, -1)  # np.atleast_2d, without its overhead
        users = np.asarray(users_xy_m, dtype=float)
        load = np.asarray(load_bps, dtype=float)
        batch, n_users = _check_step_shapes(uav, users, load)
        return self._run(
            uav,
            users.reshape(1, n_users, 2),
            load.reshape(1, n_users),
            state,
            rng,
            step_s,
            batch,
            n_users,
            "positions",
        )

    def step_many(
        self,
        uav_xyz_m: np.ndarray,
        users_xy_m: np.ndarray,
        load_bps: np.ndarray,
        state: QueueState | None = None,
        rng: np.random.Generator | None = None,
        step_s: float = 1.0,
    ) -> StepResult:
        """Simulate ``step_s`` seconds of E independent cells at once (a vectorised environment).

        ``uav_xyz_m`` is (E, 3), ``users_xy_m`` (E, U, 2), ``load_bps`` (E, U), ``state`` (if
        given) holds (E, U) arrays; every cell has its own users and loads (unlike :meth:`step`,
        whose B positions share one scenario), and the same number of users U. The result's
        arrays are (E, U). Row e is exactly what ``step(uav_xyz_m[e], users_xy_m[e],
        load_bps[e], state_e, ...)`` gives with the same fading draws; in expected mode
        (``rng=None``) that is the whole contract.

        Draw order (stochastic mode): one call ``rician_power_gain(rng, K, (E, U,
        RATE_DRAWS_PER_STEP))``, the draws :meth:`step` takes for E positions: the real parts
        of every (cell, user, draw) in C order, then all the imaginary parts. Cell e gets
        ``[:, e]`` of those two blocks, so E separate :meth:`step` calls on one generator draw
        the same numbers in a different order (real, imaginary, per cell).
        """
        uav = np.asarray(uav_xyz_m, dtype=float)
        users = np.asarray(users_xy_m, dtype=float)
        load = np.asarray(load_bps, dtype=float)
        n_envs, n_users = _check_many_shapes(uav, users, load)
        return self._run(uav, users, load, state, rng, step_s, n_envs, n_users, "environments")

    def _run(
        self,
        uav: np.ndarray,
        users: np.ndarray,
        load: np.ndarray,
        state: QueueState | None,
        rng: np.random.Generator | None,
        step_s: float,
        batch: int,
        n_users: int,
        rows: str,
    ) -> StepResult:
        """Check values, draw the fading, run the kernel: ``users`` (1 or N, U, 2), ``load`` (1
        or N, U) with the shapes already checked."""
        shape = (batch, n_users)
        bad_state = state is not None and (
            state.backlog_pkts.shape != shape
            or state.codel_count.shape != shape
            or state.at_cap_s.shape != shape
        )
        values_ok = _values_ok(uav, users, load)
        if bad_state or not values_ok or not (math.isfinite(step_s) and step_s > 0):
            # The slow path names the first bad argument, in the order it always has.
            _check_step_values(uav, users, load, step_s)
            if bad_state:
                assert state is not None
                raise InputError(
                    f"state: queue arrays must be ({batch}, {n_users}) for {batch} {rows} and "
                    f"{n_users} users, got {', '.join(str(a.shape) for a in state.arrays)}"
                )
        if state is None:  # one array of zeros serves all three (the kernel only reads them)
            zeros = np.zeros(shape)
            queues = QueueState(zeros, zeros, zeros)
        else:
            queues = state
        path_loss = _FREE_SPACE
        if self._site is not None:
            path_loss, log_gains = self._site_channel(uav, users, rng)
        elif self._urban:
            path_loss, log_gains = self._urban_channel(uav, users, rng, batch, n_users)
        elif rng is None:
            log_gains = _NO_DRAWS
        else:
            log_gains = rician_power_gain(
                rng, self.config.radio.rician_k_db, (batch, n_users, RATE_DRAWS_PER_STEP)
            )
        if rng is not None:
            np.log10(log_gains, out=log_gains)  # the kernel scales by 10: gains in dB
        return self._kernel(uav, users, load, queues, log_gains, path_loss, step_s)

    def _kernel(
        self,
        uav: np.ndarray,
        users: np.ndarray,
        load: np.ndarray,
        queues: QueueState,
        log_gains: np.ndarray,
        path_loss: np.ndarray,
        step_s: float,
    ) -> StepResult:
        """The compiled step over (N, U) rows, its outputs as a :class:`StepResult`."""
        batch, n_users = queues.backlog_pkts.shape
        out = np.empty((7, batch, n_users))
        connected = np.empty((batch, n_users), dtype=np.bool_)
        _simulate(
            self._kt,
            self._packet_bits,
            uav,
            users,
            load,
            np.ascontiguousarray(queues.backlog_pkts, dtype=float),
            np.ascontiguousarray(queues.codel_count, dtype=float),
            np.ascontiguousarray(queues.at_cap_s, dtype=float),
            log_gains,
            path_loss,
            float(step_s),
            out,
            connected,
        )
        throughput, delay, plr, backlog_out, codel_out, at_cap_out, snr = out
        return StepResult(
            throughput_bps=throughput,
            delay_s=delay,
            plr=plr,
            state=QueueState(backlog_out, codel_out, at_cap_out),
            snr_db=snr,
            connected=connected,
        )

    def _urban_channel(
        self,
        uav: np.ndarray,
        users: np.ndarray,
        rng: np.random.Generator | None,
        batch: int,
        n_users: int,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Path loss (N, U) and fading gains (N, U, draws) in an urban environment: the mean
        path loss in expected mode (no draws); a drawn LoS state and its fading otherwise."""
        ground = np.hypot(uav[:, None, 0] - users[:, :, 0], uav[:, None, 1] - users[:, :, 1])
        height = np.broadcast_to(
            np.maximum(uav[:, 2:3] - self.area.user_height_m, 0.0), (batch, n_users)
        )
        loss, gains = self.link_channel(ground, height, rng)
        return np.ascontiguousarray(loss), _NO_DRAWS if gains is None else gains

    def _site_channel(
        self, uav: np.ndarray, users: np.ndarray, rng: np.random.Generator | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Path loss (N, U) and fading gains (N, U, draws) on the site: ``users`` (1, U, 2),
        every position's, or (N, U, 2), one row each. No path: :data:`NO_LINK_LOSS_DB`."""
        assert self._site is not None
        shared = users.shape[0] == 1
        loss, gains = site_link_channel(
            self._site,
            uav,
            users[0] if shared else users,
            self.config.radio.rician_k_db,
            rng,
            RATE_DRAWS_PER_STEP,
        )
        np.minimum(loss, NO_LINK_LOSS_DB, out=loss)
        return np.ascontiguousarray(loss), _NO_DRAWS if gains is None else gains

    def link_channel_at(
        self, uav_xyz_m: np.ndarray, users_xy_m: np.ndarray, rng: np.random.Generator | None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The channel of links given by their two ends, in every environment: the AP at
        ``uav_xyz_m`` (S + (3,)) and the user at ``users_xy_m`` (S + (2,)), one link per index
        of S. Returns path loss (dB, S) and fading power gains (S + (draws,)), None in expected
        mode (``rng`` None). In the open and the towns, :meth:`link_channel` of the links'
        ground distance and height (the same numbers and draws); on a site, the site's loss
        at the exact AP position (no path: :data:`~sim.channel.NO_LINK_LOSS_DB`) and fading by
        line of sight (:func:`sim.channel.site_link_channel`, its draw order). How the fleet
        model (:mod:`sim.fleet`) builds links whose users hear different APs."""
        uav = np.asarray(uav_xyz_m, dtype=float)
        users = np.asarray(users_xy_m, dtype=float)
        shape = users.shape[:-1]
        if self._site is None:
            ground = np.hypot(uav[..., 0] - users[..., 0], uav[..., 1] - users[..., 1])
            height = np.maximum(uav[..., 2] - self.area.user_height_m, 0.0)
            return self.link_channel(ground, height, rng)
        loss, gains = site_link_channel(
            self._site,
            uav.reshape(-1, 3),
            users.reshape(-1, 1, 2),
            self.config.radio.rician_k_db,
            rng,
            RATE_DRAWS_PER_STEP,
        )
        loss = np.minimum(loss, NO_LINK_LOSS_DB).reshape(shape)
        return loss, None if gains is None else gains.reshape(*shape, RATE_DRAWS_PER_STEP)

    def link_channel(
        self, ground_m: np.ndarray, height_m: np.ndarray, rng: np.random.Generator | None
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The channel of links given by their ground distance and the AP's height above the
        user (arrays of one shape S): path loss (dB, S) and fading power gains (S + (draws,)),
        None in expected mode (``rng`` None). Free space with Rician fading in the open; in a
        town the mean path loss in expected mode, otherwise a line-of-sight state drawn per
        link (:func:`sim.channel.draw_link_channel`) and its excess loss and fading. A site's
        links depend on where both ends are, not on these two numbers: InputError naming
        ``environment`` (use :meth:`link_channel_at`)."""
        if self._site is not None:
            raise InputError(
                f"environment: {self.area.environment!r} is a site: its links need the AP's "
                f"and the user's positions (NetworkModel.link_channel_at)"
            )
        radio = self.config.radio
        environment = self.area.environment
        if environment == "open" or rng is None:
            loss = mean_path_loss_db(environment, ground_m, height_m, radio.frequency_hz)
            if rng is None:
                return loss, None
            draws = (*np.shape(ground_m), RATE_DRAWS_PER_STEP)
            return loss, rician_power_gain(rng, radio.rician_k_db, draws)
        p_los = los_probability(environment, elevation_deg(ground_m, height_m))
        los, gains = draw_link_channel(rng, p_los, radio.rician_k_db, RATE_DRAWS_PER_STEP)
        assert self._excess_db is not None
        eta_los, eta_nlos = self._excess_db
        free_space = friis_path_loss_db(np.hypot(ground_m, height_m), radio.frequency_hz)
        return free_space + np.where(los, eta_los, eta_nlos), gains

    def step_links(
        self,
        path_loss_db: np.ndarray,
        gains: np.ndarray | None,
        users_xy_m: np.ndarray,
        load_bps: np.ndarray,
        state: QueueState,
        step_s: float = 1.0,
    ) -> StepResult:
        """One step of N cells whose links are given rather than computed from a UAV position:
        ``path_loss_db`` (N, U) and fading ``gains`` (N, U, draws) or None (expected mode), as
        :meth:`link_channel` returns them, plus any loss of the caller's own (co-channel
        interference, for instance) already added. ``users_xy_m`` (N, U, 2), ``load_bps`` and
        ``state`` (N, U). Inputs are not checked here (the caller has); the result is as
        :meth:`step_many`'s. How the fleet model steps cells whose users hear different APs.
        """
        loss = np.ascontiguousarray(path_loss_db, dtype=float)
        return self._kernel(
            np.zeros((loss.shape[0], 3)),  # unused: the kernel takes the path loss given
            np.ascontiguousarray(users_xy_m, dtype=float),
            np.ascontiguousarray(load_bps, dtype=float),
            state,
            _NO_DRAWS if gains is None else np.log10(gains),
            loss,
            step_s,
        )

    @staticmethod
    def values_ok(uav: np.ndarray, users: np.ndarray, load: np.ndarray) -> bool:
        """The model's one-pass input check: every value finite, loads non-negative, nothing
        too large to simulate (False: the caller names the bad argument)."""
        return _values_ok(uav, users, load)


# No fading draws: expected mode (the kernel tells the modes apart by the last axis).
_NO_DRAWS = np.empty((0, 0, 0))
# No path loss given: the kernel computes free-space loss itself (the open environment).
_FREE_SPACE = np.empty((0, 0))


def _check_step_shapes(uav: np.ndarray, users: np.ndarray, load: np.ndarray) -> tuple[int, int]:
    """(B, U) for :meth:`NetworkModel.step`'s arrays, or InputError naming the bad one."""
    if uav.ndim != 2 or uav.shape[1] != 3:
        raise InputError(f"uav_xyz_m: must be (B, 3) positions, got shape {uav.shape}")
    flat_pairs = users.ndim == 1 and users.size % 2 == 0
    if not (flat_pairs or (users.ndim == 2 and users.shape[1] == 2)):
        raise InputError(f"users_xy_m: must be (U, 2) positions, got shape {users.shape}")
    n_users = users.size // 2
    if load.size != n_users:
        raise InputError(
            f"load_bps: must hold one load per user ({n_users}), got shape {load.shape}"
        )
    return uav.shape[0], n_users


def _check_many_shapes(uav: np.ndarray, users: np.ndarray, load: np.ndarray) -> tuple[int, int]:
    """(E, U) for :meth:`NetworkModel.step_many`'s arrays, or InputError naming the bad one."""
    if uav.ndim != 2 or uav.shape[1] != 3:
        raise InputError(f"uav_xyz_m: must be (E, 3) positions, got shape {uav.shape}")
    n_envs = uav.shape[0]
    if users.ndim != 3 or users.shape[0] != n_envs or users.shape[2] != 2:
        raise InputError(
            f"users_xy_m: must be ({n_envs}, U, 2) positions for {n_envs} environments, "
            f"got shape {users.shape}"
        )
    n_users = users.shape[1]
    if load.shape != (n_envs, n_users):
        raise InputError(
            f"load_bps: must be ({n_envs}, {n_users}), one load per user, got shape {load.shape}"
        )
    return n_envs, n_users


def _check_step_inputs(
    uav: np.ndarray, users: np.ndarray, load: np.ndarray, step_s: float
) -> tuple[int, int]:
    """(B, U) for :meth:`NetworkModel.step`'s arguments, or InputError naming the bad one."""
    shape = _check_step_shapes(uav, users, load)
    _check_step_values(uav, users, load, step_s)
    return shape


def _check_step_values(uav: np.ndarray, users: np.ndarray, load: np.ndarray, step_s: float) -> None:
    """InputError naming the first non-finite or negative argument, or a bad ``step_s``.

    The reference check; :func:`_values_ok` spares the common case its numpy calls.
    """
    # One sum is finite exactly when every value is (or an absurd 1e308 overflowed it).
    if not math.isfinite(float(uav.sum()) + float(users.sum()) + float(load.sum())):
        for name, values in (("uav_xyz_m", uav), ("users_xy_m", users), ("load_bps", load)):
            if not np.isfinite(values).all():
                raise InputError(f"{name}: must be finite")
        raise InputError("uav_xyz_m, users_xy_m, load_bps: values too large to simulate")
    if load.size and load.min() < 0:
        raise InputError("load_bps: loads must be non-negative")
    if not (math.isfinite(step_s) and step_s > 0):
        raise InputError(f"step_s: must be a positive number, got {step_s!r}")


@njit(cache=True, nogil=True)
def _values_ok(uav: np.ndarray, users: np.ndarray, load: np.ndarray) -> bool:
    """True when :func:`_check_step_values` surely passes these arrays: every value finite and
    far from overflowing a sum, every load non-negative. False sends the caller to it."""
    total = 0.0
    for value in uav.flat:
        total += abs(value)
    for value in users.flat:
        total += abs(value)
    for value in load.flat:
        if value < 0.0:
            return False
        total += value
    return total < 1e300  # False for any NaN or infinity too


@njit(cache=True, nogil=True)
def _simulate(
    kt: tuple,
    packet_bits: float,
    uav: np.ndarray,
    users: np.ndarray,
    load_bps: np.ndarray,
    backlog_in: np.ndarray,
    codel_in: np.ndarray,
    at_cap_in: np.ndarray,
    log_gains: np.ndarray,
    path_loss_db: np.ndarray,
    step_s: float,
    out: np.ndarray,
    connected_out: np.ndarray,
) -> None:
    """One step for each row b of ``uav`` (N, 3), into ``out`` (7, N, U) and ``connected_out``.

    ``users`` (S, U, 2) and ``load_bps`` (S, U) hold one scenario shared by every row (S = 1,
    :meth:`NetworkModel.step`) or one per row (S = N, :meth:`NetworkModel.step_many`).
    ``log_gains`` (N, U, draws) are log10 of the fading power gains, or (0, 0, 0) in expected
    mode. ``path_loss_db`` (N, U) is each link's path loss (urban environments), or (0, 0): the
    kernel computes free-space loss. ``out`` rows: throughput (bit/s), delay (s), loss ratio,
    backlog, CoDel count, time at the cap, SNR.
    """
    k = _Constants(*kt)
    batch, n_users = uav.shape[0], users.shape[1]
    shared = users.shape[0] == 1
    n_draws = log_gains.shape[2]
    given_loss = path_loss_db.shape[0] > 0
    gains_db = np.empty(n_draws)
    arrival_pps = np.empty(n_users)
    phy_overhead = np.empty(n_users)
    mpdu = np.empty(n_users)
    max_mpdus = np.empty(n_users)
    success = np.empty(n_users)
    attempts_per_packet = np.empty(n_users)
    residual = np.empty(n_users)
    demand = np.empty(n_users)
    attempt_rate = np.empty(n_users)
    overhead = np.empty(n_users)
    mpdu_air = np.empty(n_users)
    stalled = np.zeros(n_users)
    own_share = np.zeros(n_users)
    stall_next = np.zeros(n_users)
    stall_wait = np.zeros(n_users)
    for b in range(batch):
        s = 0 if shared else b
        # Channel and link of every user.
        for u in range(n_users):
            arrival_pps[u] = load_bps[s, u] / packet_bits
            if given_loss:
                rssi = k.tx_power_dbm - path_loss_db[b, u]
            else:
                dx = uav[b, 0] - users[s, u, 0]
                dy = uav[b, 1] - users[s, u, 1]
                dz = uav[b, 2] - k.user_height_m
                distance = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1.0)
                rssi = k.tx_power_dbm - k.path_loss_1m_db - 20.0 * np.log10(distance)
            snr = rssi - k.noise_dbm
            out[6, b, u] = snr
            connected = rssi >= k.min_rssi_dbm
            connected_out[b, u] = connected
            if n_draws == 0:
                link = expected_link(k.expected, snr)
            else:
                for d in range(n_draws):
                    gains_db[d] = 10.0 * log_gains[b, u, d]
                link = sampled_link(
                    k.expected, k.per_mid_db, k.per_slope, k.threshold_db, snr, gains_db
                )
            phy_overhead[u], mpdu[u], max_mpdus[u], success[u] = link
            residual[u] = (1.0 - success[u]) ** k.transmissions
            # Transmissions per packet: truncated geometric, at most the retry limit + 1.
            attempts_per_packet[u] = (
                (1.0 - residual[u]) / success[u] if success[u] > 1e-9 else k.transmissions
            )
            stalled[u] = 0.0
            stall_wait[u] = 0.0

        # Airtime sharing, in passes: the contenders and the backoff stalls of a pass come from
        # the one before (stalled arrivals expire unsent and free their airtime).
        n_contenders = 0.0
        for u in range(n_users):
            has_traffic = arrival_pps[u] + backlog_in[b, u] > 0.0
            n_contenders += 1.0 if has_traffic and connected_out[b, u] else 0.0
        nu = np.inf
        for sharing_pass in range(k.sharing_passes):
            for u in range(n_users):
                demand[u] = (
                    arrival_pps[u] * (1.0 - stalled[u]) + backlog_in[b, u] / step_s
                    if connected_out[b, u]
                    else 0.0
                )
                attempt_rate[u] = demand[u] * attempts_per_packet[u]
            backoff_s, inflation = contention_overhead(
                n_contenders, k.collision_table, k.slot_s, k.contention_cw_min
            )
            for u in range(n_users):
                overhead[u] = k.aifs_s + backoff_s + inflation * phy_overhead[u]
                mpdu_air[u] = inflation * mpdu[u]
            nu = fair_txop_rate(attempt_rate, overhead, mpdu_air, max_mpdus)
            n_contenders = effective_contenders(attempt_rate, nu)
            if k.backoff_stalls and sharing_pass < k.sharing_passes - 1:
                # Stalls free airtime, which shortens stalls: damped, or the estimate
                # oscillates between a saturated and an idle cell. The last pass only shares.
                _stall_fractions(
                    k, attempt_rate, overhead, mpdu_air, max_mpdus, success, nu,
                    n_contenders, inflation, stall_next, stall_wait, own_share,
                )  # fmt: skip
                change = 0.0
                for u in range(n_users):
                    change = max(change, abs(stall_next[u] - stalled[u]))
                    stalled[u] += STALL_DAMPING * (stall_next[u] - stalled[u])
                if change < STALL_TOLERANCE:
                    break  # converged (or nobody stalls): this pass's sharing stands

        # Queues, delivery, delay and loss of every user.
        for u in range(n_users):
            arrival = arrival_pps[u] * (1.0 - stalled[u])
            served_attempts = min(attempt_rate[u], nu * max_mpdus[u])
            txop_rate = max(min(attempt_rate[u], nu), 1e-12)
            service = min(served_attempts / attempts_per_packet[u], demand[u])
            dropped, queue_wait_s, backlog, count, at_cap = advance_queue(
                backlog_in[b, u],
                codel_in[b, u],
                at_cap_in[b, u],
                arrival,
                service,
                step_s,
                k.mac_queue_packets,
                k.mac_max_delay_s,
                k.qdisc_limit_packets if connected_out[b, u] else 0.0,
                k.codel_target_s,
                k.codel_interval_s,
            )
            out[3, b, u] = backlog
            out[4, b, u] = count
            out[5, b, u] = at_cap
            delivered = service * (1.0 - residual[u])
            out[0, b, u] = delivered * packet_bits
            arrived = arrival_pps[u] * step_s
            out[2, b, u] = 0.0
            if arrived > 0.0:
                lost = dropped + service * residual[u] * step_s + arrived * stalled[u]
                out[2, b, u] = min(max(lost / arrived, 0.0), 1.0)
            if arrival_pps[u] <= 0.0:
                out[1, b, u] = 0.0
            elif delivered <= 0.0:
                out[1, b, u] = k.unserved_delay_s
            else:
                # Waiting in the queues (sim.queues), for the next TXOP while the A-MPDU
                # fills, the TXOP itself, and one TXOP interval per retransmission.
                # A stalled station's packets wait for the end of its backoff stall instead.
                mpdus_per_txop = max(served_attempts / txop_rate, 1.0)
                waiting = (mpdus_per_txop - 1.0) / (2.0 * service) + (
                    attempts_per_packet[u] - 1.0
                ) / txop_rate
                out[1, b, u] = (
                    queue_wait_s
                    + max(waiting, stall_wait[u])  # the last stall pass's: not damped
                    + overhead[u]
                    + mpdus_per_txop * mpdu_air[u]
                )


@njit(cache=True, nogil=True)
def _stall_fractions(
    k: _Constants,
    attempt_rate: np.ndarray,
    overhead: np.ndarray,
    mpdu_air: np.ndarray,
    max_mpdus: np.ndarray,
    success: np.ndarray,
    nu: float,
    n_contenders: float,
    inflation: float,
    stalled: np.ndarray,
    stall_wait: np.ndarray,
    own_share: np.ndarray,
) -> None:
    """Fill ``stalled`` and ``stall_wait`` (sim.stalls) for the sharing solved at ``nu``.

    The cell's idle slots per second: when the channel is saturated, a backlogged station
    counts down every idle slot between its attempts, so the idle slots per second are its
    attempts per second (``nu`` TXOPs, inflated by collisions) times the mean backoff it draws
    per attempt; otherwise Bianchi's idle slots before each transmission plus the airtime
    nobody uses. A station's slot lasts the time it does not spend on air itself divided by
    those idle slots (alone in the cell, a slot is a slot). An attempt fails when it collides
    or its PPDU is lost (the subframe error stands in for the whole PPDU: a fade takes all of
    it). Every station with traffic can
    stall, saturated or not: a saturated one's queue ages through the stall as well.
    """
    n_users = attempt_rate.size
    collision_prob = 1.0 - 1.0 / inflation
    transmissions = 0.0
    busy = 0.0
    for u in range(n_users):
        r = attempt_rate[u]
        if r <= 0.0:
            own_share[u] = 0.0
            continue
        txops = min(r, nu)
        transmissions += txops * inflation
        own_share[u] = txops * overhead[u] + min(r, nu * max_mpdus[u]) * mpdu_air[u]
        busy += own_share[u]
    if np.isfinite(nu):
        # A backlogged station counts down every idle slot of the cell between its attempts.
        idle_slots_per_s = nu * inflation * mean_backoff_slots(collision_prob, k.cw_min, k.cw_max)
    else:
        idle_per_tx = idle_slots_per_transmission(n_contenders, collision_prob, k.contention_cw_min)
        idle_slots_per_s = transmissions * idle_per_tx + max(1.0 - busy, 0.0) / k.slot_s
    idle_slots_per_s = max(idle_slots_per_s, 1e-9)
    for u in range(n_users):
        r = attempt_rate[u]
        if r <= 0.0:
            stalled[u] = 0.0
            stall_wait[u] = 0.0
            continue
        failure = 1.0 - (1.0 - collision_prob) * success[u]
        # A station's countdown pauses for the others' airtime, not for its own.
        slot_time_s = max((1.0 - min(own_share[u], 1.0)) / idle_slots_per_s, k.slot_s)
        stalled[u], stall_wait[u] = stall_lookup(k.stall_table, failure, slot_time_s)
