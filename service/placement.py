"""The placement loop: user reports + vehicle telemetry -> policy -> geofenced setpoint.

:class:`PlacementService` is what ``tupa serve`` runs behind its HTTP side::

    service = open_service(settings)   # service.opening: opens the MAVLink link(s)
    service.start()
    service.submit(report)             # POST /v1/reports: accept(), then receipt()
    service.current_decision()         # GET /v1/setpoint
    service.stop()

Decisions: with ``decision_mode="paced"`` a background thread decides once every decision period
(the ``world``'s step, the paper's S, unless ``step_s`` is set) from the latest report; with
``"on-report"`` an accepted report asks a background thread for a decision (see below). A
decision needs a fresh report (received at most ``report_max_age_s`` ago; otherwise the target
is held) and the vehicle's position (link up; a report that arrives while the link is down is
kept, and the decision waits for the link: the paced thread retries every step, and in
``on-report`` mode the decision thread decides as soon as the link is back, if the report is
still fresh). Every kind of policy decides every period while the vehicle flies: a discrete move
applies to the zone the vehicle is in and replaces the target (:func:`sim.geometry.move_target`, the
environments' rule), so the service acts in the world the policy was trained in. Targets go
through the link, which clamps them to the geofence.

Decisions never queue. One decision runs at a time, always on the latest report. In
``on-report`` mode at most one decision is pending: a report that arrives while a decision runs
waits as *the* next one, and a newer report replaces it (latest wins), so a burst of reports
costs one decision after the running one, never one each. :meth:`PlacementService.submit` says
what became of each report (:class:`ReportReceipt`): ``decided`` (a decision was taken from it;
the answer carries it), ``held`` (a decision was attempted on it but the target is held: no link,
a stale report, a refused target or a failing policy), ``superseded`` (a newer report replaced it
before a decision read it; answered at once), ``pending`` (its decision had not ended within
:data:`REPORT_WAIT_PERIODS` decision periods of its arrival: a decision slower than the period
runs ahead of it; it stays the next report to decide unless a newer one replaces it) or, in
``paced`` mode, ``stored``. So a report is answered within two decision periods of its arrival
(when the HTTP side takes less than a quarter of one), however slow the policy and however many
reports arrive. Each decision's duration is measured (:meth:`PlacementService.decision_timing`):
one longer than the decision period is counted as an overrun (``decision_overruns``) and logged
(at most once a minute); decisions then come once per decision, not once per period.

Reports are snapshots of all users; each replaces the previous one (users come and go). Reports
are ordered by ``min(timestamp, arrival time)`` (this machine's clock): a report older than the
last accepted one in that order is ignored and counted (409), a repeat of the last one is
accepted. A report may be stamped up to ``report_max_future_s`` ahead of this machine's clock
(clock skew) and counts as stamped when it arrived, so one stamped ahead can never make the honest
reports after it "older"; one stamped further ahead is refused and counted.

Restarts: with a ``state_file`` the serving policy and the last decision are persisted after each
decision and swap. On start the persisted policy is loaded again (when it differs from the
configured one, and only from ``policy_dirs``, as for a swap: the state file is just a file; if it
cannot be loaded, the configured one serves and the reason is logged and counted), and the last
target is shown as the current decision with source ``restored`` but is *not* streamed: after a
restart nothing is sent to the vehicle until a fresh report leads to a decision, and
``arm_and_takeoff`` (when set) is deferred to that decision too (whenever the state file exists:
that is what makes a start a restart), so a restart never arms or moves the vehicle by surprise.
Meanwhile the vehicle does what its own failsafe for a lost setpoint stream does (PX4: hold;
ArduPilot GUIDED: hold the last target).

The operator view: once per decision period (after the decision in ``paced`` mode; from the
link watcher in ``on-report`` mode) the loop hands what it knows to :attr:`PlacementService.live`
(:mod:`service.live_view`), which keeps the track and the utility history and publishes a frame
to the open pages without ever waiting for them (:mod:`service.pubsub`).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import Counter, deque
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from policies.interface import Policy
from service.decisions import (
    AcceptedReport,
    Decision,
    DecisionTiming,
    Report,
    ReportOutcome,
    ReportReceipt,
    VehicleView,
    restored_decision,
)
from service.fleet_spec import SOLE_VEHICLE_ID, envelope_for
from service.live_view import LiveFrame, LiveView, Moment
from service.policy_runtime import load_policy
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig, LinkState, VehicleLink
from sim.atomic import atomic_write_json
from sim.config import AreaConfig
from sim.envelope import Envelope
from sim.errors import InputError
from sim.world import World

STATE_FORMAT = "tupa-service-state/1"
log = logging.getLogger(__name__)

LINK_POLL_S = 0.05
"""How often the ``on-report`` decision thread looks at the link while a report waits for it."""

REPORT_WAIT_PERIODS = 1.75
"""In ``on-report`` mode, how long (in decision periods, from its acceptance) a report waits for
the decision on it before it is answered ``pending``: about one period for a decision already
running and one for its own, less a quarter of a period left to the HTTP side (parsing and
answering a report of 1,000 users takes tens of milliseconds), so that the answer comes within
two periods of the report's arrival."""

