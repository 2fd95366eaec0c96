"""The vehicle link, whatever speaks MAVLink for it: its interface, its configuration and state,
and everything the backends share.

What this module owns:

* :class:`VehicleLink`, the one interface the service drives (``start``, ``close``, ``state``,
  ``set_target``, ``clear_target``, ``arm_and_takeoff``): an abstract base class, so that "go to
  definition" finds the contract and ``isinstance`` checks it. Both backends and the tests'
  in-memory fake (``tests/fakes.py``) derive from it; :mod:`service.links` picks a backend.
* :class:`LinkConfig` (what a link needs) and :class:`LinkState` (the snapshot it gives).
* :class:`VehicleLinkBase`, the machinery both MAVLink backends share, so that each backend
  module keeps only its I/O: the I/O thread's loop (open the transport, back off and reopen it
  when it dies or the vehicle stays silent), heartbeat supervision (decoding the vehicle's
  HEARTBEAT, ``link_lost`` after ``heartbeat_timeout_s`` without one), setpoint scheduling (the
  current target at ``setpoint_rate_hz``, a new one at once but never closer than
  ``setpoint_min_gap_s`` to the previous setpoint), the guided-mode requests (GUIDED at once on
  ArduPilot, OFFBOARD on PX4 once the stream has run ``px4_stream_lead_s``, during
  ``mode_request_window_s`` after a new target only, so that a pilot who took over keeps the
  vehicle), the envelope (:mod:`service.routing`: legal targets and the routes to them), the
  vehicle's STATUSTEXTs. Two mixins of it hold the rest, each in its own module: the
  arm-and-takeoff sequence the real autopilots need (:mod:`service.link_takeoff`;
  :meth:`~service.link_takeoff.TakeoffMixin.arm_and_takeoff` has its steps), and the speed
  limit, the autopilot's fence and the battery reserve (:mod:`service.link_safety`).

A backend (:mod:`service.mavlink_link` on pymavlink, :mod:`service.mavsdk_link` on MAVSDK)
implements the hooks listed on :class:`VehicleLinkBase`: open, poll and close its transport,
send one setpoint, ask for the guided mode, send a command and wait for its answer; it passes
what the vehicle says to ``_note_heartbeat`` and ``_note_status_text`` and keeps the position
fields up to date under ``self._cond``.
"""

from __future__ import annotations

import hashlib
import logging
import math
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter, deque
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Literal, Self

from service import control as vehicle_control
from service.battery import BatteryConfig, DrainEstimate
from service.control import Control, ControlHolder
from service.fence import FenceError, FencePlan, fence_compatible
from service.frames import FrameConfig, GeoPoint, area_to_ned, ned_to_area
from service.link_safety import SPEED_GIVE_BACK_S, SafetyMixin
from service.link_takeoff import (
    POSITION_FRESH_S,
    TAKEOFF_TIMEOUT_S,
    TakeoffMixin,
)
from service.modes import GUIDED_MODE_NAME, Flavour, flavour_of, mode_name
from service.routing import LinkRoute, RouteView, background_planner
from service.vehicle_mavlink import mavlink
from sim.config import AreaConfig
from sim.envelope import Envelope, area_envelope
from sim.envelope.route import BRAKE_MPS2

log = logging.getLogger(__name__)

LinkHealth = Literal["connecting", "up", "link_lost"]

STATUS_TEXTS_KEPT = 8
"""How many of the vehicle's latest STATUSTEXTs :meth:`VehicleLinkBase.state` shows."""
IDLE_WAIT_S = 0.05
"""The I/O loop's longest wait for input, and its pace while no vehicle answers."""
HEARTBEAT_PERIOD_S = 1.0
"""Our own HEARTBEAT's period (where the backend sends it)."""
PLAN_WAIT_S = 0.05
"""How long the I/O loop waits for a route it just asked for before it streams what goes on
meanwhile (:mod:`service.routing`): most plans take milliseconds; a slow one never holds the
loop longer (PX4 gives up OFFBOARD after 1 s without a setpoint)."""
TELEMETRY_REQUEST_PERIOD_S = 2.0
"""How often ``_request_telemetry`` is called while the vehicle is up."""
BATTERY_CHECK_PERIOD_S = 1.0
"""How often the battery reserve is checked (:mod:`service.battery`)."""


def signing_key_from_passphrase(passphrase: str) -> bytes:
    """A 32-byte MAVLink 2 signing key from a passphrase (SHA-256, as MAVProxy does)."""
    return hashlib.sha256(passphrase.encode()).digest()


class ControlRefused(Exception):  # noqa: N818 (a refusal, not a programming error)
    """The vehicle cannot be handed back to the service now (the message says why)."""


