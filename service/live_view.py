"""What the operator view shows, kept by the placement service: one JSON frame per decision period.

:class:`LiveView` keeps each vehicle's recent track and the utility of recent reports, and turns
a :class:`Moment` (what the service knows at one instant: link state, latest report, current
decision, policy) into a :class:`LiveFrame`. The placement loop calls :meth:`LiveView.record`
once per decision period: the tracks and the history grow (bounded), and when anyone watches a
frame is published through :attr:`LiveView.hub` (:mod:`service.pubsub`: never blocks the loop).
``GET /v1/live`` and the start of each stream use :meth:`LiveView.frame`.

A frame (``format: tupa-live/1``, JSON; metres in the area frame: x east, y north, z up)::

    {"format", "seq", "time_s", "decision_period_s",
     "area": {size_x_m, size_y_m, zone_m, z_min_m, z_max_m},
     "geofence": {"x_m": [lo, hi], "y_m": [..], "z_m": [..]},
     "envelopes": [{"inclusion": [[x, y], ...], "floor_m", "ceiling_m", "clearance_m",
                    "exclusions": [{"name", "polygon": [[x, y], ...], "floor_m", "ceiling_m"}]}],
     "site": {"cell_m", "nx", "ny", "heights_m": [...]} | null,   # buildings, on a site

     "policy": {"name", "spec"},
     "vehicles": [{"id", "link", "mode", "armed", "flavour", "streaming", "heartbeat_age_s",
                   "position_m", "heading_deg", "target_m", "track_m": [[x, y, z], ...],
                   "decision": {"source", "policy", "decided_at", "age_s"} | null,
                   "envelope": index into "envelopes",
                   "route": {"kind", "waypoints_m": [[x, y, z], ...], "hold_reason"} | null,
                   "battery": {"remaining_pct", "return_at_pct"},
                   "coverage": {"cell_m", "nx", "ny", "loss_db": [... | null]} | null}],
     "users": [{"id", "x_m", "y_m", "offered_bps", "throughput_bps", "delay_s", "plr",
                "served"}],                       # served: throughput / offered, in [0, 1]
     "report": {"timestamp", "age_s", "stale"} | null,
     "utility": {"t_s", "value", "throughput", "delay", "loss", "delay_ref_s"} | null,
     "utility_history": [[t_s, value, throughput, delay, loss], ...]}

The utility is the paper's (``sim.utility.network_utility``) of the latest report, and its three
parts are the weighted terms ``0.6·T``, ``0.3·(1 − D)`` and ``0.1·(1 − P)`` (each the same
function with the other two weights set to zero), so they add up to it. ``vehicles`` holds
the one vehicle (``uav1``) or a fleet's, in the fleet's order, each with its own track.
``heading_deg`` is the vehicle's own (telemetry; degrees clockwise from north), or null when it
sends none. On a site (``environment`` ``site:PATH``), ``site`` holds the buildings and each
vehicle's ``coverage`` the path loss from where it is (:mod:`service.live_site`); both are null
elsewhere.
"""

from __future__ import annotations

import json
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from service.decisions import Decision, Report
from service.fleet_spec import SOLE_VEHICLE_ID
from service.live_site import buildings_layer, coverage_layer
from service.pubsub import Hub
from service.vehicle_link import LinkState
from sim.channel import area_site
from sim.config import AreaConfig, UtilityConfig
from sim.envelope import Envelope, area_envelope
from sim.utility import network_utility

FORMAT = "tupa-live/1"
TRACK_POINTS = 300
"""Positions kept per vehicle (a new one when it has moved ``TRACK_STEP_M`` from the last)."""
TRACK_STEP_M = 0.5
HISTORY_POINTS = 600
"""Utility points kept: ten minutes at one report a second."""


@dataclass(frozen=True)
class LiveFrame:
    """One frame: its sequence number and its JSON (UTF-8), encoded once for every reader."""

    seq: int
    data: bytes


@dataclass(frozen=True)
class Moment:
    """What the service knows at one instant, as the operator view shows it."""

    time_s: float
    """Unix time, seconds."""
    link: LinkState
    policy_name: str
    policy_spec: str
    decision_period_s: float
    decision: Decision | None
    report: Report | None
    report_age_s: float | None
    """Seconds since the report arrived."""
    report_max_age_s: float
    fleet: tuple[tuple[str, LinkState, Decision | None], ...] = ()
    """A fleet's vehicles (id, link state, current decision), in the fleet's order; empty for
    one vehicle, which is ``link`` and ``decision`` (id ``uav1``)."""

    def vehicles(self) -> tuple[tuple[str, LinkState, Decision | None], ...]:
        """Every vehicle shown: the fleet's, or the one."""
        return self.fleet or ((SOLE_VEHICLE_ID, self.link, self.decision),)