OVERRUN_LOG_EVERY_S = 60.0
"""At most one log line per this many seconds about decisions slower than the decision period."""


def _vehicle_known(state: LinkState) -> bool:
    """What a decision needs from the link: up, with the vehicle's position."""
    return link_problem(state) is None


def link_problem(state: LinkState) -> str | None:
    """Why the link does not let the vehicle be commanded now (None: it does): the link is down,
    no position is known, or the vehicle left the service's hands (:mod:`service.control`)."""
    if state.link != "up":
        return f"mavlink link is {state.link}"
    if state.position_m is None:
        return "no vehicle position yet (telemetry not received)"
    if state.fence not in ("off", "uploaded"):
        return f"the autopilot's fence is not on the vehicle ({state.fence}): nothing streams yet"
    if state.control != "service":
        return (
            f"the {state.control} has the vehicle: {state.control_reason}; the service streams "
            "nothing until an operator hands it back (PUT /v1/vehicle/control; in a fleet "
            "/v1/vehicles/ID/control)"
        )
    return None


def vehicle_notes(state: LinkState) -> list[str]:
    """What else keeps a vehicle from being ready, besides :func:`link_problem`: a take-off in
    progress (its phase, attempt and last refusal) or failed, messages that failed the signing
    check, a vehicle that signs while no key is configured. The same for one vehicle and for
    each of a fleet's (``/readyz``)."""
    notes = []
    if state.takeoff == "running":
        refusal = (
            f"; last refusal: {state.takeoff_last_refusal}" if state.takeoff_last_refusal else ""
        )
        notes.append(
            f"take-off in progress: {state.takeoff_phase} "
            f"(attempt {state.takeoff_attempts}){refusal}"
        )
    elif state.takeoff.startswith("failed"):
        notes.append(f"take-off {state.takeoff}")
    signing_failures = state.counters.get("signing_failures", 0)
    if signing_failures and state.link != "up":
        notes.append(
            f"mavlink signing failed: {signing_failures} messages from the vehicle failed "
            "the signature check (check TUPA_MAVLINK_SIGNING_KEY against the vehicle's key); "
            "the vehicle is not commanded"
        )
    if state.counters.get("signed_vehicle_without_key", 0):
        notes.append(
            "mavlink signing: the vehicle signs its messages but no signing key is "
            "configured (TUPA_MAVLINK_SIGNING_KEY); it will ignore our setpoints"
        )
    return notes


class OutOfOrderReportError(ValueError):
    """A report older than the last accepted one."""


class FutureReportError(ValueError):
    """A report stamped further ahead of the service's clock than ``report_max_future_s``."""


class PolicyBusyError(RuntimeError):
    """Another policy is being loaded: policies are loaded one at a time."""


