"""The ns-3 backend: simulate a case (UAV position, users, loads) in ns-3 3.44 as the paper did.

ns-3 is optional (``pip install 'tupa[ns3]'``: the ``ns3`` wheel from PyPI, Python bindings
through cppyy, no C++ build). Nothing here imports it: the cases run in a child process
(:mod:`sim.ns3_worker`, ``python -m sim.ns3_worker``) that imports ns-3 once (~15 s), compiles
the scenario (a few seconds) and then simulates one case per request (~0.1–0.5 s of set-up
each). The parent enforces a time limit per case; a worker that crashes (a segfault inside ns-3)
or hangs is killed, the case is reported as failed by id (:class:`Ns3CaseError`), and the next
case gets a fresh worker. The caller never goes down with it.

Protocol per case, the one :mod:`sim.evaluate` uses for the fast model:

1. ``association_s`` (1 s): the stations associate with the AP; no traffic yet (ns-3 needs it,
   the fast model assumes associated stations).
2. ``warmup_s`` (0.5 s): every user starts its UDP CBR flow (uniform 0–5 ms start jitter).
3. ``measure_s`` (2 s): per-user throughput (payload bits delivered to the AP / window), mean
   one-way delay of the packets received in the window (FlowMonitor), and loss = packets
   dropped anywhere in the window (queue disc, MAC queue, MAC lifetime and Block Ack window,
   traffic-control layer, ARP, IP) / packets sent in the window. A station that never
   associated (out of range) loses all it sends, as in the fast model: its packets end in ARP's
   pending queue. Packets still queued at the end are neither delivered nor lost, as in the fast
   model's ``plr``.

Channel: in the ``open`` environment ns-3 computes Friis free-space loss itself (the paper's
channel, unchanged since the calibration). In an urban one (``Ns3Settings.environment``) the
parent computes each user's loss to the UAV with the fast model's own function,
:func:`sim.channel.mean_path_loss_db` (free space plus the environment's LoS-probability-weighted
excess loss, at the user's ground distance and the UAV's height above the user), and the worker
sets it per pair in ns-3's ``MatrixPropagationLossModel``, followed by the same Nakagami fading
(m = 10.73, Rician K = 13 dB) as in ``open``: the channel of the fast model's expected mode, so
that the comparison is about MAC behaviour, not two channels. Between users (who hear each
other's transmissions for carrier sense and collisions) the loss stays free space, as in
``open``: the fast model has no hidden stations, and urban ground-to-ground blockage would add
them to ns-3 alone. The LoS state itself is not drawn in ns-3 (nor in the expected mode): what
the comparison checks is the MAC on a given mean channel, not the Al-Hourani model.

On a site (``environment`` ``site:NAME`` or ``site:PATH``) the per-user loss is the
site's ray-traced mean loss at the UAV's exact position, :func:`sim.channel.site_link_channel`
in expected mode (the numbers :class:`sim.network.NetworkModel` uses there), set per pair the
same way and followed by the same Nakagami fading (the fast model's Rician/Rayleigh split by
line of sight is a stochastic-mode matter; the expected mode, and so ns-3, takes the mean loss
only). A user with no path at all gets :data:`NO_PATH_LOSS_DB` (JSON has no ``inf``): received
at about −980 dBm, under every threshold, so it never associates and loses all it sends — the
fast model's "no path = out of coverage". User to user stays free space, as in the towns: the
fast model has no hidden stations, and blocking ground-to-ground links by the site's buildings
would add them to ns-3 alone.

``interval_s`` splits the window into equal intervals (e.g. 1 s over a 10 s window, to follow
how FqCoDel delays grow). A user that sends but receives nothing in a window gets the fast
model's ``unserved_delay_s`` (1 s) as its delay.

K access points: :class:`FleetCase` holds K UAV positions (1..8), the users and
each user's AP (given: ns-3 is not asked to pick one, so that it and
:class:`sim.fleet.FleetModel` compare the same cells), and the channel mode: ``distinct`` (AP k
on channel 36 + 4k, each on its own ns-3 channel object, so cells are independent) or
``shared`` (all on channel 36, one channel object: cells contend and interfere as ns-3's PHY
and MAC make them). :meth:`Ns3Runner.run_fleet` simulates it with the same protocol and
counters; K = 1 gives :meth:`Ns3Runner.run`'s numbers exactly (same nodes, objects and random
streams in the same order; tested). In an urban environment or on a site each AP gets its users'
mean path loss as above, and AP to AP is free space (UAVs see each other in the air).

Randomness: ns-3's ``RngSeedManager`` seed is ``seed + 1`` (ns-3 wants >= 1) and its run number
``index + 1`` for the case at position ``index`` of a file, and every random stream is pinned
with ``AssignStreams``: the same case, seed and index give the same result.
"""