@dataclass(frozen=True)
class LinkConfig:
    """Everything a vehicle link needs; only ``url`` has no default."""

    url: str
    """A pymavlink connection string: ``tcp:HOST:PORT``, ``udpin:HOST:PORT``, ``udpout:...``."""
    area: AreaConfig = AreaConfig()
    """The area volume (the envelope's default)."""
    envelope: Envelope | None = None
    """Where the vehicle may fly and how it gets there (:mod:`sim.envelope`); None: the area's
    box. Targets are moved to the nearest legal point and flown to along a legal route
    (:mod:`service.routing`)."""
    frames: FrameConfig = FrameConfig()  # noqa: RUF009 (frozen, so sharing it is safe)
    """Where the area frame sits in the vehicle's local NED frame."""
    setpoint_rate_hz: float = 10.0
    """How often the current target is sent (PX4 needs more than 2 Hz)."""
    setpoint_min_gap_s: float = 0.02
    """A new target is sent at once, but never sooner than this after the previous setpoint."""
    telemetry_rate_hz: float = 10.0
    """Rate asked for GLOBAL_POSITION_INT and LOCAL_POSITION_NED."""
    brake_mps2: float = BRAKE_MPS2
    """The deceleration the vehicle's stops are reckoned with when a new route is planned while
    it moves (:func:`sim.envelope.route.plan_route_moving`); lower is safer."""
    heartbeat_timeout_s: float = 3.0
    """No vehicle HEARTBEAT for this long: the link is lost."""
    reconnect_min_s: float = 0.2
    reconnect_max_s: float = 3.0
    """Backoff between attempts to recreate the connection: doubles from min to max."""
    px4_stream_lead_s: float = 1.2
    """PX4: how long the setpoint stream runs before OFFBOARD is asked for."""
    mode_retry_s: float = 0.5
    mode_request_window_s: float = 15.0
    """After a target is set, the guided mode is asked for (every ``mode_retry_s``) this long."""
    autopilot_fence: bool = False
    """Upload the envelope as the autopilot's own fence (:mod:`service.fence`: polygons, the
    ceiling, the breach action) once the vehicle's home is known, read it back, and neither take
    off nor stream while it is not on the vehicle (pymavlink backend). Routes then keep out of
    every exclusion at every height, as the autopilot's 2-D fence polygons do."""
    fence_action: str = "rtl"
    """The autopilot's action on a fence breach: ``rtl``, ``hold``, ``land`` or ``report``."""
    battery: BatteryConfig = BatteryConfig()  # noqa: RUF009 (frozen, so sharing it is safe)
    """The battery reserve at which the service sends the vehicle home (:mod:`service.battery`)."""
    signing_key: bytes | None = None
    """Optional 32-byte MAVLink 2 signing key, the same as the vehicle's."""
    source_system: int = 255
    source_component: int = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
    heartbeat_type: int = mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    """Our HEARTBEAT type: MAV_TYPE_ONBOARD_CONTROLLER (companion computer) or MAV_TYPE_GCS."""

    def __post_init__(self) -> None:
        for name in (
            "setpoint_rate_hz",
            "telemetry_rate_hz",
            "brake_mps2",
            "heartbeat_timeout_s",
            "reconnect_min_s",
            "reconnect_max_s",
            "mode_retry_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive number, got {value!r}")
        if self.fence_action not in ("rtl", "hold", "land", "report"):
            raise ValueError(
                f"fence_action: must be rtl, hold, land or report, got {self.fence_action!r}"
            )
        if self.signing_key is not None and len(self.signing_key) != 32:
            raise ValueError(f"signing_key: must be 32 bytes, got {len(self.signing_key)}")


@dataclass(frozen=True)
class LinkState:
    """A snapshot of the link and the vehicle, as :meth:`VehicleLink.state` returns it."""

    link: LinkHealth
    """``connecting`` (never heard the vehicle), ``up``, or ``link_lost``."""
    flavour: Flavour | None
    """From the vehicle's HEARTBEAT; None before the first one."""
    mode: str | None
    armed: bool
    position_m: tuple[float, float, float] | None
    """Vehicle position in the area frame (x east, y north, z up), metres."""
    relative_alt_m: float | None
    """Altitude above home, metres (GLOBAL_POSITION_INT)."""
    heartbeat_age_s: float | None
    """Seconds since the vehicle's last HEARTBEAT; None before the first one."""
    target_m: tuple[float, float, float] | None
    """The target flown to (legal in the envelope), area frame; the route's setpoint streams."""
    streaming: bool
    takeoff: str
    """``idle``, ``running``, ``airborne`` or ``failed: <reason>``."""
    counters: dict[str, int] = field(default_factory=dict)
    takeoff_phase: str | None = None
    """While the take-off runs: the step it is at (``waiting for a position estimate``, ...)."""
    takeoff_attempts: int = 0
    """How many times the take-off sequence has started (it starts again after a refusal)."""
    takeoff_last_refusal: str | None = None
    """Why the last attempt failed, with what the vehicle said about it (its STATUSTEXT)."""
    status_texts: tuple[str, ...] = ()
    """The vehicle's latest STATUSTEXT messages, oldest first, as ``SEVERITY: text``."""
    heading_deg: float | None = None
    """Where the vehicle's nose points, degrees clockwise from north (None: not reported)."""
    system_id: int | None = None
    """The vehicle's MAVLink system id, from its HEARTBEAT; None before the first one."""
    component_id: int | None = None
    """The vehicle's MAVLink component id (its autopilot's), locked with ``system_id`` at the
    first vehicle HEARTBEAT: messages from any other system or component are not the vehicle's."""
    control: ControlHolder = "service"
    """Who has the vehicle (:mod:`service.control`): ``service`` (it streams and may ask for the
    guided mode), ``pilot``, ``autopilot`` (a failsafe, a return or a landing) or ``operator``
    (released through the API). Only an operator hands it back to the service."""
    control_reason: str = ""
    """Why: what the vehicle did when it left the service's hands, or how the service got it."""
    control_age_s: float | None = None
    """Seconds since the control last changed hands."""
    route: RouteView | None = None
    """The way to the target inside the envelope (the current setpoint first), or the hold
    point and why; None before the first target is planned."""
    fence: str = "off"
    """The autopilot's own fence (``autopilot_fence``): ``off``, ``uploaded``, what it waits
    for, or ``failed: <why>`` (tried again every ``FENCE_RETRY_S``)."""
    battery_pct: float | None = None
    """Remaining charge, % (SYS_STATUS); None while the vehicle reports none."""
    battery_voltage_v: float | None = None
    battery_drain_pct_per_s: float | None = None
    """The drain measured while flying (None before ``min_window_s`` of it)."""
    battery_return_at_pct: float | None = None
    """The charge at which the service sends the vehicle home from where it is now (the reserve
    plus the return's cost); None while the vehicle is not flying in the service's hands."""