class PlacementService:
    """Owns the link, the serving policy, the latest report and the current decision."""

    def __init__(
        self,
        settings: ServiceSettings,
        link: VehicleLink,
        policy: Policy,
        world: World | None = None,
    ) -> None:
        self.settings = settings
        self.link = link
        self.links: dict[str, VehicleLink] = {SOLE_VEHICLE_ID: link}
        """Every vehicle's link by id (one here; a fleet's in :mod:`service.fleet_placement`)."""
        self.world = world if world is not None else settings.policy_world()
        """The world the policy decides in (area, network, utility, decision period)."""
        self._policy = policy
        self._lock = threading.Lock()  # the state below; held for microseconds
        self._deciding = threading.Lock()  # one decision at a time (see decide_once)
        self._swapping = threading.Lock()  # one policy load at a time (see swap_policy)
        self._stop = threading.Event()
        self._persisted_control: dict[str, dict[str, str]] = {}  # last written control
        self._envelope_documents: dict[str, dict[str, Any]] = {}  # put in flight, by vehicle
        self._thread: threading.Thread | None = None
        self._waiting_for_link = threading.Event()  # a report was held because the link is down
        self._report: Report | None = None
        self._report_received: float | None = None  # monotonic
        self._last_order_s = -math.inf  # min(timestamp, arrival) of the last accepted report
        # Coalescing (on-report): reports are numbered as accepted; a decision records the
        # number of the report it read; waiting reports are told (under _lock) when a report is
        # accepted or a decision ends.
        self._changed = threading.Condition(self._lock)
        self._wake = threading.Event()  # on-report: a report waits for a decision
        self._report_seq = 0  # the latest accepted report's number
        self._reading_seq = 0  # the report the running (or last) decision read
        self._attempts: deque[tuple[int, Decision | None]] = deque(maxlen=16)  # ended decisions
        self._decision_last_s: float | None = None
        self._decision_max_s: float | None = None
        self._overrun_logged_at = -math.inf  # monotonic
        self._decision: Decision | None = None
        self.counters: Counter[str] = Counter()
        self._takeoff_deferred = False
        self.live = LiveView(self.world.area, self.world.utility, settings.live_max_streams)
        self.live.envelope_of = lambda vid: self.links[vid].envelope
        """The operator view's track, utility history and frames (published each period)."""

    @property
    def area(self) -> AreaConfig:
        """The area the service places in (the world's)."""
        return self.world.area

    @property
    def submit_waits(self) -> bool:
        """Whether :meth:`receipt` (and :meth:`submit`) may block before it returns
        (``on-report`` mode: it waits, up to :attr:`report_wait_s`, for the decision on the
        report), so an event loop should call it from a worker thread; otherwise it answers
        at once."""
        return self.settings.decision_mode == "on-report"

    @property
    def report_wait_s(self) -> float:
        """``on-report``: how long a report waits for its decision before it is answered
        ``pending`` (:data:`REPORT_WAIT_PERIODS` decision periods)."""
        return REPORT_WAIT_PERIODS * self.settings.decision_period_s

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_settings(cls, settings: ServiceSettings) -> PlacementService:
        """Load the policy (``InputError`` if unusable) and open the link (retries on its own).
        One vehicle; :func:`service.opening.open_service` opens whichever ``settings`` ask for."""
        from service.links import open_link

        if settings.is_fleet:
            raise ValueError("a fleet's settings: FleetPlacementService.from_settings")
        world = settings.policy_world()
        # The operator's own choice (or the served default for the environment): from any
        # directory, within the size limit.
        spec = settings.served_policy_spec()
        policy = load_policy(spec, world, max_bytes=settings.checkpoint_max_bytes)
        (vehicle,) = settings.fleet_spec().vehicles
        link_config = LinkConfig(
            url=settings.mavlink,
            area=world.area,
            envelope=vehicle.envelope(world.area),
            frames=settings.frames(),
            setpoint_rate_hz=settings.setpoint_rate_hz,
            signing_key=settings.signing_key_bytes(),
            battery=settings.battery(),
            autopilot_fence=settings.autopilot_fence,
            fence_action=settings.fence_action,
        )
        link = open_link(settings.mavlink_backend, link_config)
        return cls(settings, link, policy, world)

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> PlacementService:
        self.link.start()
        restarted = self._restore()
        if self.settings.arm_and_takeoff:
            if restarted:
                # A restart: arm and take off only once a fresh report leads to a decision.
                self._takeoff_deferred = True
                log.info("restarted (state file found): arm-and-takeoff waits for a decision")
            else:
                self.link.arm_and_takeoff(timeout_s=self.settings.takeoff_timeout_s)
        self._start_loop()
        return self

    def _start_loop(self) -> None:
        """The decision thread: once a period (``paced``) or for the latest report
        (``on-report``)."""
        if self.settings.decision_mode == "paced":
            target, name = self._run, "placement"
        else:
            target, name = self._decide_reports, "placement-on-report"
        self._thread = threading.Thread(target=target, name=name, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self.live.hub.close_all()  # ends the open pages' streams
        self._wake.set()  # wakes the on-report decision thread
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self.close_links()

    def close_links(self) -> None:
        """Close the vehicle link(s) (safe to call twice)."""
        self.link.close()

    # ------------------------------------------------------------------ inputs

    def submit_report(self, report: Report) -> Decision | None:
        """:meth:`submit`, answering only with the receipt's decision."""
        return self.submit(report).decision

    def submit(self, report: Report) -> ReportReceipt:
        """Accept a report and say what became of it: :meth:`accept`, then :meth:`receipt`."""
        return self.receipt(self.accept(report))

    def accept(self, report: Report) -> AcceptedReport:
        """Accept a report as the latest (in ``on-report`` mode, ask the decision thread for a
        decision); never blocks beyond a lock held for microseconds, so an event loop may call
        it, in the order reports arrive.

        Raises :class:`OutOfOrderReportError` (and counts it) for a report older than the last
        accepted one, ordering reports by ``min(timestamp, arrival time)``, and
        :class:`FutureReportError` (counted too) for one stamped more than
        ``report_max_future_s`` ahead of this machine's clock. A report stamped ahead (within
        the tolerance) counts as stamped when it arrived, so it cannot make honest reports
        after it "older".
        """
        now_s = time.time()
        ahead_s = report.timestamp_s - now_s
        if not ahead_s <= self.settings.report_max_future_s:  # also refuses a NaN
            self._count("reports_from_the_future")
            raise FutureReportError(
                f"timestamp: {ahead_s:.3g} s ahead of this service's clock, more than "
                f"report_max_future_s ({self.settings.report_max_future_s:g} s): a report from "
                "the future; check the controller's clock"
            )
        order_s = min(report.timestamp_s, now_s)
        with self._lock:
            if order_s < self._last_order_s:
                self.counters["reports_out_of_order"] += 1
                raise OutOfOrderReportError(
                    f"timestamp: {report.timestamp_s} is older than the last accepted report "
                    f"({self._last_order_s}; a report stamped ahead of this service's clock "
                    "counts as stamped when it arrived); ignored"
                )
            self._last_order_s = order_s
            self._report = report
            self._report_received = arrived = time.monotonic()
            self._report_seq += 1
            seq = self._report_seq
            self.counters["reports_accepted"] += 1
            self._changed.notify_all()  # a report waiting for a decision is superseded
        if self.settings.decision_mode == "on-report":
            self._wake.set()
        return AcceptedReport(seq, arrived)

    def receipt(self, accepted: AcceptedReport) -> ReportReceipt:
        """What became of an accepted report (:class:`ReportReceipt`).

        ``paced``: stored for the next period's decision (``stored``), at once. ``on-report``:
        waits until the decision on this report ends (``decided`` or ``held``), a newer report
        replaces it first (``superseded``, at once), or :attr:`report_wait_s` passes from its
        acceptance (``pending``). It never waits behind decisions on older reports beyond the
        one running when the report came. Without a decision thread (not started, or stopped)
        it decides on the caller's thread."""
        if self.settings.decision_mode != "on-report":
            return ReportReceipt("stored", self.current_decision())
        if self._decider_running():
            return self._receipt(accepted.seq, accepted.arrived + self.report_wait_s)
        self._decide_guarded()  # no decision thread: this one decides
        return self._receipt(accepted.seq, time.monotonic())

    def _decider_running(self) -> bool:
        thread = self._thread
        return thread is not None and thread.is_alive() and not self._stop.is_set()

    def _receipt(self, seq: int, deadline: float) -> ReportReceipt:
        """Wait (until ``deadline``, monotonic) for the decision on report ``seq``, and say
        what became of the report."""
        with self._lock:
            while True:
                outcome, decision = self._outcome(seq)
                if outcome is None:
                    remaining = deadline - time.monotonic()
                    if remaining > 0:
                        self._changed.wait(remaining)
                        continue
                    outcome = "pending"
                if outcome in ("superseded", "pending"):
                    self.counters[f"reports_{outcome}"] += 1
                break
        if outcome == "decided":
            return ReportReceipt(outcome, decision)
        return ReportReceipt(outcome, self.current_decision())

    def _outcome(self, seq: int) -> tuple[ReportOutcome | None, Decision | None]:
        """(what became of report ``seq`` so far, None while undecided; the decision taken
        from it). Called with ``_lock`` held."""
        for read, decision in self._attempts:
            if read == seq:
                return ("held", None) if decision is None else ("decided", decision)
        if self._report_seq > seq and self._reading_seq != seq:
            return "superseded", None  # no decision reads it any more: they read the latest
        return None, None

    def swap_policy(self, spec: str) -> Policy:
        """Load and check ``spec`` fully, then swap it in atomically (``InputError`` otherwise:
        the serving policy stays).

        Checkpoints load only from ``settings.policy_dirs`` (checked on the file as opened, see
        :func:`~service.policy_runtime.load_policy`) and up to ``checkpoint_max_bytes``. One
        swap at a time: while one is loading, another raises :class:`PolicyBusyError` at once
        (rather than queueing loads, each holding a worker thread).
        """
        if not self._swapping.acquire(blocking=False):
            self._count("policy_swaps_busy")
            raise PolicyBusyError("policy: another policy is being loaded; retry once it is done")
        try:
            policy = self._load_allowed(spec)
            with self._lock:
                self._policy = policy
                self.counters["policy_swaps"] += 1
        finally:
            self._swapping.release()
        self._persist()
        log.info("policy switched to %s", policy.name)
        return policy

    # ------------------------------------------------------------------ outputs

    @property
    def policy(self) -> Policy:
        with self._lock:
            return self._policy

    def current_decision(self) -> Decision | None:
        with self._lock:
            return self._decision

    def vehicle(self) -> LinkState:
        return self.link.state()

    def sole_vehicle_id(self) -> str | None:
        """The id of the one vehicle this service drives (``uav1``); None when it drives more.
        What the single-vehicle routes (``GET /v1/vehicle``, ...) and fields (``target``) need."""
        return next(iter(self.links)) if len(self.links) == 1 else None

    def decisions(self) -> dict[str, Decision]:
        """The target of each commanded vehicle, by id (one vehicle: its one, once decided)."""
        return self._by_vehicle(self.current_decision())

    def receipt_decisions(self, receipt: ReportReceipt) -> dict[str, Decision]:
        """The targets to answer a report with (``POST /v1/reports``), by vehicle id: the
        decision the receipt carries (taken from that report, when ``decided``)."""
        return self._by_vehicle(receipt.decision)

    def _by_vehicle(self, decision: Decision | None) -> dict[str, Decision]:
        """The one vehicle's ``decision`` by its id (none: empty)."""
        return {} if decision is None else {next(iter(self.links)): decision}

    @property
    def separation_m(self) -> float | None:
        """The minimum 3-D distance kept between any two vehicles' targets (None: one vehicle)."""
        return None

    def vehicles(self) -> list[VehicleView]:
        """The one vehicle as a fleet of one (``GET /v1/vehicles``), id ``uav1``."""
        state = self.link.state()
        return [
            VehicleView(SOLE_VEHICLE_ID, None, state, self.current_decision(), link_problem(state))
        ]

    def _can_decide(self) -> bool:
        """Whether the link lets a decision be taken now (the ``on-report`` watcher asks)."""
        return _vehicle_known(self.link.state())

    def readiness(self) -> tuple[bool, list[str]]:
        """(ready, reasons it is not): a policy is loaded and the MAVLink link is up."""
        state = self.link.state()
        problem = link_problem(state)
        reasons = [problem] if problem else []
        reasons += vehicle_notes(state)
        return not reasons, reasons

    def _count(self, name: str) -> None:
        """Count an event (counters are bumped from the decision thread and request threads)."""
        with self._lock:
            self.counters[name] += 1

    def snapshot_counters(self) -> dict[str, int]:
        """The counters by name, among them ``reports_accepted``, ``reports_superseded`` and
        ``reports_pending`` (``on-report`` answers before a decision on the report:
        :class:`ReportReceipt`), ``decisions``, ``decisions_timed``, ``decision_overruns``
        (decisions longer than the decision period) and ``decision_time_us_total``."""
        with self._lock:
            return dict(self.counters)

    def decision_timing(self) -> DecisionTiming:
        """How long decisions take against the decision period (``GET /v1/policy``)."""
        with self._lock:
            return DecisionTiming(
                mode=self.settings.decision_mode,
                period_s=self.settings.decision_period_s,
                timed=self.counters["decisions_timed"],
                last_s=self._decision_last_s,
                max_s=self._decision_max_s,
                overruns=self.counters["decision_overruns"],
            )

    # ------------------------------------------------------------------ the operator view

    def live_frame(self) -> LiveFrame:
        """The operator view's frame for now (``GET /v1/live``; the start of each stream)."""
        return self.live.frame(self._moment())

    def _moment(self) -> Moment:
        with self._lock:
            report, received, decision, policy = (
                self._report,
                self._report_received,
                self._decision,
                self._policy,
            )
        return Moment(
            time_s=time.time(),
            link=self.link.state(),
            policy_name=policy.name,
            policy_spec=policy.spec,
            decision_period_s=self.settings.decision_period_s,
            decision=decision,
            report=report,
            report_age_s=None if received is None else time.monotonic() - received,
            report_max_age_s=self.settings.report_max_age_s,
        )

    def _tick_live(self) -> None:
        """Once per decision period: the view records and publishes (never blocks; a failure
        is counted and logged, and never stops the loop), and a change of who has a vehicle is
        written to the state file."""
        try:
            self.live.record(self._moment())
        except Exception:
            self._count("live_errors")
            log.exception("operator view: could not record this period")
        control = self._control_document()
        if control != self._persisted_control:
            self._persisted_control = control
            self._persist()

    def set_envelope(self, vid: str, document: dict[str, Any], persist: bool = True) -> Envelope:
        """Give vehicle ``vid`` the envelope ``document`` (a ``tupa-envelope/1`` document, in
        the live frame) from now on, and keep it in the state file: a restart flies in it again
        (:meth:`_restore_envelopes`). InputError naming the field for a document that cannot
        be flown; nothing changes then."""
        link = self.links[vid]
        envelope = envelope_for(document, self.world.area, link.config.frames)
        link.set_envelope(envelope)
        with self._lock:
            self._envelope_documents[vid] = document
        if persist:
            self._persist()
        return envelope

    def _restore_envelopes(self, saved: object, path: object) -> None:
        """Give each vehicle the envelope an operator put in flight before the restart (a
        saved one that no longer fits the area or names an unknown vehicle is ignored and
        counted: the configured one stays)."""
        if saved is None:
            return
        if not isinstance(saved, dict):
            saved = {"": saved}
        for vid, document in saved.items():
            if vid not in self.links or not isinstance(document, dict):
                log.warning("ignoring the envelope of %r in the state file %s", vid, path)
                self._count("state_restore_errors")
                continue
            try:
                self.set_envelope(vid, document, persist=False)
            except InputError as exc:
                log.warning("ignoring the envelope of %r in the state file %s: %s", vid, path, exc)
                self._count("state_restore_errors")
                continue
            log.info("restored %s's envelope from %s", vid, path)

    def _envelopes_document(self) -> dict[str, dict[str, Any]]:
        with self._lock:
            return dict(self._envelope_documents)

    def _control_document(self) -> dict[str, dict[str, str]]:
        """Who has each vehicle that is not the service's, by id: what a restart must keep (a
        restarted service must not take back a vehicle its pilot or a failsafe took)."""
        document = {}
        for vid, link in self.links.items():
            state = link.state()
            if state.control != "service":
                document[vid] = {"holder": state.control, "reason": state.control_reason}
        return document

    # ------------------------------------------------------------------ deciding

    def decide_once(self) -> Decision | None:
        """One decision from the latest report (None when held: stale report, no link).

        Decisions are taken one at a time (the decision thread, and callers such as tests, may
        ask together; the one that reads the latest report must set the target last). The
        report it read and what came of it are recorded for the reports waiting on it
        (:meth:`submit`)."""
        with self._deciding:
            decision = None
            try:
                decision = self._decide_latest()
            finally:
                with self._lock:
                    self._attempts.append((self._reading_seq, decision))
                    self._changed.notify_all()
            return decision

    def _fresh_report(self) -> tuple[Report, Policy] | None:
        """The latest report and the serving policy, if a report is fresh enough to decide on
        (a stale one is counted: the target is held). Every ``_decide_latest`` reads the report
        through here: it records which report the decision reads."""
        with self._lock:
            report, received, policy = self._report, self._report_received, self._policy
            self._reading_seq = self._report_seq
        if report is None or received is None:
            return None
        if time.monotonic() - received > self.settings.report_max_age_s:
            self._count("decisions_held_stale")
            return None
        return report, policy

    def _decide_latest(self) -> Decision | None:
        fresh = self._fresh_report()
        if fresh is None:
            return None
        report, policy = fresh
        state = self.link.state()
        if not _vehicle_known(state):
            self._count("decisions_waiting_link")
            self._waiting_for_link.set()
            return None
        vehicle = np.asarray(state.position_m, dtype=float)
        if self._takeoff_deferred:  # the first decision after a restart (see start())
            self._takeoff_deferred = False
            self.link.arm_and_takeoff(timeout_s=self.settings.takeoff_timeout_s)
        started = time.perf_counter()
        try:
            target = policy.decide(report.users, vehicle)
            clamped = self.link.set_target(tuple(float(v) for v in target))
        except ValueError as exc:  # a non-finite target: refused by the geofence, target held
            self._count("decisions_rejected")
            log.warning("decision rejected: %s", exc)
            return None
        finally:
            self._record_decision_time(time.perf_counter() - started)
        decision = Decision(clamped, "policy", policy.name, time.time())
        with self._lock:
            self._decision = decision
            self.counters["decisions"] += 1
        self._persist()
        return decision

    def _record_decision_time(self, elapsed_s: float) -> None:
        """Record one decision's duration; one longer than the decision period is an overrun
        (counted; logged at most once every :data:`OVERRUN_LOG_EVERY_S`)."""
        period_s = self.settings.decision_period_s
        now = time.monotonic()
        with self._lock:
            self.counters["decisions_timed"] += 1
            self.counters["decision_time_us_total"] += int(elapsed_s * 1e6)
            self._decision_last_s = elapsed_s
            self._decision_max_s = max(elapsed_s, self._decision_max_s or 0.0)
            overrun = elapsed_s > period_s
            if overrun:
                self.counters["decision_overruns"] += 1
            log_it = overrun and now - self._overrun_logged_at >= OVERRUN_LOG_EVERY_S
            if log_it:
                self._overrun_logged_at = now
            overruns = self.counters["decision_overruns"]
        if log_it:
            log.warning(
                "a decision took %.3g s, longer than the decision period (%g s): decisions come "
                "once per decision, not once per period (%d such decisions so far)",
                elapsed_s,
                period_s,
                overruns,
            )

    def _decide_guarded(self) -> None:
        """:meth:`decide_once`, where a policy bug holds the target instead of failing the
        caller (the paced loop, or the report's HTTP request): counted and logged."""
        try:
            self.decide_once()
        except Exception:
            self._count("decision_errors")
            log.exception("decision failed; holding the current target")

    def _decide_reports(self) -> None:
        """``on-report`` mode's decision thread: decides the latest report whenever one waits
        (one decision at a time; reports that arrive meanwhile make one pending decision, not
        one each). A report held because the link was down is decided once the link is up
        again (if still fresh: :meth:`decide_once` holds a stale one), not only when the next
        report happens to arrive. It also gives the operator view its period."""
        period_s = self.settings.decision_period_s
        next_tick = time.monotonic()
        waiting_link = False
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_tick:  # the operator view's period (decisions come with reports)
                self._tick_live()
                next_tick += period_s
                if next_tick <= now:  # fell behind: the next period from now
                    next_tick = now + period_s
            timeout_s = min(0.5, max(0.0, next_tick - now))
            if waiting_link and not self._wake.is_set():
                if not self._can_decide():
                    self._stop.wait(min(LINK_POLL_S, timeout_s))
                    continue
                self._wake.set()  # the link is back: decide the held report
            if not self._wake.wait(timeout_s) or self._stop.is_set():
                continue
            self._wake.clear()
            self._waiting_for_link.clear()
            self._decide_guarded()
            waiting_link = self._waiting_for_link.is_set()

    def _run(self) -> None:
        step_s = self.settings.decision_period_s
        next_at = time.monotonic()
        while not self._stop.is_set():
            self._decide_guarded()
            self._tick_live()
            next_at += step_s
            delay = next_at - time.monotonic()
            if delay < 0:  # fell behind (slow policy): skip the missed steps
                next_at = time.monotonic()
                delay = 0.0
            self._stop.wait(delay)

    # ------------------------------------------------------------------ persistence

    def _state_document(self) -> dict[str, Any]:
        """What the state file holds: the serving policy and the last decision."""
        with self._lock:
            decision, policy = self._decision, self._policy
        return {
            "format": STATE_FORMAT,
            "policy": policy.spec,
            "decision": asdict(decision) if decision else None,
            "control": self._control_document(),
            "envelopes": self._envelopes_document(),
        }

    def _persist(self) -> None:
        path = self.settings.state_file
        if path is None:
            return
        state = self._state_document()
        try:
            atomic_write_json(Path(path), state)
        except OSError as exc:
            self._count("state_write_errors")
            log.warning("cannot persist the service state to %s: %s", path, exc)

    def _restore(self) -> bool:
        """Load the persisted policy and show the persisted target (never streamed: see the
        module docstring). True when the state file exists, readable or not: this start is a
        restart, and a restart must not arm or move the vehicle by itself."""
        path = self.settings.state_file
        if path is None or not Path(path).is_file():
            return False
        try:
            state = json.loads(Path(path).read_text())
            if not isinstance(state, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as exc:
            log.warning("ignoring the state file %s: %s", path, exc)
            self._count("state_restore_errors")
            return True
        self._restore_policy(state.get("policy"), path)
        self._restore_targets(state, path)
        self._restore_control(state.get("control"), path)
        self._restore_envelopes(state.get("envelopes"), path)
        return True

    def _restore_control(self, saved: object, path: object) -> None:
        """Leave each vehicle that was not the service's when it stopped with whoever had it
        (a pilot, a failsafe, an operator): only an operator hands it back."""
        if saved is None:
            return
        if not isinstance(saved, dict):
            log.warning("ignoring the control in the state file %s: not an object", path)
            self._count("state_restore_errors")
            return
        for vid, entry in saved.items():
            holder = entry.get("holder") if isinstance(entry, dict) else None
            link = self.links.get(vid)
            if link is None or holder not in ("pilot", "autopilot", "operator"):
                log.warning("ignoring the control of %r in the state file %s", vid, path)
                self._count("state_restore_errors")
                continue
            reason = str(entry.get("reason", ""))[:300]
            link.release(f"{reason} (before the service restarted)", holder)
        self._persisted_control = self._control_document()

    def _restore_targets(self, state: dict[str, Any], path: object) -> None:
        """Show the persisted target as the current decision (source ``restored``)."""
        try:
            saved = state["decision"]
            if saved is None:
                return
            decision = restored_decision(saved)
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("ignoring the target in the state file %s: %s", path, exc)
            self._count("state_restore_errors")
            return
        with self._lock:
            self._decision = decision
        log.info(
            "restored the last target %s from %s (not streamed until a decision)",
            decision.target_m,
            path,
        )

    def _load_allowed(self, spec: str) -> Policy:
        """``spec`` loaded under the checks a client's choice gets: from ``policy_dirs`` only,
        within ``checkpoint_max_bytes``."""
        return load_policy(
            spec,
            self.world,
            allowed_dirs=self.settings.policy_dirs,
            max_bytes=self.settings.checkpoint_max_bytes,
        )

    def _restore_policy(self, spec: object, path: object) -> None:
        """Serve the persisted policy ``spec`` when it differs from the configured one and loads
        under the checks of ``PUT /v1/policy`` (from ``policy_dirs``, within
        ``checkpoint_max_bytes``); otherwise keep the configured one (and log why)."""
        if spec is None:
            return
        if not isinstance(spec, str) or not spec.strip():
            log.warning(
                "state file %s: policy %r is not a policy spec; keeping %s",
                path,
                spec,
                self._policy.spec,
            )
            self._count("policy_restore_errors")
            return
        if spec == self._policy.spec:
            return
        try:
            # The state file is only a file: its policy gets the same checks as PUT /v1/policy.
            policy = self._load_allowed(spec)
        except Exception as exc:  # InputError, or anything a broken checkpoint raises
            log.warning(
                "state file %s: cannot restore the policy %r (%s); keeping the configured %s",
                path,
                spec,
                exc,
                self._policy.spec,
            )
            self._count("policy_restore_errors")
            return
        with self._lock:
            self._policy = policy
            self.counters["policy_restored"] += 1
        log.info(
            "restored the persisted policy %s (configured: %s)",
            policy.name,
            self.settings.served_policy_spec(),
        )