from __future__ import annotations

import contextlib
import importlib.util
import itertools
import json
import math
import os
import select
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sim.atomic import atomic_write_json
from sim.channel import (
    NO_LINK_LOSS_DB,
    environment_site,
    friis_path_loss_db,
    mean_path_loss_db,
    site_link_channel,
)
from sim.config import (
    AreaConfig,
    QueueConfig,
    Queueing,
    RadioConfig,
    TrafficConfig,
    UtilityConfig,
    environment_problem,
)
from sim.errors import InputError
from sim.evaluate import RESULTS_FORMAT, CaseMetrics
from sim.files import cases_document, load_cases
from sim.fleet import CHANNEL_MODES, CHANNELS_5GHZ, MAX_UAVS
from sim.scenarios import Case
from sim.utility import network_utility

INSTALL_HINT = "--backend ns3: ns-3 is not installed; pip install 'tupa[ns3]'"
NO_PATH_LOSS_DB = NO_LINK_LOSS_DB
"""The loss ns-3 is given for a site's link with no path (``+inf`` in the lookup; JSON has no
inf): the fast model's own stand-in, :data:`sim.channel.NO_LINK_LOSS_DB` (1000 dB: received at
about −980 dBm, far under ns-3's −82 dBm CCA and −90 dBm preamble thresholds: out of
coverage)."""

# Counters (cumulative in the worker) whose window difference is a packet lost.
DROP_FIELDS: tuple[str, ...] = (
    "drop_qdisc",
    "drop_mac_failed_enqueue",
    "drop_mac_expired",
    "drop_mac_retry_limit",
    "drop_mac_old_packet",
    "drop_mac_tx",
    "drop_arp",
    "drop_tc",
    "drop_ip",
)
# Counters reported as they are at the end of the window, not as differences.
_LEVEL_FIELDS = ("backlog_qdisc_pkts", "backlog_mac_pkts", "max_tx_gap_s", "ampdu_max_mpdus")


def ns3_available() -> bool:
    """Whether the ``ns3`` package is installed (checked without importing it: that takes 15 s)."""
    return importlib.util.find_spec("ns3") is not None


def require_ns3() -> None:
    """Raise :class:`InputError` (the CLI exits 2) with the install hint if ns-3 is missing."""
    if not ns3_available():
        raise InputError(INSTALL_HINT)