class VehicleLink(ABC):
    """What the service needs from a vehicle link: the one interface, whichever backend (or
    test fake) implements it. Every method returns at once; the I/O runs in the background."""

    config: LinkConfig

    @abstractmethod
    def start(self) -> Self:
        """Start the background I/O; returns at once (the link comes up in the background)."""

    @abstractmethod
    def close(self, timeout_s: float = 5.0) -> None:
        """Stop everything and drop the connection (safe to call twice)."""

    @abstractmethod
    def state(self) -> LinkState:
        """A consistent snapshot of the link and the vehicle; never blocks on I/O."""

    @abstractmethod
    def set_target(self, target_m: Sequence[float]) -> tuple[float, float, float]:
        """Fly to ``target_m`` (area frame, metres) from now on; returns the target streamed at
        the end: the legal point nearest it in the envelope (:mod:`service.routing`). NaN or
        infinite coordinates, or no legal point near it, raise ValueError and change nothing."""

    @property
    @abstractmethod
    def envelope(self) -> Envelope:
        """The envelope the vehicle flies in now."""

    @property
    @abstractmethod
    def routing_envelope(self) -> Envelope:
        """The envelope its routes are planned in: :attr:`envelope`, with every exclusion a
        full-height column while the autopilot's fence is on
        (:func:`service.fence.fence_compatible`)."""

    @abstractmethod
    def legal_target(self, target_m: Sequence[float]) -> tuple[float, float, float] | None:
        """The target :meth:`set_target` would stream for ``target_m`` (the nearest legal point
        of the envelope the routes are planned in), or None when there is none; changes
        nothing."""

    @abstractmethod
    def set_envelope(self, envelope: Envelope) -> None:
        """Fly inside ``envelope`` from now on: the route is planned again from where the vehicle
        is (a vehicle the new envelope finds outside holds there and says why)."""

    @abstractmethod
    def clear_target(self) -> None:
        """Stop streaming (the vehicle's own failsafe for a lost stream then acts)."""

    @abstractmethod
    def arm_and_takeoff(
        self, z_m: float | None = None, timeout_s: float = TAKEOFF_TIMEOUT_S
    ) -> Future[None]:
        """Arm and climb to ``z_m`` (area frame; default the area's ``z_min_m``), only when
        asked, retrying refusals until ``timeout_s``; the Future completes when airborne."""

    @abstractmethod
    def hand_back(self, reason: str = "handed back by an operator") -> None:
        """An operator hands the vehicle back to the service: the target from before is dropped,
        and the next target set streams and asks for the guided mode during its request window.
        :class:`ControlRefused` while the vehicle cannot be taken (link down, a return or landing
        mode, a failsafe flagged)."""

    @abstractmethod
    def release(
        self, reason: str = "released by an operator", holder: ControlHolder = "operator"
    ) -> None:
        """The vehicle is not the service's: it stops streaming and asks for nothing until
        :meth:`hand_back`. An operator's release (``holder`` ``operator``), or a restart that
        restores who had the vehicle when the service stopped."""

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass
class _LoopTimes:
    """The I/O loop's schedule (monotonic seconds), kept by the loop's thread only."""

    backoff_s: float
    next_open: float = 0.0
    opened_at: float = 0.0
    ever_opened: bool = False
    next_heartbeat: float = 0.0
    next_telemetry_request: float = 0.0
    next_setpoint: float = 0.0
    last_setpoint: float = -math.inf
    next_mode_request: float = 0.0
    wait_s: float = 0.0
    """How long the next poll may wait for input (until the next thing due)."""


