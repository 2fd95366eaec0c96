"""The service's MAVLink link to the vehicle, on pymavlink: telemetry in, setpoints out.

:class:`MavlinkLink` owns one pymavlink connection (any connection string pymavlink knows:
``tcp:HOST:PORT``, ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, a serial device) and runs all of
its I/O in background threads, so that callers (the placement loop, the HTTP side) never block::

    link = MavlinkLink(LinkConfig("tcp:127.0.0.1:5760", area=AreaConfig()))
    link.start()
    link.arm_and_takeoff()            # only when asked: a service never arms by surprise
    link.set_target((250.0, 250.0, 50.0))  # area frame, metres; clamped to the geofence
    print(link.state())               # position in the area frame, mode, armed, link health
    link.close()

What the I/O thread does, in a loop:

* sends our own HEARTBEAT at 1 Hz (an onboard controller or a GCS; autopilot INVALID);
* reads the vehicle's HEARTBEAT (flavour from its ``autopilot`` field, mode, armed),
  GLOBAL_POSITION_INT, LOCAL_POSITION_NED, EXTENDED_SYS_STATE and COMMAND_ACK;
* asks for the telemetry it needs with SET_MESSAGE_INTERVAL (and, on ArduPilot, the older
  REQUEST_DATA_STREAM if positions do not come);
* streams the current target as SET_POSITION_TARGET_LOCAL_NED (position only, type_mask 3576,
  MAV_FRAME_LOCAL_NED) at ``setpoint_rate_hz`` while the link is up; a *new* target goes out at
  the loop's next iteration (a few ms: the loop waits at most 5 ms for input) rather than at the
  next tick, and the steady schedule restarts from that send, so the rate never drops below
  ``setpoint_rate_hz`` (immediate sends are at least ``setpoint_min_gap_s`` apart, so a burst of
  decisions cannot flood the link);
* asks for the flavour's guided mode while a target is set: GUIDED at once on ArduPilot; on PX4
  OFFBOARD only after the stream has run ``px4_stream_lead_s`` (PX4 refuses it before), retrying;
* counts the vehicle's messages that fail the MAVLink 2 signature check (``signing_failures``:
  a wrong key on one side, or an unsigned vehicle while we sign); such messages are dropped, so
  a vehicle we cannot authenticate never comes ``up`` and is never commanded;
* watches the link: no vehicle HEARTBEAT for ``heartbeat_timeout_s`` -> ``link_lost``, streaming
  stops, the connection is recreated with backoff; when the vehicle is back, telemetry is asked
  for again and the latest target streams again. The mode is not forced back after a loss: a pilot
  who took over keeps control until the next :meth:`MavlinkLink.set_target`.

:meth:`MavlinkLink.arm_and_takeoff` runs in its own worker thread and returns a Future.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
import threading
import time
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Literal, Self

from service.frames import FrameConfig, area_to_ned, ned_to_area
from service.geofence import clamp_to_area
from sim.config import AreaConfig

# MAVLink 2 is needed for signing; pymavlink picks the wire version from this variable when its
# dialect module is first loaded (it would also switch on the first MAVLink 2 packet it sees).
os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

log = logging.getLogger(__name__)

LinkHealth = Literal["connecting", "up", "link_lost"]
Flavour = Literal["ardupilot", "px4", "generic"]

POSITION_ONLY_TYPE_MASK = 3576
"""SET_POSITION_TARGET_LOCAL_NED type_mask: use x, y, z only (ignore velocity, accel, yaw)."""

ARDUPILOT_GUIDED = 4
PX4_MAIN_AUTO = 4
PX4_MAIN_OFFBOARD = 6

ARDUPILOT_COPTER_MODES = {
    0: "STABILIZE",
    1: "ACRO",
    2: "ALT_HOLD",
    3: "AUTO",
    4: "GUIDED",
    5: "LOITER",
    6: "RTL",
    7: "CIRCLE",
    9: "LAND",
    16: "POSHOLD",
    17: "BRAKE",
    20: "GUIDED_NOGPS",
    21: "SMART_RTL",
}
PX4_MAIN_MODES = {
    1: "MANUAL",
    2: "ALTCTL",
    3: "POSCTL",
    4: "AUTO",
    5: "ACRO",
    6: "OFFBOARD",
    7: "STABILIZED",
    8: "RATTITUDE",
}
PX4_AUTO_SUB_MODES = {
    1: "READY",
    2: "TAKEOFF",
    3: "LOITER",
    4: "MISSION",
    5: "RTL",
    6: "LAND",
    8: "FOLLOW_TARGET",
    9: "PRECLAND",
}
GUIDED_MODE_NAME: dict[str, str] = {"ardupilot": "GUIDED", "px4": "OFFBOARD"}


def flavour_of(autopilot: int) -> Flavour:
    """The flavour for a HEARTBEAT ``autopilot`` value."""
    if autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    if autopilot == mavlink.MAV_AUTOPILOT_PX4:
        return "px4"
    return "generic"


def mode_name(flavour: Flavour, custom_mode: int) -> str:
    """A readable name for HEARTBEAT ``custom_mode`` (``MODE(n)`` when unknown)."""
    if flavour == "ardupilot":
        return ARDUPILOT_COPTER_MODES.get(custom_mode, f"MODE({custom_mode})")
    if flavour == "px4":
        main = (custom_mode >> 16) & 0xFF
        sub = (custom_mode >> 24) & 0xFF
        name = PX4_MAIN_MODES.get(main, f"MODE({main})")
        if main == PX4_MAIN_AUTO:
            return f"AUTO.{PX4_AUTO_SUB_MODES.get(sub, str(sub))}"
        return name
    return f"MODE({custom_mode})"


def signing_key_from_passphrase(passphrase: str) -> bytes:
    """A 32-byte MAVLink 2 signing key from a passphrase (SHA-256, as MAVProxy does)."""
    return hashlib.sha256(passphrase.encode()).digest()


@dataclass(frozen=True)
class LinkConfig:
    """Everything :class:`MavlinkLink` needs; only ``url`` has no default."""

    url: str
    """A pymavlink connection string: ``tcp:HOST:PORT``, ``udpin:HOST:PORT``, ``udpout:...``."""
    area: AreaConfig = AreaConfig()
    """The area volume: targets are clamped into it (the geofence)."""
    frames: FrameConfig = FrameConfig()  # noqa: RUF009 (frozen, so sharing it is safe)
    """Where the area frame sits in the vehicle's local NED frame."""
    setpoint_rate_hz: float = 10.0
    """How often the current target is sent (PX4 needs more than 2 Hz)."""
    setpoint_min_gap_s: float = 0.02
    """A new target is sent at once, but never sooner than this after the previous setpoint."""
    telemetry_rate_hz: float = 10.0
    """Rate asked for GLOBAL_POSITION_INT and LOCAL_POSITION_NED."""
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
            "heartbeat_timeout_s",
            "reconnect_min_s",
            "reconnect_max_s",
            "mode_retry_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive number, got {value!r}")
        if self.signing_key is not None and len(self.signing_key) != 32:
            raise ValueError(f"signing_key: must be 32 bytes, got {len(self.signing_key)}")


