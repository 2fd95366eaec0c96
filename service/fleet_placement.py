"""The placement loop for a fleet: one report of all users, K vehicles, K targets.

:class:`FleetPlacementService` is what ``tupa serve --fleet-file FILE`` (or several
``--mavlink``) runs. It is :class:`~service.placement.PlacementService` (the same report intake,
decision modes, threads, counters and policy swaps) with K links instead of one::

    service = FleetPlacementService.from_settings(settings)   # opens one link per vehicle
    service.start()
    service.submit_report(report)       # POST /v1/reports: all users, as for one vehicle
    service.vehicles()                  # GET /v1/vehicles: each link's state and target
    service.stop()

A decision, once per period (or for the latest report in ``on-report`` mode, coalesced as for
one vehicle: :mod:`service.placement`):

1. the vehicles that may be commanded: link up, position known, and the system id the fleet
   file names (if any) and no other vehicle's — two connections that reach one vehicle would
   command it twice, so the later one is not commanded (counted: ``duplicate_system_id``);
2. the fleet policy places that many targets for *all* users
   (:class:`policies.fleet_policy.FleetPolicy`), so when a vehicle is lost the others re-place
   to cover its users at the next decision — the **degraded mode** — and when it returns it is
   commanded again and the fleet re-places with it;
3. each target goes to the vehicle with the least total flight
   (:func:`~sim.fleet_targets.assign_targets`), then the guard separates the targets from
   one another and from where every vehicle that is not commanded was last seen, inside the
   volume (:func:`~sim.fleet_targets.guard_targets`); a set that fails the final check is
   not streamed at all (counted: ``decisions_rejected``); a vehicle whose flight to its target
   would come closer than the separation to another's holds where it is for this decision
   (lower indices fly first; :func:`~sim.fleet_targets.hold_crossing_paths`, the world's rule,
   counted: ``path_holds``), unless holding would leave two targets under the separation
   (two vehicles that already met that close): then nothing is held (``path_holds_skipped``);
4. each commanded vehicle's link streams its target (clamped to its own geofence, a no-op
   after the guard); a vehicle that is not commanded has its stream cleared, so that when its
   link returns it flies nothing stale until the next decision includes it.

The operator view (``GET /v1/live``, the page) shows every vehicle with its own track and
target.

Restarts, with a ``state_file``: as for one vehicle (:mod:`service.placement`), the serving
policy and every commanded vehicle's last target are written after each decision and swap. On
start the policy is restored under the checks of a swap, and each vehicle of the fleet file
that has a saved target shows it (source ``restored``, with why it is not commanded) but is
*not* streamed; ``arm_and_takeoff`` waits for the first decision from a fresh report, which
commands the fleet afresh. A saved vehicle the fleet file no longer names is ignored and
counted (``state_restore_errors``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from policies.fleet_policy import DEFAULT_FLEET_POLICY, FleetPolicy, resolve_fleet_policy
from service.decisions import Decision, ReportReceipt, VehicleView, restored_decision
from service.fleet_spec import FleetSpec
from service.live_view import Moment
from service.placement import STATE_FORMAT, PlacementService, link_problem, vehicle_notes
from service.policy_runtime import synthetic_report
from service.settings import ServiceSettings
from service.vehicle_link import LinkConfig, LinkState, VehicleLink
from sim.errors import InputError
from sim.fleet_targets import (
    assign_targets,
    guard_targets,
    hold_crossing_paths,
)
from sim.world import World

log = logging.getLogger(__name__)

LEGAL_ROUNDS = 3
"""How many times a fleet's targets are made legal in each vehicle's envelope and separated
again before they are streamed (each link moves an illegal target itself otherwise)."""
RESTORED = "restored from the state file: not streamed until the next decision (a fresh report)"


class FleetPlacementService(PlacementService):
    """Owns K links, the fleet policy, the latest report and each vehicle's current target."""

    def __init__(
        self,
        settings: ServiceSettings,
        links: dict[str, VehicleLink],
        policy: FleetPolicy,
        fleet: FleetSpec,
        world: World | None = None,
    ) -> None:
        if list(links) != list(fleet.ids):
            raise ValueError(f"links: must be the fleet's vehicles {fleet.ids}, got {list(links)}")
        super().__init__(settings, links[fleet.ids[0]], policy, world)  # type: ignore[arg-type]
        self.links = dict(links)
        self.fleet = fleet
        self._decisions: dict[str, Decision] = {}

    @classmethod
    def from_settings(cls, settings: ServiceSettings) -> FleetPlacementService:
        """Read the fleet, load and check the policy, open one link per vehicle (InputError
        naming the field for a bad fleet or policy)."""
        from service.links import open_link

        fleet = settings.fleet_spec()
        world = settings.policy_world()
        # The single vehicle's default policy cannot fly a fleet: a fleet's default is its own.
        named = "policy" in settings.model_fields_set
        spec = settings.policy if named else DEFAULT_FLEET_POLICY
        policy = load_fleet_policy(
            spec, world, fleet.separation_m, max_bytes=settings.checkpoint_max_bytes
        )
        links: dict[str, VehicleLink] = {}
        envelopes = {
            v.id: v.envelope(world.area, f"vehicles[{i}].envelope")
            for i, v in enumerate(fleet.vehicles)
        }
        for vehicle in fleet.vehicles:
            config = LinkConfig(
                url=vehicle.mavlink,
                area=world.area,
                envelope=envelopes[vehicle.id],
                frames=vehicle.frames,
                setpoint_rate_hz=settings.setpoint_rate_hz,
                signing_key=settings.signing_key_bytes(),
                battery=settings.battery(),
                autopilot_fence=settings.autopilot_fence,
                fence_action=settings.fence_action,
            )
            try:
                links[vehicle.id] = open_link(settings.mavlink_backend, config)
            except ValueError as exc:
                for link in links.values():
                    link.close()
                raise InputError(f"vehicles: {vehicle.id}: {exc}") from None
        return cls(settings, links, policy, fleet, world)

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> FleetPlacementService:
        for link in self.links.values():
            link.start()
        restarted = self._restore()
        if self.settings.arm_and_takeoff:
            if restarted:
                # A restart: arm and take off only once a fresh report leads to a decision.
                self._takeoff_deferred = True
                log.info("restarted (state file found): arm-and-takeoff waits for a decision")
            else:
                self._arm_and_take_off()
        self._start_loop()
        return self

    def _arm_and_take_off(self) -> None:
        for link in self.links.values():
            link.arm_and_takeoff(timeout_s=self.settings.takeoff_timeout_s)

    def close_links(self) -> None:
        for link in self.links.values():
            link.close()

    # ------------------------------------------------------------------ outputs

    def vehicles(self) -> list[VehicleView]:
        """Every vehicle, in the fleet's order: state, current target, why not commanded."""
        decisions = self.decisions()
        states = {vid: link.state() for vid, link in self.links.items()}
        _, problems = self._commandable(states)
        views = []
        for vehicle in self.fleet.vehicles:
            vid = vehicle.id
            problem = problems.get(vid)
            decision = decisions.get(vid)
            if problem is None and decision is None:
                problem = "not commanded yet: waiting for the next decision (a fresh report)"
            elif decision is not None and decision.source == "restored":
                problem = problem or RESTORED
            elif problem is not None:
                decision = None
            views.append(VehicleView(vid, vehicle.system_id, states[vid], decision, problem))
        return views

    def decisions(self) -> dict[str, Decision]:
        """The target of each commanded vehicle, by id."""
        with self._lock:
            return dict(self._decisions)

    def receipt_decisions(self, receipt: ReportReceipt) -> dict[str, Decision]:
        """The fleet's targets now (a receipt carries one decision; a fleet's is K)."""
        return self.decisions()

    @property
    def separation_m(self) -> float | None:
        return self.fleet.separation_m

    def current_decision(self) -> Decision | None:
        """The latest decision's first target (the fleet's targets: :meth:`decisions`)."""
        decisions = self.decisions()
        return next(iter(decisions.values()), None)

    def readiness(self) -> tuple[bool, list[str]]:
        """Ready while at least one vehicle can be commanded (degraded mode serves the rest);
        the reasons name every vehicle that cannot, ready or not."""
        states = {vid: link.state() for vid, link in self.links.items()}
        flying, problems = self._commandable(states)
        reasons = [f"{vid}: {problem}" for vid, problem in problems.items()]
        reasons += [
            f"{vid}: {note}" for vid, state in states.items() for note in vehicle_notes(state)
        ]
        return bool(flying), reasons

    def _can_decide(self) -> bool:
        flying, _ = self._commandable({vid: link.state() for vid, link in self.links.items()})
        return bool(flying)

    def _moment(self) -> Moment:
        """The operator view's moment: every vehicle, with its current target."""
        moment = super()._moment()
        fleet = tuple((v.id, v.state, v.decision) for v in self.vehicles())
        return replace(moment, link=fleet[0][1], decision=fleet[0][2], fleet=fleet)

    # ------------------------------------------------------------------ persistence

    def _state_document(self) -> dict[str, Any]:
        """The serving policy and each commanded vehicle's last decision, by id."""
        with self._lock:
            decisions, policy = dict(self._decisions), self._policy
        return {
            "format": STATE_FORMAT,
            "policy": policy.spec,
            "decisions": {vid: asdict(d) for vid, d in decisions.items()},
            "control": self._control_document(),
            "envelopes": self._envelopes_document(),
        }

    def _restore_targets(self, state: dict[str, Any], path: object) -> None:
        """Show each saved vehicle's target (source ``restored``, never streamed)."""
        saved = state.get("decisions")
        if saved is None:
            if state.get("decision") is not None:
                log.warning(
                    "ignoring the state file %s's target: one vehicle's, not a fleet's", path
                )
                self._count("state_restore_errors")
            return
        if not isinstance(saved, dict):
            log.warning("ignoring the targets in the state file %s: not an object by vehicle", path)
            self._count("state_restore_errors")
            return
        restored = {}
        for vid, entry in saved.items():
            if vid not in self.links:
                log.warning("state file %s: %r is not in the fleet file; ignored", path, vid)
                self._count("state_restore_errors")
                continue
            try:
                restored[vid] = restored_decision(entry)
            except (ValueError, KeyError, TypeError) as exc:
                log.warning("ignoring %s's target in the state file %s: %s", vid, path, exc)
                self._count("state_restore_errors")
        with self._lock:
            self._decisions = restored
        if restored:
            log.info(
                "restored the last targets of %s from %s (not streamed until a decision)",
                ", ".join(restored),
                path,
            )

    # ------------------------------------------------------------------ deciding

    def _commandable(self, states: dict[str, LinkState]) -> tuple[list[str], dict[str, str]]:
        """(the ids that may be commanded now, in fleet order; why each other one may not)."""
        flying: list[str] = []
        problems: dict[str, str] = {}
        owner: dict[int, str] = {}
        for vehicle in self.fleet.vehicles:
            vid, state = vehicle.id, states[vehicle.id]
            heard = state.system_id
            if problem := link_problem(state):
                problems[vid] = problem
            elif vehicle.system_id is not None and heard != vehicle.system_id:
                problems[vid] = (
                    f"system id {heard} heard, the fleet file says {vehicle.system_id}: "
                    "not commanded"
                )
            elif heard is not None and heard in owner:
                problems[vid] = (
                    f"system id {heard} is also {owner[heard]}'s: two connections reach one "
                    "vehicle; not commanded"
                )
            else:
                flying.append(vid)
            if heard is not None and state.link == "up":
                owner.setdefault(heard, vid)
        return flying, problems

    def _decide_latest(self) -> Decision | None:
        fresh = self._fresh_report()
        if fresh is None:
            return None
        report, policy = fresh
        states = {vid: link.state() for vid, link in self.links.items()}
        flying, problems = self._commandable(states)
        if any("also" in p for p in problems.values()):
            self._count("duplicate_system_id")
        for vid in problems:  # nothing stale is streamed when its link returns
            if states[vid].target_m is not None:
                self.links[vid].clear_target()
        with self._lock:
            for vid in problems:
                self._decisions.pop(vid, None)
        if not flying:
            self._count("decisions_waiting_link")
            self._waiting_for_link.set()
            return None
        if problems:
            self._count("decisions_degraded")
        if self._takeoff_deferred:  # the first decision after a restart (see start())
            self._takeoff_deferred = False
            self._arm_and_take_off()
        positions = np.array([states[vid].position_m for vid in flying], dtype=float)
        obstacles = np.array(
            [states[vid].position_m for vid in problems if states[vid].position_m is not None],
            dtype=float,
        ).reshape(-1, 3)
        started = time.perf_counter()
        try:
            wanted = np.asarray(policy.decide_fleet(report.users, positions), dtype=float)  # type: ignore[attr-defined]
            if wanted.shape != positions.shape:
                raise ValueError(f"the policy gave {wanted.shape} targets for {len(flying)}")
            targets = guard_targets(
                assign_targets(positions, wanted), obstacles, self.fleet.separation_m, self.area
            )
            targets = self._legal_targets(flying, targets, obstacles)
            targets = self._hold_crossing_paths(flying, positions, targets, obstacles)
        except ValueError as exc:  # refused by the guard: nothing is streamed
            self._count("decisions_rejected")
            log.warning("fleet decision rejected: %s", exc)
            return None
        finally:
            self._record_decision_time(time.perf_counter() - started)
        decided_at = time.time()
        decisions = {}
        for vid, target in zip(flying, targets, strict=True):
            clamped = self.links[vid].set_target(tuple(float(v) for v in target))
            decisions[vid] = Decision(clamped, "policy", policy.name, decided_at)
        with self._lock:
            self._decisions = decisions
            self.counters["decisions"] += 1
        self._persist()
        return next(iter(decisions.values()))

    def _legal_targets(
        self, flying: list[str], targets: np.ndarray, obstacles: np.ndarray
    ) -> np.ndarray:
        """``targets`` each moved into its vehicle's envelope as its link would move it, and
        separated again where that brought two too close (at most :data:`LEGAL_ROUNDS` rounds;
        a target with no legal point near stays, and its link refuses it)."""
        for _ in range(LEGAL_ROUNDS):
            legal = np.array(
                [
                    self.links[vid].legal_target(tuple(t)) or tuple(t)
                    for vid, t in zip(flying, targets.tolist(), strict=True)
                ],
                dtype=float,
            )
            if np.allclose(legal, targets, rtol=0.0, atol=1e-9):
                return legal
            targets = guard_targets(legal, obstacles, self.fleet.separation_m, self.area)
        return targets

    def _hold_crossing_paths(
        self, flying: list[str], positions: np.ndarray, targets: np.ndarray, obstacles: np.ndarray
    ) -> np.ndarray:
        """``targets`` with each vehicle whose flight there would come too close to another's
        held where it is for this decision, or sent round a vehicle hovering in its way, the
        world's rule (:func:`sim.fleet_targets.hold_crossing_paths`; counted: ``path_holds``,
        ``path_detours``). When holding
        would leave two targets under the separation (two vehicles that already met that close,
        holding each other in place), nothing is held: the guard's separated targets go out as
        they are, and that is counted (``path_holds_skipped``)."""
        envelopes = [self.links[vid].routing_envelope for vid in flying]
        holds = hold_crossing_paths(
            envelopes, positions, targets, self.world.flight, self.fleet.separation_m, self.area,
            obstacles,
        )  # fmt: skip
        if holds.skipped:
            self._count("path_holds_skipped")
        for k, vid in enumerate(flying):
            if holds.held[k]:
                self._count("path_holds")
                log.info("%s holds where it is: its flight would cross another's", vid)
            elif holds.detoured[k]:
                self._count("path_detours")
                log.info("%s goes round a vehicle hovering in its way", vid)
        return holds.targets_m

    def _load_allowed(self, spec: str) -> FleetPolicy:  # type: ignore[override]
        return load_fleet_policy(
            spec,
            self.world,
            self.fleet.separation_m,
            allowed_dirs=self.settings.policy_dirs,
            max_bytes=self.settings.checkpoint_max_bytes,
        )


def load_fleet_policy(
    spec: str,
    world: World,
    separation_m: float,
    allowed_dirs: Sequence[Path] | None = None,
    max_bytes: int | None = None,
) -> FleetPolicy:
    """The fleet policy ``spec`` (a name, or a fleet checkpoint: only from ``allowed_dirs`` when
    given, within ``max_bytes``), checked by one decision on a synthetic report for two
    vehicles (InputError naming ``policy`` otherwise)."""
    policy = resolve_fleet_policy(spec, world, separation_m, allowed_dirs, max_bytes)
    try:
        targets = policy.decide_fleet(synthetic_report(world.area), np.zeros((2, 3)))
    except InputError:
        raise
    except Exception as exc:
        log.warning("fleet policy %r fails on a test decision: %s", spec, exc)
        raise InputError("policy: fails on a test decision (see the service log)") from None
    if targets.shape != (2, 3) or not np.all(np.isfinite(targets)):
        raise InputError("policy: gives unusable targets on a test decision")
    policy.reset()  # the test decision's users are nobody's: their APs are forgotten
    return policy
