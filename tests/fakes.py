"""In-memory stand-ins for the service's collaborators, for tests of the logic above them.

:class:`FakeLink` is a real :class:`~service.vehicle_link.VehicleLink` whose vehicle lives in
memory: no autopilot process, no sockets, no MAVLink. It keeps the contract the real links keep
(``tests/service/test_link_contract.py`` runs its no-vehicle part on it): targets are moved into
the envelope and flown to along its routes the same way (:class:`service.routing.LinkRoute`),
NaN targets are refused, a target streams
only while the link is up and no take-off is running, ``arm_and_takeoff`` returns a Future that
completes once airborne. The vehicle flies in a straight line towards the route's current
setpoint at ``speed_mps`` and climbs at ``climb_mps``, as time passes: simulated time through
:meth:`FakeLink.advance` (deterministic; the default), or wall-clock time on a thread of its own
with ``realtime=True``. :meth:`FakeLink.set_link` makes the link drop and come back.

    link = FakeLink(position_m=(250.0, 250.0, 50.0))      # up, airborne, in OFFBOARD when told
    service = PlacementService(settings, link, policy).start()
    service.submit_report(report)
    link.advance(2.0)                                     # the vehicle flies for 2 s
"""

from __future__ import annotations

import math
import threading
import time
from collections import Counter
from collections.abc import Sequence
from concurrent.futures import Future
from typing import Self

from service.control import Control, ControlHolder
from service.routing import LinkRoute
from service.vehicle_link import (
    TAKEOFF_TIMEOUT_S,
    ControlRefused,
    LinkConfig,
    LinkHealth,
    LinkState,
    VehicleLink,
)
from sim.envelope import Envelope

Vec3 = tuple[float, float, float]