class VehicleLinkBase(TakeoffMixin, SafetyMixin, VehicleLink):
    """What both MAVLink backends share (see the module docstring): the I/O loop, heartbeat
    supervision, setpoint scheduling, the geofence, the vehicle state it exposes and the
    take-off sequence.

    A backend implements the hooks (``_open_transport``, ``_transport_open``, ``_poll``,
    ``_close_transport``, ``_send_setpoint``, ``_send_guided_mode_request``, ``_ask``,
    ``_ask_arm``; optionally ``_send_heartbeat``, ``_request_telemetry``, ``_ready_to_command``,
    ``_stop_stream``, ``_on_link_up``), decodes the vehicle's HEARTBEATs through
    :meth:`_note_heartbeat` and its STATUSTEXTs through :meth:`_note_status_text`, and keeps the
    position fields below up to date under ``self._cond``.
    """

    _thread_name = "vehicle-link"
    _silence_is_connect_failure = False
    """A transport that never heard the vehicle counts in ``connect_failures`` when it is dropped
    (for backends whose ``_open_transport`` accepts any address, such as MAVSDK)."""

    def __init__(self, config: LinkConfig) -> None:
        self.config = config
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._workers: list[threading.Thread] = []
        self._transport_dead = False  # set by the backend: the transport must be recreated
        self.counters: Counter[str] = Counter(
            dict.fromkeys(
                ("setpoints_sent", "geofence_clamps", "reconnects", "connect_failures"), 0
            )
        )
        # Vehicle state (under self._cond).
        self._health: LinkHealth = "connecting"
        self._flavour: Flavour | None = None
        self._custom_mode: int | None = None
        self._armed = False
        self._last_hb: float | None = None
        self._up_since = 0.0
        self._ned: tuple[float, float, float] | None = None
        self._ned_velocity: tuple[float, float, float] | None = None  # with the position, m/s
        self._position_at: float | None = None
        self._relative_alt_m: float | None = None
        self._system_id: int | None = None  # the vehicle's, from its HEARTBEAT
        # (system, component) locked at the first vehicle HEARTBEAT, for this object's lifetime
        # (see _vehicle_ids_match); foreign systems already logged, at most 256.
        self._vehicle_ids: tuple[int, int | None] | None = None
        self._foreign_logged: set[int] = set()
        self._system_status: int | None = None  # HEARTBEAT.system_status
        self._control = Control("service", "waiting for the vehicle", time.monotonic())
        self._failsafe_text: tuple[float, str] | None = None  # the latest failsafe STATUSTEXT
        self._control_fresh = False  # handed back: the next HEARTBEAT is the new baseline
        self._heading_deg: float | None = None  # GLOBAL_POSITION_INT.hdg (MAVSDK: its heading)
        self._home_amsl_m: float | None = None
        self._ekf_flags: int | None = None  # ArduPilot's EKF_STATUS_REPORT.flags, when it sends it
        self._status_texts: deque[tuple[float, str]] = deque(maxlen=STATUS_TEXTS_KEPT)
        self._battery_pct: float | None = None  # SYS_STATUS.battery_remaining (None: unknown)
        self._battery_voltage_v: float | None = None
        self._drain = DrainEstimate(config.battery)
        self._battery_checked_at = -math.inf
        self._return_pending: str | None = None  # why the vehicle is being sent home
        # Streaming state.
        self._target_m: tuple[float, float, float] | None = None
        envelope = config.envelope or area_envelope(config.area)
        self._fence_envelope = envelope  # what goes on the autopilot (its fence)
        waiting = "waiting for the vehicle's origin (GPS_GLOBAL_ORIGIN)"
        self._fence = waiting if config.autopilot_fence else "off"
        self._fence_next_try = 0.0
        self._speed_limit_mps: float | None = None  # set in this stay in GUIDED (ArduPilot)
        self._speed_set_at = -math.inf
        self._speed_next_try = 0.0
        self._speed_busy = False
        # PX4's MPC_XY_VEL_MAX and the speeds it caps: the vehicle's own values while the
        # service has changed them (service.link_safety).
        self._speed_params_own: dict[str, float] | None = None
        # What the service set it to; NaN from a PARAM_SET until the vehicle confirms it.
        self._speed_param_mps: float | None = None
        self._closing = False
        self._origin: GeoPoint | None = None  # the local NED origin, from GPS_GLOBAL_ORIGIN
        self._routing = LinkRoute(
            fence_compatible(envelope) if config.autopilot_fence else envelope,
            background_planner(f"{self._thread_name}-routes"),
            self._route_planned,
        )
        self._target_dirty = False  # a new target not sent yet: send it at once
        self._awaiting_plan = False  # the I/O loop waits for a route plan it asked for
        self._hold_setpoints = False
        self._stream_since: float | None = None
        self._streamed_area_m: tuple[float, float, float] | None = None  # the latest setpoint
        self._mode_wanted_until = 0.0
        self._mode_asked_at = -math.inf  # the latest guided-mode request (monotonic)
        # Take-off bookkeeping (under self._cond).
        self._takeoff = "idle"
        self._takeoff_phase: str | None = None
        self._takeoff_attempts = 0
        self._takeoff_last_refusal: str | None = None

    # ------------------------------------------------------------------ backend hooks

    @abstractmethod
    def _open_transport(self, now: float) -> bool:
        """Open the connection to the vehicle; False when it cannot be opened (counted in
        ``connect_failures`` and tried again with backoff)."""

    @abstractmethod
    def _transport_open(self) -> bool:
        """A connection is open (it may not have heard the vehicle yet)."""

    @abstractmethod
    def _poll(self, wait_s: float) -> None:
        """Take in what the vehicle sent, waiting up to ``wait_s`` for it. Raising drops the
        connection (it is opened anew with backoff)."""

    @abstractmethod
    def _close_transport(self) -> None:
        """Drop the connection (safe to call twice, and from :meth:`close`)."""

    @abstractmethod
    def _send_setpoint(self, ned_m: tuple[float, float, float], now: float, new: bool) -> bool:
        """Send one position setpoint (local NED, metres); ``new`` for the first of a stream.
        True when it went out."""

    @abstractmethod
    def _send_guided_mode_request(self, flavour: Flavour) -> None:
        """Ask (once, without waiting) for the flavour's guided mode (GUIDED / OFFBOARD)."""

    @abstractmethod
    def _ask(self, command: int, params: Sequence[float], timeout_s: float) -> int | None:
        """Send a COMMAND_LONG (again, while unanswered) and wait up to ``timeout_s`` for its
        final COMMAND_ACK: the MAV_RESULT, or None when no answer came."""

    @abstractmethod
    def _param_float(self, name: str, value: float | None, timeout_s: float) -> float | None:
        """Set the vehicle's REAL32 parameter ``name`` to ``value`` (None: only read it), from a
        worker thread: the value the vehicle reports afterwards, or None when no answer came in
        ``timeout_s``."""

    @abstractmethod
    def _ask_arm(self, timeout_s: float) -> int | None:
        """Ask the vehicle to arm (never forced), once: MAV_RESULT_ACCEPTED, another MAV_RESULT
        for a refusal, or None when no answer came."""

    def _send_heartbeat(self) -> None:
        """Send our own HEARTBEAT (every ``HEARTBEAT_PERIOD_S``; none where the library does)."""

    def _request_telemetry(self, now: float) -> None:
        """Ask for the telemetry the link needs (every ``TELEMETRY_REQUEST_PERIOD_S`` while the
        vehicle is up; a backend that asks once per connection leaves this empty)."""

    def _ready_to_command(self) -> bool:
        """The transport can address the vehicle (beyond hearing its HEARTBEAT)."""
        return True

    def _stop_stream(self) -> None:
        """A setpoint was due but nothing streams (no target, link down, held for take-off)."""

    def _on_link_up(self, now: float) -> None:
        """The vehicle's HEARTBEAT is back (called under ``self._cond``): reset per-session
        bookkeeping."""

    def _request_origin(self) -> None:
        """Ask for the vehicle's GPS_GLOBAL_ORIGIN (for the fence's geography)."""

    def _upload_fence(self, plan: FencePlan) -> object:
        """Put ``plan`` on the autopilot and read it back (in the I/O thread); raises
        MissionError or FenceError when it did not. A backend that cannot says so."""
        raise FenceError(
            "autopilot_fence: this backend cannot upload a fence (use --mavlink-backend pymavlink)"
        )

    # ------------------------------------------------------------------ public API

    def start(self) -> Self:
        """Start the I/O thread (returns at once; the link comes up in the background)."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop every thread and drop the connection (safe to call twice); a speed limit the
        service put on a PX4 is given back first (:meth:`_give_back_speed_param`)."""
        self._give_back_speed_param(min(timeout_s, SPEED_GIVE_BACK_S))
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for thread in [self._thread, *self._workers]:
            if thread is not None:
                thread.join(timeout_s)
        self._thread = None
        self._routing.close()
        self._close_transport()

    def state(self) -> LinkState:
        """A consistent snapshot (never blocks on I/O)."""
        now = time.monotonic()
        with self._cond:
            position = ned_to_area(*self._ned, self.config.frames) if self._ned else None
            return LinkState(
                link=self._health,
                flavour=self._flavour,
                mode=self._mode_locked(),
                armed=self._armed,
                position_m=position,
                relative_alt_m=self._relative_alt_m,
                heartbeat_age_s=None if self._last_hb is None else now - self._last_hb,
                target_m=self._target_m,
                streaming=self._streaming_now(),
                takeoff=self._takeoff,
                counters={**self.counters, **self._routing.counters},
                takeoff_phase=self._takeoff_phase,
                takeoff_attempts=self._takeoff_attempts,
                takeoff_last_refusal=self._takeoff_last_refusal,
                status_texts=tuple(text for _, text in self._status_texts),
                heading_deg=self._heading_deg,
                system_id=self._system_id,
                component_id=self._vehicle_ids[1] if self._vehicle_ids else None,
                control=self._control.holder,
                control_reason=self._control.reason,
                control_age_s=now - self._control.since_s,
                route=self._routing.view(),
                fence=self._fence,
                battery_pct=self._battery_pct,
                battery_voltage_v=self._battery_voltage_v,
                battery_drain_pct_per_s=self._drain.measured_pct_per_s,
                battery_return_at_pct=self._return_at_pct(),
            )

    def set_target(self, target_m: Sequence[float]) -> tuple[float, float, float]:
        """Fly to ``target_m`` (area frame, metres) from now on; returns the target streamed.

        A target outside the envelope is moved to the nearest legal point (logged and counted
        in ``geofence_clamps``); the vehicle flies there along a legal route, or holds and says
        why (:mod:`service.routing`; :attr:`LinkState.route`). NaN or infinite coordinates, or a
        target with no legal point near it, raise ValueError and change nothing. A new target
        goes out at the I/O loop's next iteration and opens a window of
        ``mode_request_window_s`` in which the guided mode is asked for; the same target set
        again opens none (the paced loop sets it every period). Nothing streams while the
        service does not hold the vehicle (:mod:`service.control`).
        """
        with self._cond:
            legal, changed = self._routing.set_target(target_m, self.counters)
            if changed:
                self._target_dirty = True
                self._cond.notify_all()  # wakes an I/O loop waiting on it: out at once
                # A new target (only): the guided mode may be asked for during the window.
                self._mode_wanted_until = time.monotonic() + self.config.mode_request_window_s
            self._target_m = legal
        return legal

    def set_envelope(self, envelope: Envelope) -> None:
        """Fly inside ``envelope`` from now on (see :meth:`VehicleLink.set_envelope`)."""
        with self._cond:
            if self.config.autopilot_fence:
                # Planned as the autopilot's fence has it; nothing streams until it is on board.
                self._fence_envelope = envelope
                self._fence = "uploading a new envelope"
                self._fence_next_try = 0.0
                envelope = fence_compatible(envelope)
            self._routing.set_envelope(envelope)
            if self._target_m is not None:
                self._target_dirty = True
                self._cond.notify_all()

    @property
    def envelope(self) -> Envelope:
        """The envelope the vehicle flies in now (as given: routes keep out of its exclusions
        at every height when the autopilot's fence is on)."""
        with self._cond:
            return self._fence_envelope

    @property
    def routing_envelope(self) -> Envelope:
        with self._cond:
            return self._routing.envelope

    def legal_target(self, target_m: Sequence[float]) -> tuple[float, float, float] | None:
        """See :meth:`VehicleLink.legal_target`."""
        with self._cond:
            return self._routing.legal(target_m)

    def clear_target(self) -> None:
        """Stop streaming setpoints (the vehicle keeps its own behaviour for a lost stream)."""
        with self._cond:
            self._target_m = None
            self._routing.clear()
            self._stream_since = None

    def hand_back(self, reason: str = "handed back by an operator") -> None:
        """Give the vehicle back to the service (see :meth:`VehicleLink.hand_back`)."""
        with self._cond:
            refusal = vehicle_control.handback_refusal(
                self._flavour, self._mode_locked(), self._health == "up", self._failsafe_flagged()
            )
            if refusal is not None:
                raise ControlRefused(refusal)
            self._set_control(Control("service", reason, time.monotonic()))
            # The target from before the vehicle left is stale: the next decision streams.
            self._target_m = None
            self._routing.clear()
            self._stream_since = None
            # A mode change made before the hand-back but heard after it is not a new takeover.
            self._control_fresh = True

    def release(
        self, reason: str = "released by an operator", holder: ControlHolder = "operator"
    ) -> None:
        """Take the vehicle from the service (see :meth:`VehicleLink.release`)."""
        if holder == "service":
            raise ValueError("holder: release gives the vehicle to someone other than the service")
        with self._cond:
            self._set_control(Control(holder, reason, time.monotonic()))

    def _set_control(self, control: Control) -> None:
        """Change who has the vehicle, logged and counted (call under ``self._cond``)."""
        if control == self._control:
            return
        was = self._control.holder
        self._control = control
        if control.holder != "service":
            self._stream_since = None
            self.counters["control_released"] += 1
            log.warning("the %s has the vehicle: %s", control.holder, control.reason)
        elif was != "service":
            self.counters["control_handed_back"] += 1
            log.info("the service has the vehicle again: %s", control.reason)

    def _failsafe_flagged(self) -> bool:
        """The vehicle's HEARTBEAT flags a failsafe (call under ``self._cond``)."""
        return self._system_status in (
            vehicle_control.MAV_STATE_CRITICAL,
            vehicle_control.MAV_STATE_EMERGENCY,
        )

    # ------------------------------------------------------------------ the I/O loop

    def _run(self) -> None:
        """The I/O thread: (re)open the transport, take in telemetry, send what is due."""
        times = _LoopTimes(backoff_s=self.config.reconnect_min_s)
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                self._check_heartbeat(now)
                if not self._transport_open():
                    self._open_when_due(times, now)
                    continue
                try:
                    self._poll(times.wait_s)
                except Exception:  # a broken transport or a parser surprise: recreate it
                    log.exception("vehicle link receive failed; recreating the connection")
                    self._transport_dead = True
                self._serve(times, time.monotonic())
        except Exception:
            log.exception("%s thread failed", self._thread_name)
            raise
        finally:
            self._close_transport()

    def _open_when_due(self, times: _LoopTimes, now: float) -> None:
        """Open the transport once the backoff allows it; back off further when it fails."""
        if now < times.next_open:
            self._stop.wait(min(IDLE_WAIT_S, times.next_open - now))
            return
        if self._open_transport(now):
            if times.ever_opened:
                self.counters["reconnects"] += 1
            times.ever_opened = True
            times.opened_at = now
            times.next_heartbeat = 0.0
            times.backoff_s = self.config.reconnect_min_s
            self._transport_dead = False
        else:
            self.counters["connect_failures"] += 1
            self._back_off(times, now)

    def _back_off(self, times: _LoopTimes, now: float) -> None:
        times.next_open = now + times.backoff_s
        times.backoff_s = min(times.backoff_s * 2, self.config.reconnect_max_s)

    def _serve(self, times: _LoopTimes, now: float) -> None:
        """One pass with the transport open: drop it if it died or the vehicle stays silent;
        otherwise send what is due (our HEARTBEAT, telemetry requests, setpoints, mode requests)
        and work out how long the next poll may wait."""
        config = self.config
        health = self._check_heartbeat(now)
        with self._cond:
            silent_since = max(times.opened_at, self._last_hb or 0.0)
        if self._transport_dead or (
            health != "up" and now - silent_since > config.heartbeat_timeout_s
        ):
            if not self._transport_dead:
                if self._silence_is_connect_failure and silent_since == times.opened_at:
                    # Such a backend accepts a connection it cannot make yet (it retries by
                    # itself), so a connection that never heard the vehicle is the failure.
                    self.counters["connect_failures"] += 1
                log.info("no vehicle on %s: opening the connection anew", config.url)
            self._close_transport()
            self._back_off(times, now)
            return
        if now >= times.next_heartbeat:
            times.next_heartbeat = now + HEARTBEAT_PERIOD_S
            self._send_heartbeat()
        times.wait_s = IDLE_WAIT_S
        if health != "up" or not self._ready_to_command():
            return
        if now >= times.next_telemetry_request:
            times.next_telemetry_request = now + TELEMETRY_REQUEST_PERIOD_S
            self._request_telemetry(now)
        if config.autopilot_fence and now >= self._fence_next_try:
            self._fence_step(now)
        if now - self._battery_checked_at >= BATTERY_CHECK_PERIOD_S:
            self._battery_checked_at = now
            self._check_battery_reserve(now)
        period_s = 1.0 / config.setpoint_rate_hz
        with self._cond:
            dirty = self._target_dirty
        if dirty and now - times.last_setpoint >= config.setpoint_min_gap_s:
            # A new target: on the wire now, and the steady schedule restarts from here.
            times.next_setpoint = now + period_s
            times.last_setpoint = now
            self._stream_setpoint(now)
        elif now >= times.next_setpoint:
            times.next_setpoint = max(times.next_setpoint + period_s, now - period_s)
            times.last_setpoint = now
            self._stream_setpoint(now)
        if now >= times.next_mode_request:
            times.next_mode_request = now + config.mode_retry_s
            flavour = self._guided_mode_due(now)
            if flavour is not None:
                self._send_guided_mode_request(flavour)
        if now >= self._speed_next_try:
            self._speed_limit_step(now)
        wake_at = min(times.next_setpoint, times.next_mode_request)
        with self._cond:
            if self._target_dirty:  # set_target notifies self._cond: a new target wakes a poll
                wake_at = min(wake_at, times.last_setpoint + config.setpoint_min_gap_s)
        times.wait_s = min(max(wake_at - time.monotonic(), 0.001), IDLE_WAIT_S)

    def _check_heartbeat(self, now: float) -> LinkHealth:
        """Declare the link lost after ``heartbeat_timeout_s`` without a vehicle HEARTBEAT."""
        with self._cond:
            last_hb = self._last_hb
            timeout_s = self.config.heartbeat_timeout_s
            if self._health == "up" and last_hb is not None and now - last_hb > timeout_s:
                self._health = "link_lost"
                self._stream_since = None
                log.warning("no HEARTBEAT for %.1f s: link lost", now - last_hb)
            return self._health

    def _note_heartbeat(
        self,
        autopilot: int,
        vehicle_type: int,
        base_mode: int,
        custom_mode: int,
        system_id: int | None = None,
        system_status: int | None = None,
        component_id: int | None = None,
    ) -> bool:
        """A HEARTBEAT heard on the link (from MAVLink system ``system_id``, component
        ``component_id``). False, and nothing changes, when it is not the vehicle's: a ground
        station, a companion computer or a peripheral (autopilot INVALID, or type GCS,
        ONBOARD_CONTROLLER, GIMBAL, CAMERA, ADSB, ...), or another system or component than the
        vehicle's (:meth:`_vehicle_ids_match`: the first vehicle HEARTBEAT locks them; others are
        counted in ``foreign_messages``). Otherwise the
        flavour, mode, armed state and system id are the vehicle's, and the link is up; telemetry
        from before a loss no longer counts as fresh. Outside the service's take-off, a mode
        change, a return or landing mode or a disarm takes the vehicle out of the service's hands
        (:func:`service.control.after_heartbeat`)."""
        if autopilot == mavlink.MAV_AUTOPILOT_INVALID or vehicle_type in (
            mavlink.MAV_TYPE_GCS,
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
            # Peripherals, some of which send an autopilot in their HEARTBEAT: never the vehicle
            # (the first vehicle HEARTBEAT locks its ids).
            mavlink.MAV_TYPE_ANTENNA_TRACKER,
            mavlink.MAV_TYPE_GIMBAL,
            mavlink.MAV_TYPE_ADSB,
            mavlink.MAV_TYPE_CAMERA,
            mavlink.MAV_TYPE_CHARGING_STATION,
            mavlink.MAV_TYPE_FLARM,
            mavlink.MAV_TYPE_SERVO,
            mavlink.MAV_TYPE_ODID,
            mavlink.MAV_TYPE_BATTERY,
            mavlink.MAV_TYPE_PARACHUTE,
            mavlink.MAV_TYPE_LOG,
            mavlink.MAV_TYPE_OSD,
            mavlink.MAV_TYPE_IMU,
            mavlink.MAV_TYPE_GPS,
            mavlink.MAV_TYPE_WINCH,
            mavlink.MAV_TYPE_ILLUMINATOR,
            mavlink.MAV_TYPE_GRIPPER,
        ):
            return False
        now = time.monotonic()
        with self._cond:
            if system_id is not None and not self._vehicle_ids_match(
                system_id, component_id, lock=True
            ):
                return False
            previous_mode, previous_armed = self._mode_locked(), self._armed
            after_loss = self._health == "link_lost"
            self._flavour = flavour = flavour_of(autopilot)
            if system_id is not None:
                self._system_id = system_id
            self._custom_mode = custom_mode
            if after_loss or self._mode_locked() != previous_mode:
                self._speed_limit_mps = None  # a new stay in GUIDED starts at WPNAV_SPEED
            self._armed = bool(base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self._system_status = system_status
            self._last_hb = now
            self._follow_control(previous_mode, previous_armed, after_loss, now)
            if self._health != "up":
                log.info("vehicle HEARTBEAT (%s): link up", flavour)
                self._health = "up"
                self._up_since = now
                self._position_at = None
                self._ekf_flags = None
                self._on_link_up(now)
            self._cond.notify_all()
        return True

    def _vehicle_ids_match(
        self, system_id: int, component_id: int | None, lock: bool = False
    ) -> bool:
        """Whether a message from ``system_id``/``component_id`` is the vehicle's (call under
        ``self._cond``). The first vehicle HEARTBEAT (``lock``) locks the pair for this link's
        lifetime: a transport recreated after a loss keeps it, so another system heard while the
        vehicle is silent never takes its place; only a new link (a restarted service) chooses
        again. Before the lock nothing is the vehicle's; after it, a message from another pair
        is counted in ``foreign_messages`` and each foreign system is logged once. A None
        ``component_id`` matches on the system alone."""
        if self._vehicle_ids is None:
            if not lock:
                return False
            self._vehicle_ids = (system_id, component_id)
            log.info("vehicle: MAVLink system %s component %s", system_id, component_id)
            return True
        locked_system, locked_component = self._vehicle_ids
        if system_id == locked_system and (
            component_id is None or locked_component is None or component_id == locked_component
        ):
            return True
        self.counters["foreign_messages"] += 1
        if system_id not in self._foreign_logged:
            self._foreign_logged.add(system_id)
            log.warning(
                "MAVLink system %s component %s sends vehicle messages on the link of system %s "
                "component %s: ignored (counted in foreign_messages; only signing keeps out a "
                "sender that copies the vehicle's ids)",
                system_id,
                component_id,
                locked_system,
                locked_component,
            )
        return False

    def _follow_control(
        self, previous_mode: str | None, previous_armed: bool, after_loss: bool, now: float
    ) -> None:
        """Who has the vehicle after this HEARTBEAT (call under ``self._cond``); the take-off
        sequence owns the vehicle's modes while it runs, and a disarm after it makes the
        take-off ``idle`` again."""
        if self._takeoff == "running" or self._flavour is None:
            return
        fresh, self._control_fresh = self._control_fresh, False
        seen = self._observation(
            None if fresh else previous_mode,
            None if fresh else previous_armed,
            after_loss,
            at_start=previous_mode is None and not fresh,
            now=now,
        )
        self._set_control(vehicle_control.after_heartbeat(self._control, seen, now))
        if previous_armed and not self._armed and self._takeoff == "airborne":
            self._takeoff = "idle"

    def _observation(
        self,
        previous_mode: str | None,
        previous_armed: bool | None,
        after_loss: bool,
        at_start: bool,
        now: float,
    ) -> vehicle_control.Observation:
        """What the latest HEARTBEAT shows, for :func:`service.control.after_heartbeat` (call
        under ``self._cond``, with the flavour and mode known)."""
        mode = self._mode_locked()
        assert self._flavour is not None and mode is not None
        failsafe_text = None
        if self._failsafe_text is not None:
            at, text = self._failsafe_text
            if now - at <= vehicle_control.FAILSAFE_EVIDENCE_S:
                failsafe_text = text
        return vehicle_control.Observation(
            flavour=self._flavour,
            mode=mode,
            armed=self._armed,
            previous_mode=previous_mode,
            previous_armed=previous_armed,
            failsafe_flagged=self._failsafe_flagged(),
            failsafe_text=failsafe_text,
            after_link_loss=after_loss,
            at_start=at_start,
            streamed=self.counters.get("setpoints_sent", 0) > 0,
        )

    def _stream_setpoint(self, now: float) -> None:
        """The current setpoint of the route, if one streams, paced while the autopilot does not
        hold the envelope's speed limit (:meth:`_paced_locked`); counted when it went out. A
        stream that starts (again) plans the route from where the vehicle is now."""
        with self._cond:
            self._target_dirty = False
            setpoint = None
            new = False
            if self._streaming_now():
                new = self._stream_since is None
                if new:
                    self._routing.replan()
                setpoint = self._routing.setpoint(
                    self._position_locked(now),
                    self._velocity_locked(now),
                    self.config.brake_mps2,
                    self._wait_for_plan,
                )
                if not self._streaming_now():  # changed while the lock was let go
                    setpoint = None
                elif setpoint is not None:
                    setpoint = self._paced_locked(setpoint, now)
                    if setpoint is None:  # nothing to pace from yet: nothing goes out now
                        return
            if setpoint is None:
                self._stream_since = None
                self._streamed_area_m = None
            else:
                ned_m = area_to_ned(*setpoint, self.config.frames)
                self._streamed_area_m = setpoint
                if new:
                    self._stream_since = now
        if setpoint is None:
            self._stop_stream()
            return
        if self._send_setpoint(ned_m, now, new):
            with self._cond:
                self.counters["setpoints_sent"] += 1

    def _wait_for_plan(self, plan: Future) -> None:
        """Wait up to ``PLAN_WAIT_S`` for a route plan just asked for (called under
        ``self._cond``, which is let go meanwhile: the API and the link's workers are not held
        up by a plan)."""
        self._awaiting_plan = True
        try:
            self._cond.wait_for(plan.done, PLAN_WAIT_S)
        finally:
            self._awaiting_plan = False

    def _route_planned(self) -> None:
        """A route plan ended (on the planner's thread): stream it at once, unless the I/O loop
        has taken it already or is waiting for it (:meth:`_wait_for_plan`)."""
        with self._cond:
            if self._routing.planning:
                if not self._awaiting_plan:
                    self._target_dirty = True
                self._cond.notify_all()

    def _position_locked(self, now: float) -> tuple[float, float, float] | None:
        """Where the vehicle is (area frame) from a fresh LOCAL_POSITION_NED, or None (call
        under ``self._cond``)."""
        if self._ned is None or self._position_at is None:
            return None
        if now - self._position_at > POSITION_FRESH_S:
            return None
        return ned_to_area(*self._ned, self.config.frames)

    def _velocity_locked(self, now: float) -> tuple[float, float, float] | None:
        """How fast the vehicle moves (area frame, m/s) with its fresh position, or None when
        not known (call under ``self._cond``)."""
        if self._ned_velocity is None or self._position_locked(now) is None:
            return None
        north, east, down = self._ned_velocity
        return (east, north, -down)

    def _streaming_now(self) -> bool:
        return (
            self._health == "up"
            and self._target_m is not None
            and not self._hold_setpoints
            and self._control.service_has_it
            and self._fence in ("off", "uploaded")
        )

    def _guided_mode_due(self, now: float) -> Flavour | None:
        """The flavour when the guided mode (GUIDED / OFFBOARD) should be asked for now, counted
        as a mode request; None when not: no target streams (which includes: the service does
        not hold the vehicle), the request window is closed, the vehicle is already in it or in a
        return or landing mode, it flags a failsafe, no HEARTBEAT came since the last request
        (its answer is not known yet: asking again could undo a pilot's switch made meanwhile),
        or (PX4) the stream has not run ``px4_stream_lead_s`` yet."""
        with self._cond:
            flavour = self._flavour
            mode = self._mode_locked()
            if (
                flavour not in GUIDED_MODE_NAME
                or not self._streaming_now()
                or now > self._mode_wanted_until
                or mode is None
                or mode == GUIDED_MODE_NAME[flavour]
                or vehicle_control.is_return_or_land(flavour, mode)
                or self._failsafe_flagged()
                or self._last_hb is None
                or self._last_hb <= self._mode_asked_at
            ):
                return None
            if flavour == "px4" and (
                self._stream_since is None
                or now - self._stream_since < self.config.px4_stream_lead_s
            ):
                return None
            self.counters["mode_requests"] += 1
            self._mode_asked_at = now
            return flavour

    def _note_status_text(self, severity: int, text: str) -> None:
        """A STATUSTEXT from the vehicle: logged and kept for :meth:`state` (call under no lock)."""
        text = text.strip()
        if not text:
            return
        entry = mavlink.enums["MAV_SEVERITY"].get(severity)
        name = entry.name.removeprefix("MAV_SEVERITY_") if entry is not None else str(severity)
        with self._cond:
            self._status_texts.append((time.monotonic(), f"{name}: {text}"))
            if vehicle_control.is_failsafe_text(severity, text):
                self._failsafe_text = (time.monotonic(), text)
            self._cond.notify_all()
        level = logging.WARNING if severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO
        log.log(level, "vehicle says: %s", text)

    # ------------------------------------------------------------------ modes

    def _mode_locked(self) -> str | None:
        """The mode the vehicle's HEARTBEAT shows, None before one (call under ``self._cond``)."""
        if self._flavour is None or self._custom_mode is None:
            return None
        return mode_name(self._flavour, self._custom_mode)

    def _mode_is(self, name: str) -> bool:
        """The vehicle's HEARTBEAT shows mode ``name`` (call under ``self._cond``)."""
        return self._mode_locked() == name

    def _mode_now(self) -> str:
        with self._cond:
            return self._mode_locked() or "unknown"