class LiveView:
    """The track, the utility history and the frames (see the module docstring)."""

    def __init__(
        self,
        area: AreaConfig,
        utility: UtilityConfig,
        max_streams: int = 16,
        max_frames: int = 4,
    ) -> None:
        self.area = area
        self.utility_config = utility
        self.hub: Hub[LiveFrame] = Hub(max_streams, max_frames)
        """Where frames go out; each stream subscribes here."""
        self._parts = {
            "throughput": replace(utility, weight_delay=0.0, weight_loss=0.0),
            "delay": replace(utility, weight_throughput=0.0, weight_loss=0.0),
            "loss": replace(utility, weight_throughput=0.0, weight_delay=0.0),
        }
        self._lock = threading.Lock()  # the state below (the loop writes, requests read)
        self._tracks: dict[str, deque[tuple[float, float, float]]] = {}
        self._history: deque[tuple[float, float, float, float, float]] = deque(
            maxlen=HISTORY_POINTS
        )
        self._utility: dict[str, float] | None = None
        self._report_seen: Report | None = None
        self._seq = 0
        self.envelope_of: Callable[[str], Envelope | None] = lambda _vehicle_id: None
        """Each vehicle's envelope by id (the service sets it; None: the area's box)."""
        self._envelope_docs: dict[int, tuple[Envelope, dict[str, Any]]] = {}
        self._site = area_site(area)  # the area's district (site:PATH), None elsewhere
        self._buildings = None if self._site is None else buildings_layer(self._site, area)

    def record(self, moment: Moment) -> None:
        """Once per decision period: extend the track and the history, and publish a frame
        when anyone watches (building it only then)."""
        with self._lock:
            for vehicle_id, link, _ in moment.vehicles():
                position = link.position_m
                if position is None or not all(math.isfinite(v) for v in position):
                    continue
                track = self._tracks.setdefault(vehicle_id, deque(maxlen=TRACK_POINTS))
                last = track[-1] if track else None
                if last is None or math.dist(last, position) >= TRACK_STEP_M:
                    track.append(tuple(round(float(v), 1) for v in position))  # type: ignore[arg-type]
            report = moment.report
            if report is not None and report is not self._report_seen:
                self._report_seen = report
                parts = self.utility_parts(report)
                self._utility = None
                if parts is not None:
                    self._utility = u = {"t_s": round(moment.time_s, 3), **parts}
                    self._history.append(
                        (u["t_s"], u["value"], u["throughput"], u["delay"], u["loss"])
                    )
        if len(self.hub):
            self.hub.publish(self.frame(moment))

    def utility_parts(self, report: Report) -> dict[str, float] | None:
        """The report's utility and its three weighted parts (they add up to it); None when a
        number in the report makes one of them non-finite (the API refuses such reports, a
        Python caller may not), so a frame never carries NaN and no warning is raised on the
        loop's thread."""
        users = report.users
        args = (users.throughput_bps, users.delay_s, users.plr, users.offered_bps)
        with np.errstate(all="ignore"):
            out = {"value": float(network_utility(*args, self.utility_config))}
            for name, config in self._parts.items():
                out[name] = float(network_utility(*args, config))
        if not all(math.isfinite(v) for v in out.values()):
            return None
        return {name: round(v, 4) for name, v in out.items()}

    def frame(self, moment: Moment) -> LiveFrame:
        """The frame for ``moment`` (with the track and history recorded so far)."""
        with self._lock:
            self._seq += 1
            seq = self._seq
            tracks = {vid: [list(p) for p in track] for vid, track in self._tracks.items()}
            history = [list(h) for h in self._history]
            utility = self._utility if moment.report is self._report_seen else None
        if utility is None and moment.report is not None:  # a report the loop has not seen yet
            parts = self.utility_parts(moment.report)
            utility = None if parts is None else {"t_s": round(moment.time_s, 3), **parts}
        area = self.area
        envelopes: list[dict[str, Any]] = []
        envelope_index: dict[str, int] = {}
        for vid, _, _ in moment.vehicles():
            document = self._envelope_document(vid)
            if document not in envelopes:
                envelopes.append(document)
            envelope_index[vid] = envelopes.index(document)
        body: dict[str, Any] = {
            "format": FORMAT,
            "seq": seq,
            "time_s": round(moment.time_s, 3),
            "decision_period_s": moment.decision_period_s,
            "area": {
                "size_x_m": area.size_x_m,
                "size_y_m": area.size_y_m,
                "zone_m": area.zone_m,
                "z_min_m": area.z_min_m,
                "z_max_m": area.z_max_m,
            },
            "geofence": {  # the volume every target is clamped into (sim.geometry.clamp_point)
                "x_m": [0.0, area.size_x_m],
                "y_m": [0.0, area.size_y_m],
                "z_m": [area.z_min_m, area.z_max_m],
            },
            "envelopes": envelopes,
            "site": self._buildings,
            "policy": {"name": moment.policy_name, "spec": moment.policy_spec},
            "vehicles": [
                {
                    **_vehicle(vid, link, decision, moment.time_s, tracks.get(vid, [])),
                    "envelope": envelope_index[vid],
                    "coverage": self._coverage(link.position_m),
                }
                for vid, link, decision in moment.vehicles()
            ],
            "users": _users(moment.report),
            "report": _report(moment),
            "utility": (
                {**utility, "delay_ref_s": self.utility_config.delay_ref_s} if utility else None
            ),
            "utility_history": history,
        }
        data = json.dumps(body, separators=(",", ":"), allow_nan=False).encode()
        return LiveFrame(seq, data)

    def _coverage(self, position_m: tuple[float, float, float] | None) -> dict[str, Any] | None:
        """On a site, what the vehicle at ``position_m`` covers (:func:`~service.live_site.
        coverage_layer`); None elsewhere or without a (finite) position."""
        if self._site is None or position_m is None:
            return None
        if not all(math.isfinite(v) for v in position_m):
            return None
        return coverage_layer(self._site, self.area, position_m)

    def _envelope_document(self, vehicle_id: str) -> dict[str, Any]:
        """The vehicle's envelope as the frame carries it, built once per envelope."""
        envelope = self.envelope_of(vehicle_id) or area_envelope(self.area)
        kept = self._envelope_docs.get(id(envelope))
        if kept is None or kept[0] is not envelope:
            kept = (envelope, envelope_document(envelope))
            self._envelope_docs[id(envelope)] = kept
        return kept[1]