def ns3_version() -> str | None:
    """The installed ``ns3`` distribution's version (e.g. ``3.44.post0``), None if absent."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ns3")
    except PackageNotFoundError:
        return None


def nakagami_m_for_rician(k_db: float) -> float:
    """Nakagami shape m with the same amount of fading as Rician K: m = (K + 1)² / (2K + 1).

    K = 13 dB gives m = 10.73.
    """
    k = 10.0 ** (k_db / 10.0)
    return (k + 1.0) ** 2 / (2.0 * k + 1.0)


@dataclass(frozen=True)
class Ns3Settings:
    """How a case is simulated in ns-3 (defaults: the protocol of ``tupa sim evaluate``).

    ``environment``: the channel (module doc): ``open`` (ns-3's Friis), an urban class of
    :data:`sim.config.ENVIRONMENTS` (per-user loss from :func:`sim.channel.mean_path_loss_db`)
    or a site, ``site:NAME`` / ``site:PATH`` (per-user loss from the site, loaded and checked
    here: InputError naming ``environment`` for an unknown, missing or broken one).
    """

    queueing: Queueing = "fq-codel"
    warmup_s: float = 0.5
    measure_s: float = 2.0
    interval_s: float | None = None  # None: one interval, the whole measurement window
    association_s: float = 1.0
    seed: int = 0
    radio: RadioConfig = field(default_factory=RadioConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    user_height_m: float = AreaConfig().user_height_m
    unserved_delay_s: float = QueueConfig().unserved_delay_s
    environment: str = "open"

    def __post_init__(self) -> None:
        problem = environment_problem(self.environment, on_disk=True)
        if problem is not None:
            raise InputError(f"environment: {problem}")
        environment_site(self.environment)  # a site: there and sound ("environment: ...")
        if self.queueing not in ("fq-codel", "mac-only"):
            raise InputError(f"queueing: must be fq-codel or mac-only, got {self.queueing!r}")
        if not (math.isfinite(self.warmup_s) and self.warmup_s >= 0):
            raise InputError(f"warmup_s: must be >= 0, got {self.warmup_s}")
        if not (math.isfinite(self.measure_s) and self.measure_s > 0):
            raise InputError(f"measure_s: must be > 0, got {self.measure_s}")
        if self.interval_s is not None and not (
            math.isfinite(self.interval_s) and 0 < self.interval_s <= self.measure_s
        ):
            raise InputError(f"interval_s: must be in (0, measure_s], got {self.interval_s}")
        if not (math.isfinite(self.association_s) and self.association_s >= 0):
            raise InputError(f"association_s: must be >= 0, got {self.association_s}")
        if self.seed < 0:
            raise InputError(f"seed: must be >= 0, got {self.seed}")

    @property
    def simulated_s(self) -> float:
        """Simulated seconds per case (association + warm-up + measurement)."""
        return self.association_s + self.warmup_s + self.measure_s

    def snapshot_times_s(self) -> list[float]:
        """Times at which the worker copies its counters: window start, interval ends."""
        start = self.association_s + self.warmup_s
        n = 1 if self.interval_s is None else max(1, round(self.measure_s / self.interval_s))
        return [start + self.measure_s * k / n for k in range(n + 1)]

    def to_dict(self) -> dict[str, Any]:
        return {
            "environment": self.environment,
            "queueing": self.queueing,
            "warmup_s": self.warmup_s,
            "measure_s": self.measure_s,
            "interval_s": self.interval_s,
            "association_s": self.association_s,
            "seed": self.seed,
            "nakagami_m": nakagami_m_for_rician(self.radio.rician_k_db),
        }


class Ns3CaseError(RuntimeError):
    """One case could not be simulated: the worker crashed, hung or raised."""

    def __init__(self, case_id: str, reason: str) -> None:
        super().__init__(f"case {case_id}: ns-3 failed: {reason}")
        self.case_id = case_id
        self.reason = reason


@dataclass(frozen=True)
class Ns3CaseResult:
    """One case simulated in ns-3: the metrics over the window and what ns-3 saw.

    ``detail`` holds per-user counters over the window (arrays (U,), keys as in
    :data:`sim.ns3_worker.FIELDS`: drops by cause, PPDUs, MCS, backoffs, AP PHY drops ...);
    ``intervals`` the metrics per interval when ``interval_s`` was set (else one entry, the
    window). ``wall_s`` is the worker's time for the case, ns-3 set-up included.
    """

    metrics: CaseMetrics
    intervals: list[CaseMetrics]
    detail: dict[str, np.ndarray]
    association_s: np.ndarray
    wall_s: float

    def to_dict(self, with_detail: bool = True) -> dict[str, Any]:
        """The ``tupa sim evaluate`` entry of this case, plus ns-3 extras."""
        out = self.metrics.to_dict()
        if with_detail:
            for u, user in enumerate(out["users"]):
                user["ns3"] = {
                    name: _plain(values[u]) for name, values in self.detail.items() if values[u]
                }
        out["wall_s"] = round(self.wall_s, 4)
        out["association_s"] = [round(float(t), 6) for t in self.association_s]
        if len(self.intervals) > 1:
            out["intervals"] = [m.to_dict() for m in self.intervals]
        return out


def _plain(value: float) -> float | int:
    return int(value) if float(value).is_integer() else float(value)


def _metrics(
    case: Case | FleetCase,
    start: dict[str, Any],
    end: dict[str, Any],
    settings: Ns3Settings,
    utility: UtilityConfig,
) -> tuple[CaseMetrics, dict[str, np.ndarray]]:
    """Metrics over the window between two worker snapshots."""
    window_s = end["time_s"] - start["time_s"]
    names = end["users"][0].keys()
    detail = {
        name: np.array(
            [
                e[name] if name in _LEVEL_FIELDS else e[name] - s[name]
                for s, e in zip(start["users"], end["users"], strict=True)
            ]
        )
        for name in names
    }
    rx = detail["rx_pkts"]
    tx = detail["tx_pkts"]
    lost = sum(detail[name] for name in DROP_FIELDS)
    throughput_bps = rx * settings.traffic.packet_bytes * 8.0 / window_s
    with np.errstate(invalid="ignore", divide="ignore"):
        delay_s = np.where(rx > 0, detail["delay_sum_s"] / np.maximum(rx, 1), 0.0)
        plr = np.where(tx > 0, np.clip(lost / np.maximum(tx, 1), 0.0, 1.0), 0.0)
    sending = case.load_bps > 0
    delay_s = np.where(sending & (rx <= 0), settings.unserved_delay_s, delay_s)
    delay_s = np.where(sending, delay_s, 0.0)
    value = network_utility(throughput_bps, delay_s, plr, case.load_bps, utility)
    return CaseMetrics(case.id, float(value), throughput_bps, delay_s, plr), detail


def link_losses_db(case: Case, settings: Ns3Settings) -> tuple[np.ndarray, np.ndarray]:
    """The losses the worker sets in an urban environment or on a site: each user's mean path
    loss to the UAV (U,), exactly what the fast model's expected mode uses — in a town
    :func:`sim.channel.mean_path_loss_db` at the ground distance and the UAV's height above the
    user (floored at 0 as the model does), on a site the site's loss at the UAV's exact
    position (:func:`sim.channel.site_link_channel`, no path: :data:`NO_PATH_LOSS_DB`) — and
    the free-space loss between users (U, U)."""
    users = case.users_xy_m
    frequency_hz = settings.radio.frequency_hz
    site = environment_site(settings.environment)
    if site is not None:
        loss, _ = site_link_channel(
            site, case.uav_xyz_m[None, :], users, settings.radio.rician_k_db, None, 0
        )
        to_uav = np.minimum(loss[0], NO_PATH_LOSS_DB)
    else:
        ground_m = np.hypot(users[:, 0] - case.uav_xyz_m[0], users[:, 1] - case.uav_xyz_m[1])
        height_m = max(float(case.uav_xyz_m[2]) - settings.user_height_m, 0.0)
        to_uav = mean_path_loss_db(settings.environment, ground_m, height_m, frequency_hz)
    between = np.hypot(users[:, None, 0] - users[None, :, 0], users[:, None, 1] - users[None, :, 1])
    return np.asarray(to_uav, dtype=float), friis_path_loss_db(between, frequency_hz)


def _request(case: Case, settings: Ns3Settings, index: int) -> dict[str, Any]:
    doc = cases_document(AreaConfig(), [case])["cases"][0]
    losses: dict[str, list[float]] = {}
    if settings.environment != "open":
        to_uav, between = link_losses_db(case, settings)
        losses = {"ap_loss_db": to_uav.tolist(), "sta_loss_db": between.ravel().tolist()}
    return {
        **losses,
        "case": doc,
        "queueing": settings.queueing,
        "snapshot_times_s": settings.snapshot_times_s(),
        "user_height_m": settings.user_height_m,
        "app_start_s": settings.association_s,
        "seed": settings.seed + 1,
        "run": index + 1,
        "packet_bytes": settings.traffic.packet_bytes,
        "nakagami_m": nakagami_m_for_rician(settings.radio.rician_k_db),
    }


@dataclass(frozen=True)
class FleetCase:
    """A case with K access points: UAV k at ``uav_xyz_m[k]`` (K, 3) carries AP k;
    user i, at ``users_xy_m[i]`` offering ``load_bps[i]``, is a station of AP
    ``association[i]`` (0..K−1: given, not decided in ns-3, so that ns-3 and the fast model
    compare the same cells; a user that hears no AP is given one all the same and, out of
    range in ns-3 too, never associates). ``channel_mode`` as in :class:`sim.fleet.FleetConfig`:
    ``distinct`` puts AP k on 20 MHz channel 36 + 4k (its own channel object in ns-3: no
    energy crosses between cells), ``shared`` puts every AP on channel 36 (one channel: cells
    contend and interfere as the PHY and MAC decide). Bad values raise :class:`InputError`
    naming the field. APs closer than the fleet's separation, even at one place, are accepted
    (ns-3 simulates them; separation is the caller's constraint, as for ``FleetModel``).
    """

    id: str
    uav_xyz_m: np.ndarray  # (K, 3)
    users_xy_m: np.ndarray  # (U, 2)
    load_bps: np.ndarray  # (U,)
    association: np.ndarray  # (U,) AP index per user
    channel_mode: str = "distinct"

    def __post_init__(self) -> None:
        uav = np.array(self.uav_xyz_m, dtype=np.float64)
        if uav.ndim != 2 or uav.shape[1] != 3:
            raise InputError(f"uav_xyz_m: must be (K, 3) UAV positions, got shape {uav.shape}")
        if not 1 <= uav.shape[0] <= MAX_UAVS:
            raise InputError(
                f"uav_xyz_m: must hold 1..{MAX_UAVS} UAV positions (K), got {uav.shape[0]}"
            )
        if not np.all(np.isfinite(uav)):
            raise InputError("uav_xyz_m: must be finite")
        try:
            scenario = Case(self.id, uav[0], self.users_xy_m, self.load_bps)  # checks users
        except ValueError as exc:  # names the field (users_xy_m or load_bps)
            raise InputError(str(exc)) from None
        raw = np.asarray(self.association)
        if raw.shape != (scenario.n_users,):
            raise InputError(
                f"association: must hold one AP index per user ({scenario.n_users}), "
                f"got shape {raw.shape}"
            )
        if raw.dtype.kind not in "iu" and not (
            raw.dtype.kind == "f" and np.all(np.isfinite(raw)) and np.all(raw == np.round(raw))
        ):
            raise InputError(f"association: must be integer AP indices, got {raw.tolist()}")
        assoc = raw.astype(np.int64)
        bad = np.flatnonzero((assoc < 0) | (assoc >= uav.shape[0]))
        if bad.size:
            raise InputError(
                f"association: user {int(bad[0])}'s AP index {int(assoc[bad[0]])} is outside "
                f"0..{uav.shape[0] - 1}"
            )
        if self.channel_mode not in CHANNEL_MODES:
            raise InputError(
                f"channel_mode: must be one of {', '.join(CHANNEL_MODES)}, "
                f"got {self.channel_mode!r}"
            )
        for array in (uav, assoc):
            array.setflags(write=False)
        object.__setattr__(self, "uav_xyz_m", uav)
        object.__setattr__(self, "users_xy_m", scenario.users_xy_m)
        object.__setattr__(self, "load_bps", scenario.load_bps)
        object.__setattr__(self, "association", assoc)

    @property
    def n_uavs(self) -> int:
        return int(self.uav_xyz_m.shape[0])

    @property
    def n_users(self) -> int:
        return int(self.load_bps.shape[0])

    @property
    def channels(self) -> tuple[int, ...]:
        """Each AP's 5 GHz channel number (:attr:`sim.fleet.FleetConfig.channels`)."""
        if self.channel_mode == "shared":
            return (CHANNELS_5GHZ[0],) * self.n_uavs
        return CHANNELS_5GHZ[: self.n_uavs]

    def cell(self, k: int) -> Case:
        """AP ``k`` and its own users as a single-AP :class:`Case` (id ``<id>-cell<k>``): what
        that cell would be alone. :class:`InputError` if AP ``k`` serves nobody."""
        mine = self.association == k
        if not np.any(mine):
            raise InputError(f"k: AP {k} serves no user (a case needs at least one)")
        return Case(f"{self.id}-cell{k}", self.uav_xyz_m[k], self.users_xy_m[mine],
                    self.load_bps[mine])  # fmt: skip


def fleet_link_losses_db(
    case: FleetCase, settings: Ns3Settings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The losses the worker sets for a fleet case in an urban environment or on a site, as
    :func:`link_losses_db` per AP: each AP to each user (K, U), the mean path loss of the fast
    model's expected mode; AP to AP (K, K) and user to user (U, U), free space (3-D distance
    between the UAVs: they see each other in the air, as :class:`sim.fleet.FleetModel`
    assumes for carrier sense on a shared channel)."""
    frequency_hz = settings.radio.frequency_hz
    per_ap = []
    for uav in case.uav_xyz_m:
        single = Case(case.id, uav, case.users_xy_m, case.load_bps)
        to_uav, between = link_losses_db(single, settings)
        per_ap.append(to_uav)
    gap = case.uav_xyz_m[:, None, :] - case.uav_xyz_m[None, :, :]
    ap_ap = friis_path_loss_db(np.sqrt(np.sum(gap * gap, axis=-1)), frequency_hz)
    return np.array(per_ap), np.asarray(ap_ap, dtype=float), between


def _fleet_request(case: FleetCase, settings: Ns3Settings, index: int) -> dict[str, Any]:
    single = Case(case.id, case.uav_xyz_m[0], case.users_xy_m, case.load_bps)
    request = _request(single, settings, index)
    request.pop("ap_loss_db", None)
    request.pop("sta_loss_db", None)
    if settings.environment != "open":
        to_uavs, ap_ap, between = fleet_link_losses_db(case, settings)
        request["ap_loss_db"] = to_uavs.ravel().tolist()
        request["ap_ap_loss_db"] = ap_ap.ravel().tolist()
        request["sta_loss_db"] = between.ravel().tolist()
    request["fleet"] = {
        "uavs": case.uav_xyz_m.tolist(),
        "channels": list(case.channels),
        "association": case.association.tolist(),
    }
    return request


class Ns3Runner:
    """A worker process that simulates cases one at a time; use it as a context manager.

    ``case_timeout_s``: the limit per case (default: 120 s + 30 s per simulated second, for a
    loaded machine); ``start_timeout_s``: the limit for importing ns-3 and compiling the
    scenario in a fresh worker; ``niceness``: the worker's ``os.nice`` increment (19 for
    background runs on a shared machine).
    """

    def __init__(
        self,
        case_timeout_s: float | None = None,
        start_timeout_s: float = 300.0,
        niceness: int = 0,
    ) -> None:
        require_ns3()
        self.case_timeout_s = case_timeout_s
        self.start_timeout_s = start_timeout_s
        self.niceness = niceness
        # The module run as ``python -m`` in the child (tests swap in a fake one).
        self.worker_module = "sim.ns3_worker"
        self.version: str | None = ns3_version()
        self.load_s: float | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._log: Any = None
        self._requests: Any = None
        self._reply_fd: int | None = None
        self._buffer = b""
        # After this many failed starts in a row, later cases fail at once (ns-3 is broken).
        self.max_start_failures = 2
        self._start_failures = 0
        self._start_error = ""

    # ---------------------------------------------------------------- process management

    def _start(self) -> None:
        request_r, request_w = os.pipe()
        reply_r, reply_w = os.pipe()
        root = str(Path(__file__).resolve().parent.parent)
        env = dict(os.environ)
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        self._log = tempfile.TemporaryFile()  # noqa: SIM115  (closed in _stop)
        try:
            self._proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    self.worker_module,
                    str(request_r),
                    str(reply_w),
                    str(self.niceness),
                ],
                pass_fds=(request_r, reply_w),
                stdin=subprocess.DEVNULL,
                stdout=self._log,
                stderr=self._log,
                env=env,
                cwd=root,
            )
        finally:
            os.close(request_r)
            os.close(reply_w)
        self._requests = os.fdopen(request_w, "w", encoding="utf-8")
        self._reply_fd = reply_r
        self._buffer = b""
        reply = self._read_reply(time.monotonic() + self.start_timeout_s, "starting ns-3")
        if not reply.get("ok"):
            self._stop()
            raise RuntimeError(reply.get("error", "ns-3 worker failed to start"))
        self.load_s = float(reply.get("load_s", math.nan))
        self.version = reply.get("ns3_version", self.version)

    def _log_tail(self, lines: int = 8) -> str:
        if self._log is None:
            return ""
        with contextlib.suppress(OSError, ValueError):
            self._log.seek(0)
            text = self._log.read().decode("utf-8", "replace")
            kept = [
                line
                for line in text.splitlines()
                if line.strip() and "Failed to materialize symbols" not in line
            ]
            return " | ".join(kept[-lines:])
        return ""

    def _stop(self) -> None:
        if self._requests is not None:
            with contextlib.suppress(OSError):
                self._requests.close()
            self._requests = None
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self._proc.wait(timeout=10)
            self._proc = None
        if self._reply_fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._reply_fd)
            self._reply_fd = None
        if self._log is not None:
            self._log.close()
            self._log = None

    def _read_reply(self, deadline: float, what: str) -> dict[str, Any]:
        """One JSON line from the worker; raises TimeoutError or EOFError (worker gone)."""
        assert self._reply_fd is not None
        while b"\n" not in self._buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"{what}: no answer within the time limit")
            ready, _, _ = select.select([self._reply_fd], [], [], remaining)
            if not ready:
                continue
            chunk = os.read(self._reply_fd, 1 << 20)
            if not chunk:
                code = self._proc.wait(timeout=10) if self._proc is not None else None
                raise EOFError(f"{what}: the ns-3 worker exited (status {code})")
            self._buffer += chunk
        line, self._buffer = self._buffer.split(b"\n", 1)
        return json.loads(line)

    def close(self) -> None:
        """Stop the worker (idempotent)."""
        self._stop()

    def __enter__(self) -> Ns3Runner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- simulation

    def timeout_for(self, settings: Ns3Settings) -> float:
        if self.case_timeout_s is not None:
            return self.case_timeout_s
        return 120.0 + 30.0 * settings.simulated_s

    def run(
        self,
        case: Case,
        settings: Ns3Settings = Ns3Settings(),
        index: int = 0,
        utility: UtilityConfig = UtilityConfig(),
    ) -> Ns3CaseResult:
        """Simulate one case; raises :class:`Ns3CaseError` if the worker crashes, hangs or
        raises (the worker is then replaced on the next call)."""
        return self._simulate(case, _request(case, settings, index), settings, utility)

    def run_fleet(
        self,
        case: FleetCase,
        settings: Ns3Settings = Ns3Settings(),
        index: int = 0,
        utility: UtilityConfig = UtilityConfig(),
    ) -> Ns3CaseResult:
        """Simulate one case with K access points (:class:`FleetCase`); the result's metrics
        are per user over all users (utility: :func:`sim.utility.network_utility` over all of
        them, as :class:`sim.fleet.FleetModel`'s). K = 1 gives :meth:`run`'s numbers for the
        same users, UAV, settings and index. Raises :class:`Ns3CaseError` as :meth:`run`."""
        return self._simulate(case, _fleet_request(case, settings, index), settings, utility)

    def _simulate(
        self,
        case: Case | FleetCase,
        request: dict[str, Any],
        settings: Ns3Settings,
        utility: UtilityConfig,
    ) -> Ns3CaseResult:
        if self._start_failures >= self.max_start_failures:
            raise Ns3CaseError(case.id, f"not run: {self._start_error}")
        try:
            if self._proc is None:
                try:
                    self._start()
                except (TimeoutError, EOFError, OSError, RuntimeError) as exc:
                    self._start_failures += 1
                    self._start_error = f"the ns-3 worker failed to start: {exc}"
                    raise
                self._start_failures = 0
            assert self._requests is not None
            self._requests.write(json.dumps(request) + "\n")
            self._requests.flush()
            reply = self._read_reply(
                time.monotonic() + self.timeout_for(settings), f"case {case.id}"
            )
        except (TimeoutError, EOFError, BrokenPipeError, OSError, RuntimeError) as exc:
            reason = f"{exc}"
            tail = self._log_tail()
            self._stop()
            raise Ns3CaseError(
                case.id, reason + (f" [worker log: {tail}]" if tail else "")
            ) from None
        if not reply.get("ok"):
            raise Ns3CaseError(case.id, str(reply.get("error", "unknown error")).strip())
        snapshots = reply["snapshots"]
        metrics, detail = _metrics(case, snapshots[0], snapshots[-1], settings, utility)
        intervals = [
            _metrics(case, a, b, settings, utility)[0] for a, b in itertools.pairwise(snapshots)
        ]
        return Ns3CaseResult(
            metrics=metrics,
            intervals=intervals,
            detail=detail,
            association_s=np.array(reply["assoc_time_s"], dtype=float),
            wall_s=float(reply["wall_s"]),
        )


def evaluate_case_ns3(
    case: Case,
    settings: Ns3Settings = Ns3Settings(),
    index: int = 0,
    utility: UtilityConfig = UtilityConfig(),
) -> CaseMetrics:
    """Simulate one case in a fresh worker (slow: ~20 s of start-up); raises Ns3CaseError."""
    with Ns3Runner() as runner:
        return runner.run(case, settings, index, utility).metrics


def evaluate_cases_ns3(
    cases: Sequence[Case],
    settings: Ns3Settings = Ns3Settings(),
    runner: Ns3Runner | None = None,
    on_result: Callable[[int, Ns3CaseResult | Ns3CaseError], None] | None = None,
    indices: Iterable[int] | None = None,
) -> list[Ns3CaseResult | Ns3CaseError]:
    """Simulate every case (case i with run number i + 1, or ``indices[i]`` + 1).

    Never raises for a failed case: its entry is the :class:`Ns3CaseError`. ``on_result`` is
    called after each case (for progress and incremental writes).
    """
    own = runner is None
    runner = runner or Ns3Runner()
    out: list[Ns3CaseResult | Ns3CaseError] = []
    index_list = list(indices) if indices is not None else list(range(len(cases)))
    try:
        for case, index in zip(cases, index_list, strict=True):
            try:
                result: Ns3CaseResult | Ns3CaseError = runner.run(case, settings, index)
            except Ns3CaseError as exc:
                result = exc
            out.append(result)
            if on_result is not None:
                on_result(len(out) - 1, result)
    finally:
        if own:
            runner.close()
    return out


def results_document(
    source: str,
    settings: Ns3Settings,
    results: Sequence[Ns3CaseResult | Ns3CaseError],
    version: str | None,
    with_detail: bool = True,
) -> dict[str, Any]:
    """The ``tupa-case-results/1`` document of an ns-3 run (``tupa sim evaluate`` fields plus
    ``backend``, ``ns3_version``, the ns-3 settings and ``failed``: cases that did not run)."""
    done = [r for r in results if isinstance(r, Ns3CaseResult)]
    failed = [r for r in results if isinstance(r, Ns3CaseError)]
    return {
        "format": RESULTS_FORMAT,
        "source": source,
        "backend": "ns3",
        "ns3_version": version,
        "environment": settings.environment,
        "mode": "stochastic",
        "seed": settings.seed,
        "queueing": settings.queueing,
        "warmup_s": settings.warmup_s,
        "measure_s": settings.measure_s,
        "ns3": settings.to_dict(),
        "cases": [r.to_dict(with_detail) for r in done],
        "failed": [{"id": e.case_id, "error": e.reason} for e in failed],
    }


def evaluate_cases_file_ns3(
    cases_path: Path,
    out_path: Path,
    seed: int,
    queueing: Queueing = "fq-codel",
    warmup_s: float = 0.5,
    measure_s: float = 2.0,
) -> tuple[str, int]:
    """``tupa sim evaluate --backend ns3``: every case of a file, results written atomically.

    Returns a one-line summary and the number of failed cases (listed under ``failed`` in the
    output; the others are written all the same). InputError if ns-3 is not installed.
    """
    area, cases = load_cases(cases_path)  # InputError naming a bad environment
    settings = Ns3Settings(  # InputError naming a bad environment
        queueing=queueing,
        warmup_s=warmup_s,
        measure_s=measure_s,
        seed=seed,
        user_height_m=area.user_height_m,
        environment=area.environment,
    )
    require_ns3()
    with Ns3Runner() as runner:
        results = evaluate_cases_ns3(cases, settings, runner)
        version = runner.version
    atomic_write_json(
        out_path, results_document(str(cases_path), settings, results, version, with_detail=False)
    )
    done = [r for r in results if isinstance(r, Ns3CaseResult)]
    failed = [r for r in results if isinstance(r, Ns3CaseError)]
    mean_utility = float(np.mean([r.metrics.utility for r in done])) if done else math.nan
    summary = (
        f"evaluated {len(done)} cases in ns-3 {version} (mean utility {mean_utility:.3f}); "
        f"wrote {out_path}"
    )
    for error in failed:
        summary += f"\n{error}"
    return summary, len(failed)
