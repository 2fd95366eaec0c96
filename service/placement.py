"""The placement loop: user reports + vehicle telemetry -> policy -> geofenced setpoint.

:class:`PlacementService` is what ``tupa serve`` runs behind its HTTP side::

    service = PlacementService.from_settings(settings)   # opens the MAVLink link
    service.start()
    service.submit_report(report)      # from POST /v1/reports
    service.current_decision()         # GET /v1/setpoint
    service.stop()

Decisions: with ``decision_mode="paced"`` a background thread decides once every decision period
(the ``world``'s step, the paper's S, unless ``step_s`` is set) from the latest report; with
``"on-report"`` each accepted report triggers a decision at once. A decision needs a fresh report
(received at most ``report_max_age_s`` ago; otherwise the target is held) and the vehicle's
position (link up; a report that arrives while the link is down is kept, and the decision waits for
the link: the paced thread retries every step, and in ``on-report`` mode a watcher thread decides
as soon as the link is back, if the report is still fresh). Every kind of policy decides every
period while the vehicle flies: a discrete move applies to the zone the vehicle is in and replaces
the target (:func:`sim.world.move_target`, the environments' rule), so the service acts in the
world the policy was trained in. Targets go through the link, which clamps them to the geofence.

Reports are snapshots of all users; each replaces the previous one (users come and go). A report
whose ``timestamp`` is older than the last accepted one is ignored and counted; one stamped more
than ``report_max_future_s`` ahead of this machine's clock is refused and counted (accepted, it
would make every honest report after it "older").

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
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from policies.interface import Policy
from service.live_view import LiveFrame, LiveView, Moment
from service.policy_runtime import load_policy
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig, LinkState, VehicleLink
from sim.config import AreaConfig
from sim.files import atomic_write_json
from sim.observation import UserReports
from sim.world import World

STATE_FORMAT = "tupa-service-state/1"
log = logging.getLogger(__name__)

LINK_POLL_S = 0.05
"""How often the ``on-report`` watcher looks at the link while a report waits for it."""


@dataclass(frozen=True)
class Report:
    """One report of all users, as the network controller sends it (already validated)."""

    timestamp_s: float
    user_ids: tuple[str, ...]
    users: UserReports

    @classmethod
    def from_columns(
        cls, timestamp_s: float, user_ids: tuple[str, ...], columns: dict[str, np.ndarray]
    ) -> Report:
        """A report from one array per :class:`~sim.observation.UserReports` field (``x_m``,
        ``y_m``, ``offered_bps``, ``throughput_bps``, ``delay_s``, ``plr``), one entry a user."""
        return cls(timestamp_s, user_ids, UserReports(**columns))


@dataclass(frozen=True)
class Decision:
    """A target and where it came from."""

    target_m: tuple[float, float, float]
    source: str
    """``policy`` (decided from a report), ``restored`` (from the state file)."""
    policy: str
    decided_at: float
    """Unix time, seconds."""


def restored_decision(saved: Any) -> Decision:
    """A decision as the state file keeps it (``asdict``), shown again with source
    ``restored``; ValueError, KeyError or TypeError when it is not one."""
    target = tuple(float(v) for v in saved["target_m"])
    if len(target) != 3 or not all(math.isfinite(v) for v in target):
        raise ValueError(f"target_m: not three finite numbers: {target}")
    return Decision(target, "restored", str(saved.get("policy", "")), time.time())  # type: ignore[arg-type]


@dataclass(frozen=True)
class VehicleView:
    """One vehicle of the fleet as ``GET /v1/vehicles`` shows it."""

    id: str
    system_id: int | None
    """The system id the fleet file requires (None: any); the heard one is ``state.system_id``."""
    state: LinkState
    decision: Decision | None
    """The target it is flying to (None: not commanded now)."""
    problem: str | None
    """Why it is not commanded now (None: it is)."""


def _vehicle_known(state: LinkState) -> bool:
    """What a decision needs from the link: up, with the vehicle's position."""
    return link_problem(state) is None