@dataclass(frozen=True)
class LinkState:
    """A snapshot of the link and the vehicle, as :meth:`MavlinkLink.state` returns it."""

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
    """The (geofenced) target being streamed, area frame."""
    streaming: bool
    takeoff: str
    """``idle``, ``running``, ``airborne`` or ``failed: <reason>``."""
    counters: dict[str, int] = field(default_factory=dict)


class VehicleLinkBase(ABC):
    """What every vehicle link shares, whatever speaks MAVLink for it (pymavlink or MAVSDK): the
    vehicle state it exposes (:meth:`state`), the geofenced target it streams (:meth:`set_target`,
    :meth:`clear_target`), the arm-and-takeoff worker's bookkeeping, and the thread lifecycle.

    A backend implements ``_run`` (the I/O thread), ``_command`` and ``_arm_until_accepted``
    (used by the shared arm-and-takeoff worker) and ``_release`` (drop the connection), and keeps
    the fields below up to date under ``self._cond``.
    """

    _thread_name = "vehicle-link"

    def __init__(self, config: LinkConfig) -> None:
        self.config = config
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._workers: list[threading.Thread] = []
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
        self._ned: tuple[float, float, float] | None = None
        self._position_at: float | None = None
        self._relative_alt_m: float | None = None
        self._home_amsl_m: float | None = None
        # Streaming state.
        self._target_m: tuple[float, float, float] | None = None
        self._target_dirty = False  # a new target not sent yet: send it at once
        self._hold_setpoints = False
        self._stream_since: float | None = None
        self._mode_wanted_until = 0.0
        self._takeoff = "idle"

    # Implemented by each backend.
    @abstractmethod
    def _run(self) -> None:
        """The I/O thread: connect, read telemetry, stream setpoints, until ``_stop`` is set."""

    @abstractmethod
    def _command(self, command: int, params: Sequence[float], deadline: float) -> None:
        """Send a COMMAND_LONG until accepted, retrying refusals with backoff, until ``deadline``
        (TimeoutError naming the last result)."""

    @abstractmethod
    def _arm_until_accepted(self, deadline: float) -> None:
        """Arm the vehicle, retrying refusals until ``deadline``."""

    @abstractmethod
    def _release(self) -> None:
        """Drop the connection (called once the threads have stopped)."""

    # ------------------------------------------------------------------ public API

    def start(self) -> Self:
        """Start the I/O thread (returns at once; the link comes up in the background)."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._thread = threading.Thread(target=self._run, name=self._thread_name, daemon=True)
        self._thread.start()
        return self

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop every thread and drop the connection (safe to call twice)."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()
        for thread in [self._thread, *self._workers]:
            if thread is not None:
                thread.join(timeout_s)
        self._thread = None
        self._release()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def state(self) -> LinkState:
        """A consistent snapshot (never blocks on I/O)."""
        now = time.monotonic()
        with self._cond:
            position = ned_to_area(*self._ned, self.config.frames) if self._ned else None
            mode = (
                mode_name(self._flavour, self._custom_mode)
                if self._flavour is not None and self._custom_mode is not None
                else None
            )
            return LinkState(
                link=self._health,
                flavour=self._flavour,
                mode=mode,
                armed=self._armed,
                position_m=position,
                relative_alt_m=self._relative_alt_m,
                heartbeat_age_s=None if self._last_hb is None else now - self._last_hb,
                target_m=self._target_m,
                streaming=self._streaming_now(),
                takeoff=self._takeoff,
                counters=dict(self.counters),
            )

    def set_target(self, target_m: Sequence[float]) -> tuple[float, float, float]:
        """Stream ``target_m`` (area frame, metres) from now on; returns the geofenced target.

        A target outside the area volume is clamped to it (logged and counted); NaN or infinite
        coordinates raise ValueError and change nothing.
        """
        try:
            clamped, was_clamped = clamp_to_area(target_m, self.config.area)
        except ValueError:
            with self._cond:
                self.counters["targets_rejected"] += 1
            raise
        with self._cond:
            if was_clamped:
                self.counters["geofence_clamps"] += 1
                log.warning("target %s outside the geofence: clamped to %s", target_m, clamped)
            if clamped != self._target_m:
                self._target_dirty = True
                self._cond.notify_all()  # wakes an I/O loop waiting on it: out at once
            self._target_m = clamped
            self._mode_wanted_until = time.monotonic() + self.config.mode_request_window_s
        return clamped

    def clear_target(self) -> None:
        """Stop streaming setpoints (the vehicle keeps its own behaviour for a lost stream)."""
        with self._cond:
            self._target_m = None
            self._stream_since = None

    def arm_and_takeoff(self, z_m: float | None = None, timeout_s: float = 60.0) -> Future[None]:
        """Arm and climb to ``z_m`` (area frame; default the area's ``z_min_m``), in a worker.

        ArduPilot: GUIDED, arm, MAV_CMD_NAV_TAKEOFF (altitude above home). PX4: arm,
        MAV_CMD_NAV_TAKEOFF (AMSL altitude). Refusals (e.g. no position estimate yet) are retried
        with backoff until ``timeout_s``. Position setpoints are held back until the vehicle is
        airborne (on ArduPilot a setpoint while the takeoff is still on the ground cancels it).
        The Future completes when airborne, or with the reason it failed.
        """
        area = self.config.area
        z_m = area.z_min_m if z_m is None else min(max(float(z_m), area.z_min_m), area.z_max_m)
        future: Future[None] = Future()
        worker = threading.Thread(
            target=self._takeoff_worker,
            args=(z_m, timeout_s, future),
            name=f"{self._thread_name}-takeoff",
            daemon=True,
        )
        with self._cond:
            self._takeoff = "running"
            self._hold_setpoints = True
        self._workers.append(worker)
        worker.start()
        return future

    def _streaming_now(self) -> bool:
        return self._health == "up" and self._target_m is not None and not self._hold_setpoints

    def _guided_mode_due(self, now: float) -> Flavour | None:
        """The flavour when the guided mode (GUIDED / OFFBOARD) should be asked for now, counted
        as a mode request; None when not: no target streams, the request window is closed, the
        vehicle is already in it, or (PX4) the stream has not run ``px4_stream_lead_s`` yet."""
        with self._cond:
            flavour = self._flavour
            if (
                flavour not in GUIDED_MODE_NAME
                or not self._streaming_now()
                or now > self._mode_wanted_until
                or self._custom_mode is None
                or mode_name(flavour, self._custom_mode) == GUIDED_MODE_NAME[flavour]
            ):
                return None
            if flavour == "px4" and (
                self._stream_since is None
                or now - self._stream_since < self.config.px4_stream_lead_s
            ):
                return None
            self.counters["mode_requests"] += 1
            return flavour

    def _wait_for(self, condition: Callable[[], bool], deadline: float, what: str) -> None:
        with self._cond:
            while not condition():
                remaining = deadline - time.monotonic()
                if self._stop.is_set():
                    raise RuntimeError("link closed")
                if remaining <= 0:
                    raise TimeoutError(f"timed out waiting for {what}")
                self._cond.wait(min(remaining, 0.2))

    def _takeoff_worker(self, z_m: float, timeout_s: float, future: Future[None]) -> None:
        deadline = time.monotonic() + timeout_s
        alt_rel_m = z_m - self.config.frames.area_origin_down_m
        airborne_alt_m = max(alt_rel_m * 0.9, alt_rel_m - 1.0)
        try:
            self._wait_for(
                lambda: self._health == "up" and self._home_amsl_m is not None,
                deadline,
                "the vehicle and its position",
            )
            with self._cond:
                flavour = self._flavour
                flying = (self._relative_alt_m or 0.0) >= airborne_alt_m and self._armed
            if not flying:
                if flavour == "ardupilot":
                    self._command(
                        mavlink.MAV_CMD_DO_SET_MODE,
                        (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, ARDUPILOT_GUIDED),
                        deadline,
                    )
                if not self._armed:
                    self._arm_until_accepted(deadline)
                with self._cond:
                    home_amsl_m = self._home_amsl_m or 0.0
                alt_param = alt_rel_m + home_amsl_m if flavour == "px4" else alt_rel_m
                self._command(
                    mavlink.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, math.nan, 0, 0, alt_param), deadline
                )
                self._wait_for(
                    lambda: (self._relative_alt_m or 0.0) >= airborne_alt_m,
                    deadline,
                    f"{airborne_alt_m:.1f} m above home",
                )
            with self._cond:
                self._takeoff = "airborne"
                self._hold_setpoints = False
                self._mode_wanted_until = time.monotonic() + self.config.mode_request_window_s
            log.info("airborne at %.1f m above home", alt_rel_m)
            future.set_result(None)
        except Exception as exc:
            with self._cond:
                self._takeoff = f"failed: {exc}"
                self._hold_setpoints = False
            log.warning("arm and takeoff failed: %s", exc)
            future.set_exception(exc)


class MavlinkLink(VehicleLinkBase):
    """The MAVLink link and setpoint streamer. See the module docstring."""

    _thread_name = "mavlink-link"

    def __init__(self, config: LinkConfig) -> None:
        super().__init__(config)
        self._send_lock = threading.Lock()
        self._conn: Any = None
        self._transport_dead = False
        self._t0 = time.monotonic()
        self.counters["signing_failures"] = 0
        self._target_sys = 1
        self._target_comp = 1
        self._landed_state: int | None = None
        self._acks: dict[int, tuple[int, int]] = {}
        self._ack_seq = 0
        self._up_since = 0.0
        self._fallback_streams_sent = False

    def _arm_until_accepted(self, deadline: float) -> None:
        self._command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1,), deadline)

    def _release(self) -> None:
        self._close_conn()

    # ------------------------------------------------------------------ connection

    def _open_conn(self) -> bool:
        config = self.config
        try:
            conn = mavutil.mavlink_connection(
                config.url,
                source_system=config.source_system,
                source_component=config.source_component,
                dialect="ardupilotmega",
                autoreconnect=False,
                retries=1,
            )
        except (OSError, ValueError) as exc:
            log.debug("cannot open %s: %s", config.url, exc)
            return False
        # pymavlink prints on a closed TCP socket; we notice it ourselves instead.
        conn.handle_eof = self._on_transport_dead
        conn.handle_disconnect = self._on_transport_dead
        if config.signing_key is not None:
            conn.setup_signing(config.signing_key, sign_outgoing=True)
        with self._send_lock:
            self._conn = conn
        self._transport_dead = False
        log.info("MAVLink connection open: %s", config.url)
        return True

    def _on_transport_dead(self) -> None:
        self._transport_dead = True

    def _close_conn(self) -> None:
        with self._send_lock:
            conn, self._conn = self._conn, None
        if conn is not None:
            with contextlib.suppress(Exception):
                conn.close()

    def _send(self, fn: Callable[[Any], None]) -> bool:
        """Run ``fn(mav)`` on the current connection under the send lock; False if none."""
        with self._send_lock:
            conn = self._conn
            if conn is None:
                return False
            try:
                fn(conn.mav)
            except OSError as exc:
                log.debug("send failed: %s", exc)
                self._transport_dead = True
                return False
            return True

    # ------------------------------------------------------------------ the I/O loop

    def _run(self) -> None:
        config = self.config
        backoff_s = config.reconnect_min_s
        next_open = 0.0
        opened_at = 0.0
        ever_opened = False
        next_heartbeat = 0.0
        next_setpoint = 0.0
        next_mode_request = 0.0
        next_telemetry_request = 0.0
        setpoint_period_s = 1.0 / config.setpoint_rate_hz
        last_setpoint = -math.inf
        while not self._stop.is_set():
            now = time.monotonic()
            self._check_heartbeat(now)
            if self._conn is None:
                if now < next_open:
                    self._stop.wait(min(0.05, next_open - now))
                    continue
                if self._open_conn():
                    if ever_opened:
                        self.counters["reconnects"] += 1
                    ever_opened = True
                    opened_at = now
                    next_heartbeat = 0.0
                    backoff_s = config.reconnect_min_s
                else:
                    self.counters["connect_failures"] += 1
                    next_open = now + backoff_s
                    backoff_s = min(backoff_s * 2, config.reconnect_max_s)
                continue
            try:
                self._receive(timeout_s=0.005)
            except Exception:  # a broken transport or a parser surprise: recreate it
                log.exception("MAVLink receive failed; recreating the connection")
                self._transport_dead = True
            now = time.monotonic()
            health = self._check_heartbeat(now)
            with self._cond:
                silent_since = max(opened_at, self._last_hb or 0.0)
            if self._transport_dead or (
                health != "up" and now - silent_since > config.heartbeat_timeout_s
            ):
                self._close_conn()
                next_open = now + backoff_s
                backoff_s = min(backoff_s * 2, config.reconnect_max_s)
                continue
            if now >= next_heartbeat:
                next_heartbeat = now + 1.0
                self._send(
                    lambda mav: mav.heartbeat_send(
                        config.heartbeat_type,
                        mavlink.MAV_AUTOPILOT_INVALID,
                        0,
                        0,
                        mavlink.MAV_STATE_ACTIVE,
                    )
                )
            if health != "up":
                continue
            if now >= next_telemetry_request:
                next_telemetry_request = now + 2.0
                self._request_telemetry(now)
            with self._cond:
                dirty = self._target_dirty
            if dirty and now - last_setpoint >= config.setpoint_min_gap_s:
                # A new target: on the wire now, and the steady schedule restarts from here.
                next_setpoint = now + setpoint_period_s
                last_setpoint = now
                self._send_setpoint(now)
            elif now >= next_setpoint:
                next_setpoint = max(next_setpoint + setpoint_period_s, now - setpoint_period_s)
                last_setpoint = now
                self._send_setpoint(now)
            if now >= next_mode_request:
                next_mode_request = now + config.mode_retry_s
                self._request_guided_mode(now)

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

    def _receive(self, timeout_s: float) -> None:
        conn = self._conn
        message = conn.recv_match(blocking=True, timeout=timeout_s)
        count = 0
        while message is not None and count < 200:
            self._handle(message)
            count += 1
            message = conn.recv_msg()

    def _handle(self, message: Any) -> None:
        kind = message.get_type()
        now = time.monotonic()
        with self._cond:
            if kind == "HEARTBEAT":
                if message.autopilot == mavlink.MAV_AUTOPILOT_INVALID or message.type in (
                    mavlink.MAV_TYPE_GCS,
                    mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
                ):
                    return  # another ground station or companion, not the vehicle
                header = message.get_header()
                if (
                    self.config.signing_key is None
                    and getattr(header, "incompat_flags", 0) & mavlink.MAVLINK_IFLAG_SIGNED
                ):
                    # It signs, we cannot: it will most likely ignore what we send.
                    self.counters["signed_vehicle_without_key"] += 1
                self._target_sys, self._target_comp = header.srcSystem, header.srcComponent
                self._flavour = flavour_of(message.autopilot)
                self._custom_mode = message.custom_mode
                self._armed = bool(message.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self._last_hb = now
                if self._health != "up":
                    log.info("vehicle HEARTBEAT (%s): link up", self._flavour)
                    self._health = "up"
                    self._up_since = now
                    self._position_at = None
                    self._fallback_streams_sent = False
            elif kind == "LOCAL_POSITION_NED":
                self._ned = (message.x, message.y, message.z)
                self._position_at = now
            elif kind == "GLOBAL_POSITION_INT":
                self._relative_alt_m = message.relative_alt / 1000.0
                self._home_amsl_m = (message.alt - message.relative_alt) / 1000.0
            elif kind == "EXTENDED_SYS_STATE":
                self._landed_state = message.landed_state
            elif kind == "COMMAND_ACK":
                self._ack_seq += 1
                self._acks[message.command] = (self._ack_seq, message.result)
            elif kind == "BAD_DATA":
                self.counters["bad_data"] += 1
                if "signature" in str(getattr(message, "reason", "")).lower():
                    self.counters["signing_failures"] += 1
                return
            else:
                return
            self._cond.notify_all()

    def _request_telemetry(self, now: float) -> None:
        """SET_MESSAGE_INTERVAL for what we need, until positions come; ArduPilot fallback."""
        with self._cond:
            if self._position_at is not None and now - self._position_at < 1.0:
                return
            flavour = self._flavour
            use_fallback = (
                flavour == "ardupilot"
                and not self._fallback_streams_sent
                and now - self._up_since > 1.5
            )
            if use_fallback:
                self._fallback_streams_sent = True
            sys_id, comp_id = self._target_sys, self._target_comp
        rate_hz = self.config.telemetry_rate_hz
        wanted = (
            (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, rate_hz),
            (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, rate_hz),
            (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2.0),
        )
        for message_id, hz in wanted:
            self._send_command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, (message_id, 1e6 / hz))
        if use_fallback:
            log.info("no positions after SET_MESSAGE_INTERVAL: REQUEST_DATA_STREAM fallback")
            for stream in (mavlink.MAV_DATA_STREAM_POSITION, mavlink.MAV_DATA_STREAM_EXTRA3):
                self._send(
                    lambda mav, s=stream: mav.request_data_stream_send(
                        sys_id, comp_id, s, int(rate_hz), 1
                    )
                )

    def _send_setpoint(self, now: float) -> None:
        with self._cond:
            self._target_dirty = False
            if not self._streaming_now():
                self._stream_since = None
                return
            assert self._target_m is not None
            north_m, east_m, down_m = area_to_ned(*self._target_m, self.config.frames)
            sys_id, comp_id = self._target_sys, self._target_comp
            if self._stream_since is None:
                self._stream_since = now
        time_boot_ms = int((now - self._t0) * 1000) & 0xFFFFFFFF
        fields = (
            time_boot_ms,
            sys_id,
            comp_id,
            mavlink.MAV_FRAME_LOCAL_NED,
            POSITION_ONLY_TYPE_MASK,
            north_m,
            east_m,
            down_m,
            *([0.0] * 8),  # velocity, acceleration, yaw, yaw rate: ignored by the type_mask
        )
        sent = self._send(lambda mav: mav.set_position_target_local_ned_send(*fields))
        if sent:
            with self._cond:
                self.counters["setpoints_sent"] += 1

    def _request_guided_mode(self, now: float) -> None:
        """Ask for GUIDED / OFFBOARD while a target streams and the request window is open."""
        flavour = self._guided_mode_due(now)
        if flavour is None:
            return
        main = ARDUPILOT_GUIDED if flavour == "ardupilot" else PX4_MAIN_OFFBOARD
        custom = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        self._send_command_long(mavlink.MAV_CMD_DO_SET_MODE, (custom, main))

    def _send_command_long(self, command: int, params: Sequence[float]) -> bool:
        """Send COMMAND_LONG ``command`` (params padded with zeros to 7) to the vehicle."""
        values = [*params, *([0.0] * (7 - len(params)))]
        with self._cond:
            sys_id, comp_id = self._target_sys, self._target_comp
        return self._send(lambda mav: mav.command_long_send(sys_id, comp_id, command, 0, *values))

    # ------------------------------------------------------------------ arm and takeoff

    def _command(self, command: int, params: Sequence[float], deadline: float) -> None:
        """COMMAND_LONG until ACCEPTED, retrying refusals with backoff; TimeoutError at deadline."""
        backoff_s = 0.3
        last_result: int | None = None
        while not self._stop.is_set():
            if time.monotonic() > deadline:
                raise TimeoutError(f"command {command} not accepted (last result {last_result})")
            with self._cond:
                seq_before = self._ack_seq  # only an ACK newer than this answers us
                self.counters["commands_sent"] += 1
            self._send_command_long(command, params)
            ack_by = min(deadline, time.monotonic() + 1.5)
            with self._cond:
                while not self._stop.is_set():
                    seq, result = self._acks.get(command, (0, -1))
                    if seq > seq_before:
                        last_result = result
                        break
                    remaining = ack_by - time.monotonic()
                    if remaining <= 0:
                        break
                    self._cond.wait(remaining)
            if last_result == mavlink.MAV_RESULT_ACCEPTED:
                return
            self._stop.wait(min(backoff_s, max(0.0, deadline - time.monotonic())))
            backoff_s = min(backoff_s * 2, 2.0)
        raise RuntimeError("link closed")