class FakeLink(VehicleLink):
    """A vehicle link whose vehicle is simulated in memory (see the module docstring)."""

    def __init__(
        self,
        config: LinkConfig | None = None,
        *,
        position_m: Sequence[float] = (0.0, 0.0, 0.0),
        airborne: bool | None = None,
        up: bool = True,
        speed_mps: float = 10.0,
        climb_mps: float = 3.0,
        realtime: bool = False,
        tick_s: float = 0.02,
        system_id: int = 1,
    ) -> None:
        """``position_m``: where the vehicle is (area frame); ``airborne`` (default: above 1 m)
        says whether it flies (armed) or stands on the ground (disarmed, deaf to setpoints until
        :meth:`arm_and_takeoff`); ``up``: the link is up from the start, else ``connecting``."""
        self.config = config if config is not None else LinkConfig("fake:")
        self.system_id = system_id
        """The MAVLink system id its HEARTBEATs would carry."""
        x_m, y_m, z_m = (float(v) for v in position_m)
        self.speed_mps = speed_mps
        self.climb_mps = climb_mps
        self.realtime = realtime
        self.tick_s = tick_s
        self.counters: Counter[str] = Counter(
            dict.fromkeys(
                ("setpoints_sent", "geofence_clamps", "reconnects", "connect_failures"), 0
            )
        )
        self.clock_s = 0.0
        """Simulated seconds since the link was made (advanced by :meth:`advance`)."""
        self.arms = 0
        """How many times the vehicle was armed."""
        self.targets: list[Vec3] = []
        """Every target streamed, geofenced, in order."""
        self.started = False
        self.closed = False
        self._cond = threading.Condition()
        self._position: Vec3 = (x_m, y_m, z_m)
        self._airborne = z_m > 1.0 if airborne is None else airborne
        self._health: LinkHealth = "up" if up else "connecting"
        self._heard_at: float | None = time.monotonic() if up else None
        self._target: Vec3 | None = None
        self._routing = LinkRoute(self.config.envelope or Envelope.for_area(self.config.area))
        self._takeoff = "airborne" if self._airborne else "idle"
        self._takeoff_z_m = 0.0
        self._takeoff_deadline_s = math.inf
        self._takeoff_attempts = 0
        self._takeoff_armed = False
        self._takeoff_future: Future[None] | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._control = Control("service", "waiting for the vehicle", time.monotonic())

    # ------------------------------------------------------------------ VehicleLink

    def start(self) -> Self:
        self.started = True
        if self.realtime and self._thread is None:
            self._thread = threading.Thread(target=self._run, name="fake-link", daemon=True)
            self._thread.start()
        return self

    def close(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self.closed = True

    def state(self) -> LinkState:
        with self._cond:
            heard = self._heard_at is not None
            if self._health == "up":
                self._heard_at = time.monotonic()
            streaming = self._streaming()
            return LinkState(
                link=self._health,
                flavour="px4" if heard else None,
                mode=("OFFBOARD" if streaming and self._airborne else "AUTO.LOITER")
                if heard
                else None,
                armed=self._airborne or self._takeoff_armed,
                position_m=self._position if heard else None,
                relative_alt_m=self._position[2] - self.config.frames.area_origin_down_m
                if heard
                else None,
                heartbeat_age_s=time.monotonic() - self._heard_at if self._heard_at else None,
                target_m=self._target,
                streaming=streaming,
                takeoff=self._takeoff,
                counters={**self.counters, **self._routing.counters},
                takeoff_phase="climbing" if self._takeoff == "running" else None,
                takeoff_attempts=self._takeoff_attempts,
                system_id=self.system_id if heard else None,
                control=self._control.holder,
                control_reason=self._control.reason,
                control_age_s=time.monotonic() - self._control.since_s,
                route=self._routing.view(),
            )

    def set_target(self, target_m: Sequence[float]) -> tuple[float, float, float]:
        with self._cond:
            legal, _ = self._routing.set_target(target_m, self.counters)
            self._target = legal
            self.targets.append(legal)
        return legal

    @property
    def envelope(self) -> Envelope:
        with self._cond:
            return self._routing.envelope

    @property
    def routing_envelope(self) -> Envelope:
        return self.envelope

    def legal_target(self, target_m: Sequence[float]) -> tuple[float, float, float] | None:
        with self._cond:
            return self._routing.legal(target_m)

    def set_envelope(self, envelope: Envelope) -> None:
        with self._cond:
            self._routing.set_envelope(envelope)

    def clear_target(self) -> None:
        with self._cond:
            self._target = None
            self._routing.clear()

    def hand_back(self, reason: str = "handed back by an operator") -> None:
        with self._cond:
            if self._health != "up":
                raise ControlRefused("the vehicle's link is not up")
            self._control = Control("service", reason, time.monotonic())

    def release(
        self, reason: str = "released by an operator", holder: ControlHolder = "operator"
    ) -> None:
        with self._cond:
            self._control = Control(holder, reason, time.monotonic())

    def vehicle_leaves(
        self, holder: ControlHolder = "pilot", reason: str = "left OFFBOARD"
    ) -> None:
        """The vehicle leaves the service's hands (a pilot's switch, a failsafe): nothing streams
        until :meth:`hand_back`."""
        with self._cond:
            self._control = Control(holder, reason, time.monotonic())

    def arm_and_takeoff(
        self, z_m: float | None = None, timeout_s: float = TAKEOFF_TIMEOUT_S
    ) -> Future[None]:
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise ValueError(f"timeout_s: must be a positive number, got {timeout_s!r}")
        area = self.config.area
        z_m = area.z_min_m if z_m is None else min(max(float(z_m), area.z_min_m), area.z_max_m)
        future: Future[None] = Future()
        with self._cond:
            self._takeoff_attempts = 1
            if self._airborne:  # taken over as it flies, without arming
                self._takeoff = "airborne"
                future.set_result(None)
                return future
            self._takeoff = "running"
            self._takeoff_armed = False
            self._takeoff_z_m = z_m
            self._takeoff_deadline_s = self.clock_s + timeout_s
            self._takeoff_future = future
        self._advance_takeoff()
        return future

    # ------------------------------------------------------------------ simulation

    def advance(self, dt_s: float) -> None:
        """Let ``dt_s`` simulated seconds pass: the vehicle climbs (take-off) or flies towards the
        streamed target; a take-off past its timeout fails."""
        with self._cond:
            self.clock_s += dt_s
            x_m, y_m, z_m = self._position
            if self._takeoff == "running" and self._takeoff_armed:
                self._position = (x_m, y_m, min(z_m + self.climb_mps * dt_s, self._takeoff_z_m))
            elif self._streaming() and self._airborne:
                reach_m = self.speed_mps * dt_s
                for _ in range(16):  # along the route's legs, as far as dt_s reaches
                    setpoint = self._routing.setpoint(self._position)
                    if setpoint is None or reach_m <= 0:
                        break
                    reach_m -= self._fly_towards(setpoint, reach_m)
                    if self._routing.setpoint(self._position) == setpoint:
                        break
                self.counters["setpoints_sent"] += 1
        self._advance_takeoff()

    def _fly_towards(self, setpoint: Vec3, reach_m: float) -> float:
        """Move straight towards ``setpoint`` by at most ``reach_m`` (under ``self._cond``);
        returns the distance flown."""
        distance_m = math.dist(self._position, setpoint)
        step_m = min(distance_m, reach_m)
        if distance_m > 0:
            self._position = tuple(  # type: ignore[assignment]
                p + (t - p) * step_m / distance_m
                for p, t in zip(self._position, setpoint, strict=True)
            )
        return step_m

    def place_at(self, position_m: Sequence[float]) -> None:
        """The vehicle is at ``position_m`` (area frame) now: a replay of recorded telemetry."""
        with self._cond:
            self._position = tuple(float(v) for v in position_m)  # type: ignore[assignment]

    def set_link(self, up: bool) -> None:
        """The link comes up (again) or is lost (no HEARTBEAT: ``link_lost``)."""
        with self._cond:
            if up and self._health != "up":
                if self._health == "link_lost":
                    self.counters["reconnects"] += 1
                self._health = "up"
                self._heard_at = time.monotonic()
            elif not up and self._health == "up":
                self._health = "link_lost"
        self._advance_takeoff()

    def _streaming(self) -> bool:
        return (
            self._health == "up"
            and self._target is not None
            and self._takeoff != "running"
            and self._control.holder == "service"
        )

    def _advance_takeoff(self) -> None:
        """Arm once the vehicle is heard; complete the take-off once at its altitude."""
        with self._cond:
            future = self._takeoff_future
            if self._takeoff != "running" or future is None:
                return
            if self._health == "up" and not self._takeoff_armed:
                self.arms += 1
                self._takeoff_armed = True
            done: BaseException | None = None
            if self._takeoff_armed and self._position[2] >= self._takeoff_z_m:
                self._takeoff, self._airborne = "airborne", True
            elif self.clock_s >= self._takeoff_deadline_s:
                done = TimeoutError("not airborne before the take-off timeout")
                self._takeoff = f"failed: {done}"
                self._takeoff_armed = False
            else:
                return
            self._takeoff_future = None
        if done is None:
            future.set_result(None)
        else:
            future.set_exception(done)

    def _run(self) -> None:
        last = time.monotonic()
        while not self._stop.wait(self.tick_s):
            now = time.monotonic()
            self.advance(now - last)
            last = now