def link_problem(state: LinkState) -> str | None:
    """Why the link does not let the vehicle be commanded now (None: it does)."""
    if state.link != "up":
        return f"mavlink link is {state.link}"
    if state.position_m is None:
        return "no vehicle position yet (telemetry not received)"
    return None


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
        self.links: dict[str, VehicleLink] = {"uav1": link}
        """Every vehicle's link by id (one here; a fleet's in :mod:`service.fleet_placement`)."""
        self.world = world if world is not None else settings.policy_world()
        """The world the policy decides in (area, network, utility, decision period)."""
        self._policy = policy
        self._lock = threading.Lock()  # the state below; held for microseconds
        self._deciding = threading.Lock()  # one decision at a time (see decide_once)
        self._swapping = threading.Lock()  # one policy load at a time (see swap_policy)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._waiting_for_link = threading.Event()  # a report was held because the link is down
        self._report: Report | None = None
        self._report_received: float | None = None  # monotonic
        self._last_timestamp_s = -math.inf
        self._decision: Decision | None = None
        self.counters: Counter[str] = Counter()
        self._takeoff_deferred = False
        self.live = LiveView(self.world.area, self.world.utility, settings.live_max_streams)
        """The operator view's track, utility history and frames (published each period)."""

    @property
    def area(self) -> AreaConfig:
        """The area the service places in (the world's)."""
        return self.world.area

    @property
    def submit_runs_policy(self) -> bool:
        """Whether :meth:`submit_report` runs the policy before it returns (``on-report``
        mode: milliseconds to a second for the oracle with hundreds of users), so an event
        loop should call it from a worker thread; otherwise it only stores the report."""
        return self.settings.decision_mode == "on-report"

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_settings(cls, settings: ServiceSettings) -> PlacementService:
        """Load the policy (``InputError`` if unusable) and open the link (retries on its own)."""
        from service.links import open_link

        if settings.is_fleet:
            from service.fleet_placement import FleetPlacementService

            return FleetPlacementService.from_settings(settings)
        world = settings.policy_world()
        # The operator's own choice: from any directory, within the size limit.
        policy = load_policy(settings.policy, world, max_bytes=settings.checkpoint_max_bytes)
        link_config = LinkConfig(
            url=settings.mavlink,
            area=world.area,
            frames=settings.frames(),
            setpoint_rate_hz=settings.setpoint_rate_hz,
            signing_key=settings.signing_key_bytes(),
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
        """The decision thread (``paced``) or the link watcher (``on-report``)."""
        if self.settings.decision_mode == "paced":
            target, name = self._run, "placement"
        else:
            target, name = self._decide_when_link_returns, "placement-link-watch"
        self._thread = threading.Thread(target=target, name=name, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self.live.hub.close_all()  # ends the open pages' streams
        self._waiting_for_link.set()  # wakes the on-report watcher
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self.close_links()

    def close_links(self) -> None:
        """Close the vehicle link(s) (safe to call twice)."""
        self.link.close()

    # ------------------------------------------------------------------ inputs

    def submit_report(self, report: Report) -> Decision | None:
        """Accept a report; decide at once in ``on-report`` mode. Returns the current decision.

        Raises :class:`OutOfOrderReportError` (and counts it) for a report older than the last one,
        and :class:`FutureReportError` (counted too) for one stamped more than
        ``report_max_future_s`` ahead of this machine's clock: accepted, it would make every
        honest report after it "older" until the clock caught up.
        """
        ahead_s = report.timestamp_s - time.time()
        if not ahead_s <= self.settings.report_max_future_s:  # also refuses a NaN
            self._count("reports_from_the_future")
            raise FutureReportError(
                f"timestamp: {ahead_s:.3g} s ahead of this service's clock, more than "
                f"report_max_future_s ({self.settings.report_max_future_s:g} s): a report from "
                "the future; check the controller's clock"
            )
        with self._lock:
            if report.timestamp_s < self._last_timestamp_s:
                self.counters["reports_out_of_order"] += 1
                raise OutOfOrderReportError(
                    f"timestamp: {report.timestamp_s} is older than the last accepted report "
                    f"({self._last_timestamp_s}); ignored"
                )
            self._last_timestamp_s = report.timestamp_s
            self._report = report
            self._report_received = time.monotonic()
            self.counters["reports_accepted"] += 1
        if self.settings.decision_mode == "on-report":
            self._decide_guarded()
        return self.current_decision()

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

    @property
    def is_fleet(self) -> bool:
        """Whether this service drives a fleet (:mod:`service.fleet_placement`)."""
        return False

    def vehicles(self) -> list[VehicleView]:
        """The one vehicle as a fleet of one (``GET /v1/vehicles``), id ``uav1``."""
        state = self.link.state()
        return [VehicleView("uav1", None, state, self.current_decision(), link_problem(state))]

    def _can_decide(self) -> bool:
        """Whether the link lets a decision be taken now (the ``on-report`` watcher asks)."""
        return _vehicle_known(self.link.state())

    def readiness(self) -> tuple[bool, list[str]]:
        """(ready, reasons it is not): a policy is loaded and the MAVLink link is up."""
        state = self.link.state()
        problem = link_problem(state)
        reasons = [problem] if problem else []
        if state.takeoff == "running":
            refusal = (
                f"; last refusal: {state.takeoff_last_refusal}"
                if state.takeoff_last_refusal
                else ""
            )
            reasons.append(
                f"take-off in progress: {state.takeoff_phase} "
                f"(attempt {state.takeoff_attempts}){refusal}"
            )
        elif state.takeoff.startswith("failed"):
            reasons.append(f"take-off {state.takeoff}")
        signing_failures = state.counters.get("signing_failures", 0)
        if signing_failures and state.link != "up":
            reasons.append(
                f"mavlink signing failed: {signing_failures} messages from the vehicle failed "
                "the signature check (check TUPA_MAVLINK_SIGNING_KEY against the vehicle's key); "
                "the vehicle is not commanded"
            )
        if state.counters.get("signed_vehicle_without_key", 0):
            reasons.append(
                "mavlink signing: the vehicle signs its messages but no signing key is "
                "configured (TUPA_MAVLINK_SIGNING_KEY); it will ignore our setpoints"
            )
        return not reasons, reasons

    def _count(self, name: str) -> None:
        """Count an event (counters are bumped from the decision thread and request threads)."""
        with self._lock:
            self.counters[name] += 1

    def snapshot_counters(self) -> dict[str, int]:
        with self._lock:
            return dict(self.counters)

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
        is counted and logged, and never stops the loop)."""
        try:
            self.live.record(self._moment())
        except Exception:
            self._count("live_errors")
            log.exception("operator view: could not record this period")

    # ------------------------------------------------------------------ deciding

    def decide_once(self) -> Decision | None:
        """One decision from the latest report (None when held: stale report, no link).

        Decisions are taken one at a time: in ``on-report`` mode concurrent reports and the link
        watcher may ask together, and the one that reads the latest report must set the target
        last (unserialised, a slow decision on an older report could overwrite a newer one)."""
        with self._deciding:
            return self._decide_latest()

    def _fresh_report(self) -> tuple[Report, Policy] | None:
        """The latest report and the serving policy, if a report is fresh enough to decide on
        (a stale one is counted: the target is held)."""
        with self._lock:
            report, received, policy = self._report, self._report_received, self._policy
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
        started = time.perf_counter()
        if self._takeoff_deferred:  # the first decision after a restart (see start())
            self._takeoff_deferred = False
            self.link.arm_and_takeoff(timeout_s=self.settings.takeoff_timeout_s)
        try:
            target = policy.decide(report.users, vehicle)
            clamped = self.link.set_target(tuple(float(v) for v in target))
        except ValueError as exc:  # a non-finite target: refused by the geofence, target held
            self._count("decisions_rejected")
            log.warning("decision rejected: %s", exc)
            return None
        decision = Decision(clamped, "policy", policy.name, time.time())
        with self._lock:
            self._decision = decision
            self.counters["decisions"] += 1
            self.counters["decision_time_us_total"] += int((time.perf_counter() - started) * 1e6)
        self._persist()
        return decision

    def _decide_guarded(self) -> None:
        """:meth:`decide_once`, where a policy bug holds the target instead of failing the
        caller (the paced loop, or the report's HTTP request): counted and logged."""
        try:
            self.decide_once()
        except Exception:
            self._count("decision_errors")
            log.exception("decision failed; holding the current target")

    def _decide_when_link_returns(self) -> None:
        """``on-report`` mode: a report held because the link was down is decided once the link
        is up again (if still fresh: :meth:`decide_once` holds a stale one), not only when the
        next report happens to arrive. It also gives the operator view its period."""
        period_s = self.settings.decision_period_s
        next_tick = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_tick:  # the operator view's period (decisions come with reports)
                self._tick_live()
                next_tick += period_s
                if next_tick <= now:  # fell behind: the next period from now
                    next_tick = now + period_s
            if not self._waiting_for_link.wait(min(0.5, max(0.0, next_tick - now))):
                continue
            if self._can_decide() and not self._stop.is_set():
                self._waiting_for_link.clear()
                self._decide_guarded()
            else:
                self._stop.wait(LINK_POLL_S)

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
        return True

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
            "restored the persisted policy %s (configured: %s)", policy.name, self.settings.policy
        )