def envelope_document(envelope: Envelope) -> dict[str, Any]:
    """An envelope as the live frame carries it (polygons as corner lists, metres)."""

    def ring(polygon: Any) -> list[list[float]]:
        return [[round(x, 2), round(y, 2)] for x, y in polygon.exterior.coords[:-1]]

    return {
        "inclusion": ring(envelope.inclusion),
        "exclusions": [
            {
                "name": e.name,
                "polygon": ring(e.footprint),
                "floor_m": e.floor_m,
                "ceiling_m": e.ceiling_m,
            }
            for e in envelope.exclusions
        ],
        "floor_m": envelope.floor_m,
        "ceiling_m": envelope.ceiling_m,
        "clearance_m": envelope.clearance_m,
    }


def _number(value: float | None, digits: int | None = 3) -> float | int | None:
    """``value`` rounded (``digits`` None: to an int), or None when unknown or not finite
    (JSON has no NaN)."""
    if value is None or not math.isfinite(value):
        return None
    return round(float(value), digits)


def _point(point: tuple[float, float, float] | None) -> list[float | None] | None:
    return None if point is None else [_number(v, 2) for v in point]


def _vehicle(
    vehicle_id: str,
    state: LinkState,
    decision: Decision | None,
    time_s: float,
    track: list[list[float]],
) -> dict[str, Any]:
    return {
        "id": vehicle_id,
        "link": state.link,
        "mode": state.mode,
        "armed": state.armed,
        "flavour": state.flavour,
        "streaming": state.streaming,
        "control": {"holder": state.control, "reason": state.control_reason},
        "heartbeat_age_s": _number(state.heartbeat_age_s),
        "position_m": _point(state.position_m),
        "heading_deg": _number(state.heading_deg, 1),
        "target_m": _point(decision.target_m if decision else state.target_m),
        "track_m": track,
        "route": None
        if state.route is None
        else {
            "kind": state.route.kind,
            "waypoints_m": [_point(w) for w in state.route.waypoints_m],
            "hold_reason": state.route.hold_reason,
        },
        "battery": {
            "remaining_pct": _number(state.battery_pct, 1),
            "return_at_pct": _number(state.battery_return_at_pct, 1),
        },
        "decision": None
        if decision is None
        else {
            "source": decision.source,
            "policy": decision.policy,
            "decided_at": round(decision.decided_at, 3),
            "age_s": _number(time_s - decision.decided_at),
        },
    }


def _users(report: Report | None) -> list[dict[str, Any]]:
    if report is None:
        return []
    users = report.users
    offered = np.asarray(users.offered_bps, dtype=float)
    throughput = np.asarray(users.throughput_bps, dtype=float)
    with np.errstate(all="ignore"):
        served = np.clip(throughput / np.maximum(offered, 1e-9), 0.0, 1.0)
    return [
        {
            "id": user_id,
            "x_m": _number(float(users.x_m[i]), 2),
            "y_m": _number(float(users.y_m[i]), 2),
            "offered_bps": _number(float(offered[i]), None),
            "throughput_bps": _number(float(throughput[i]), None),
            "delay_s": _number(float(users.delay_s[i]), 5),
            "plr": _number(float(users.plr[i]), 4),
            "served": _number(float(served[i]), 4),
        }
        for i, user_id in enumerate(report.user_ids)
    ]


def _report(moment: Moment) -> dict[str, Any] | None:
    if moment.report is None:
        return None
    age = moment.report_age_s
    return {
        "timestamp": moment.report.timestamp_s,
        "age_s": _number(age),
        "stale": age is None or age > moment.report_max_age_s,
    }
