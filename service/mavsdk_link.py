"""The service's vehicle link on the native MAVSDK binding (``mavsdk`` >= 4, no mavsdk_server).

:class:`MavsdkLink` is a second backend behind the interface of
:class:`service.mavlink_link.MavlinkLink`, for PX4 users who already run MAVSDK: the same
:class:`~service.mavlink_link.LinkConfig` in, the same :class:`~service.mavlink_link.LinkState` out,
the same methods (``start``, ``close``, ``state``, ``set_target``, ``clear_target``,
``arm_and_takeoff``) with the same meaning::

    link = MavsdkLink(LinkConfig("udpin:0.0.0.0:14540", area=AreaConfig()))
    link.start()
    link.arm_and_takeoff().result(timeout=60)
    link.set_target((250.0, 250.0, 50.0))   # area frame; clamped to the geofence
    print(link.state())
    link.close()

How it maps onto MAVSDK:

* the connection string is a pymavlink one (``tcp:HOST:PORT``, ``udpin:HOST:PORT``,
  ``udpout:HOST:PORT``, ``/dev/ttyUSB0,57600``), translated by :func:`mavsdk_url`; MAVSDK URLs
  (``udpin://0.0.0.0:14540``) pass through. MAVSDK sends our HEARTBEAT (system and component
  ids from the config; type GCS or, for anything else, MAVSDK's companion computer).
* the vehicle's HEARTBEATs come through the MavlinkDirect plugin and are decoded exactly as the
  pymavlink backend decodes them (flavour, mode names, armed, link health, heartbeat age);
  positions come from the Telemetry plugin (``position_velocity_ned``, ``position``), at
  ``telemetry_rate_hz`` asked with Telemetry's ``set_rate_*``.
* setpoints: the Offboard plugin's ``set_position_ned`` is called at ``setpoint_rate_hz`` while a
  target streams. MAVSDK itself also re-sends the latest setpoint every 50 ms (20 Hz) while its
  offboard stream is active, so the vehicle sees about ``max(setpoint_rate_hz, 20)`` setpoints a
  second; ``counters["setpoints_sent"]`` counts the link's own calls. MAVSDK always sends a yaw
  with a position setpoint, so the link sends the heading the vehicle had when the stream started
  (it does not turn the vehicle).
* mode: OFFBOARD the PX4 way: the stream first, then ``Offboard.start`` after
  ``px4_stream_lead_s``, retried every ``mode_retry_s`` during ``mode_request_window_s`` after a
  :meth:`MavsdkLink.set_target` (on ArduPilot MAVSDK maps it to GUIDED).
* :meth:`MavsdkLink.clear_target` stops the stream without a mode change, as the pymavlink
  backend does, so that the vehicle's own offboard-loss failsafe acts (``Offboard.stop`` would
  also switch to Hold). MAVSDK has no call for that, so the Offboard plugin is dropped and made
  anew, which ends its re-sending.
* arm and takeoff: the shared take-off sequence (:meth:`VehicleLinkBase.arm_and_takeoff`);
  arming through the Action plugin; the takeoff as MAV_CMD_NAV_TAKEOFF through MavlinkDirect,
  with the params of :mod:`service.mavlink_commands` (NaN as JSON null), as the pymavlink
  backend sends it. The vehicle's STATUSTEXTs come from Telemetry's ``status_text``. This
  backend (meant for PX4) does not subscribe to ArduPilot's EKF_STATUS_REPORT: on ArduPilot it
  waits for LOCAL_POSITION_NED only, and ArduCopter's arming refusals until its EKF uses GPS are
  retried with backoff. ``Action.takeoff`` is not used: on PX4 it climbs to MIS_TAKEOFF_ALT, and
  ``Action.set_takeoff_altitude`` would rewrite that vehicle parameter, which a service must not
  do behind the operator's back.
* link loss: no vehicle HEARTBEAT for ``heartbeat_timeout_s`` -> ``link_lost``, streaming stops,
  the MAVSDK instance is dropped and made anew with backoff (``reconnect_min_s`` to
  ``reconnect_max_s``); the latest target streams again once the vehicle is back.

Not supported: **MAVLink 2 signing**. The native binding (mavsdk 4.1) exposes no signing call
(none in its Python API nor among libcmavsdk's exported functions; MAVSDK declined to plan it in
mavlink/MAVSDK#1060), so a ``signing_key`` in the config raises ValueError naming it: use the
``pymavlink`` backend for a signed link.

All MAVSDK calls happen in this module's threads, never in the caller's; MAVSDK's callbacks only
update the snapshot under a condition variable, and no MAVSDK call is made while holding it (a
MAVSDK unsubscribe waits for a running callback, which may be waiting for that lock). Tearing a
session down (link loss, close) first waits, up to ``UNANSWERED_WAIT_S``, for MAVSDK to answer the
asynchronous calls still in flight (an ``Offboard.start`` is asked for every ``mode_retry_s``),
and keeps their ctypes callbacks alive until the instance is destroyed: destroying the plugins
with a command in flight crashed the process natively (SIGSEGV inside the plugins' destroy; see
``benchmarks/mavsdk_link_loss.py``). MAVSDK's own log lines are queued by its callback and logged
from a thread of ours (:func:`route_mavsdk_logs_to_python`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Self

from service.frames import area_to_ned
from service.mavlink_link import (
    LinkConfig,
    LinkHealth,
    VehicleLinkBase,
    flavour_of,
    mavlink,
)

log = logging.getLogger(__name__)

MAV_COMP_ID_AUTOPILOT1 = 1
COMMAND_ACK_TIMEOUT_S = 5.0
"""How long a command may wait for MAVSDK's answer (MAVSDK retransmits within it)."""
ACTION_RESULTS = {
    "COMMAND_DENIED": mavlink.MAV_RESULT_DENIED,
    "COMMAND_DENIED_NOT_LANDED": mavlink.MAV_RESULT_DENIED,
    "COMMAND_DENIED_LANDED_STATE_UNKNOWN": mavlink.MAV_RESULT_DENIED,
    "TIMEOUT": None,
    "NO_SYSTEM": None,
    "CONNECTION_ERROR": None,
    "BUSY": mavlink.MAV_RESULT_TEMPORARILY_REJECTED,
    "UNSUPPORTED": mavlink.MAV_RESULT_UNSUPPORTED,
}
"""MAVSDK's ActionResult names for a refused arming, as the MAV_RESULT they stand for (None: no
answer); any other refusal counts as MAV_RESULT_FAILED."""
UNANSWERED_WAIT_S = 3.0
"""How long closing a session waits for MAVSDK to answer the calls still open. MAVSDK answers an
unacknowledged command with a timeout after its own retries (3 tries by default); this bound is
meant to leave room for that, not to be reached."""
SIGNING_UNSUPPORTED = (
    "signing_key: the mavsdk backend cannot sign MAVLink 2 (the native mavsdk binding has no "
    "signing API); use mavlink_backend 'pymavlink' for a signed link, or no key"
)


_MAVSDK_LOG_LEVELS = (logging.DEBUG, logging.DEBUG, logging.INFO, logging.WARNING)
"""MAVSDK's levels (debug, info, warn, err) one step down: it reports every failed connection
attempt as an error, and the link retries an unreachable vehicle for as long as it runs (its own
state says so)."""
_mavsdk_log_lines: queue.SimpleQueue[tuple[int, str, str | None, int]] = queue.SimpleQueue()


def _queue_mavsdk_log_line(level: int, message: str, file: str | None, line: int) -> bool:
    """MAVSDK's log callback, called on MAVSDK's own native threads: only queues the line."""
    _mavsdk_log_lines.put((int(level), message, file, line))
    return True  # MAVSDK does not print it itself


def _log_mavsdk_lines() -> None:
    """The ``mavsdk-log`` thread: logs the queued lines to the ``mavsdk`` logger."""
    logger = logging.getLogger("mavsdk")
    while True:
        level, message, file, line = _mavsdk_log_lines.get()
        logger.log(_MAVSDK_LOG_LEVELS[min(max(level, 0), 3)], "%s (%s:%d)", message, file, line)


_log_thread: threading.Thread | None = None
_log_route_lock = threading.Lock()


def route_mavsdk_logs_to_python() -> None:
    """Send MAVSDK's own log lines to the ``mavsdk`` Python logger instead of stdout.

    MAVSDK has one process-wide log callback; this installs ours only when nobody installed one
    (an application that subscribed its own keeps it). :meth:`MavsdkLink.start` calls it.
    MAVSDK calls the callback on its own threads, in the middle of its I/O and of its teardown;
    the callback only queues the line, and a daemon thread of ours hands it to ``logging``, so
    no logging handler (file or stream I/O, locks) ever runs on a MAVSDK thread.
    """
    import mavsdk.logging as mavsdk_logging

    global _log_thread
    with _log_route_lock:
        if getattr(mavsdk_logging, "_log_callback_ref", None) is not None:
            return
        if _log_thread is None:
            _log_thread = threading.Thread(target=_log_mavsdk_lines, name="mavsdk-log", daemon=True)
            _log_thread.start()
        mavsdk_logging.log_subscribe(_queue_mavsdk_log_line)


def mavsdk_url(url: str) -> str:
    """A MAVSDK connection URL for a pymavlink connection string (MAVSDK URLs pass through).

    ``tcp:H:P`` -> ``tcpout://H:P`` (client); ``tcpin:H:P`` -> ``tcpin://H:P`` (server);
    ``udpin:H:P`` and ``udp:H:P`` -> ``udpin://H:P``; ``udpout:H:P`` -> ``udpout://H:P``;
    a serial device ``/dev/ttyUSB0`` or ``/dev/ttyUSB0,921600`` -> ``serial:///dev/ttyUSB0:921600``
    (57600 baud when none is given). ValueError for anything else.
    """
    text = url.strip()
    if "://" in text:
        return text
    if text.startswith(("/", "COM")):
        device, _, baud = text.partition(",")
        baud = baud or "57600"
        if not baud.isdigit():
            raise ValueError(f"url: bad baud rate in {url!r}")
        return f"serial://{device}:{baud}"
    scheme, sep, rest = text.partition(":")
    schemes = {
        "tcp": "tcpout",
        "tcpout": "tcpout",
        "tcpin": "tcpin",
        "udp": "udpin",
        "udpin": "udpin",
        "udpout": "udpout",
    }
    host, _, port = rest.rpartition(":")
    if not sep or scheme.lower() not in schemes or not host or not port.isdigit():
        raise ValueError(
            f"url: expected tcp:HOST:PORT, udpin:HOST:PORT, udpout:HOST:PORT, a serial device "
            f"or a MAVSDK URL, got {url!r}"
        )
    return f"{schemes[scheme.lower()]}://{host}:{port}"


@dataclass
class _Session:
    """One MAVSDK instance, its connection and (once the vehicle is found) its plugins."""

    sdk: Any
    opened_at: float
    system: Any = None
    system_id: int | None = None
    telemetry: Any = None
    action: Any = None
    offboard: Any = None
    direct: Any = None
    offboard_fed: bool = False
    """The Offboard plugin got a setpoint since it was made (so MAVSDK may be re-sending it)."""
    keep: list[Any] = field(default_factory=list)
    """Objects to ``destroy()`` after the instance (its Configuration)."""
    trampolines: list[Any] = field(default_factory=list)
    """The ctypes callbacks of asynchronous calls MAVSDK may still answer (a command waiting
    for its ACK or timeout). A plugin's ``destroy()`` drops its own, but MAVSDK's threads run
    until the instance itself is destroyed: a late answer into a dropped one is a native crash.
    Held here until then."""
    unanswered: int = 0
    """Asynchronous calls made through :meth:`call_async` that MAVSDK has not answered yet."""
    answered: threading.Condition = field(default_factory=threading.Condition)

    def hold_callbacks(self, plugin: Any) -> None:
        """Keep ``plugin``'s pending callbacks alive past its ``destroy()`` (see ``trampolines``;
        the binding keeps them in ``_callbacks``)."""
        self.trampolines.extend(getattr(plugin, "_callbacks", ()))

    def call_async(self, start: Callable[[Callable[..., None]], None], callback: Callable) -> None:
        """``start(answer)``: an asynchronous MAVSDK call whose answer goes to ``callback``,
        counted in ``unanswered`` until it comes (see :meth:`wait_answered`)."""
        once = threading.Lock()

        def answer(*args: Any) -> None:
            try:
                callback(*args)
            finally:
                if once.acquire(blocking=False):
                    self._answered_one()

        with self.answered:
            self.unanswered += 1
        try:
            start(answer)
        except BaseException:
            if once.acquire(blocking=False):
                self._answered_one()
            raise

    def _answered_one(self) -> None:
        with self.answered:
            self.unanswered -= 1
            self.answered.notify_all()

    def wait_answered(self, timeout_s: float) -> bool:
        """Wait until MAVSDK has answered every :meth:`call_async` (a command it gave up on is
        answered too, with a timeout), at most ``timeout_s``; False if some are still open."""
        with self.answered:
            return self.answered.wait_for(lambda: self.unanswered == 0, timeout_s)


class MavsdkLink(VehicleLinkBase):
    """The vehicle link and setpoint streamer on MAVSDK. See the module docstring."""

    _thread_name = "mavsdk-link"

    def __init__(self, config: LinkConfig) -> None:
        if config.signing_key is not None:
            raise ValueError(SIGNING_UNSUPPORTED)
        super().__init__(config)
        self.mavsdk_url = mavsdk_url(config.url)
        self._sdk_lock = threading.RLock()
        self._session: _Session | None = None
        self._heading_deg: float | None = None
        self._stream_yaw_deg = 0.0

    def start(self) -> Self:
        """Start the I/O thread (returns at once; the link comes up in the background)."""
        route_mavsdk_logs_to_python()
        return super().start()

    def _release(self) -> None:
        self._close_session()

    # ------------------------------------------------------------------ the MAVSDK session

    def _open_session(self, now: float) -> bool:
        from mavsdk import ComponentType, Configuration, Mavsdk

        config = self.config
        component_type = (
            ComponentType.GROUND_STATION
            if config.heartbeat_type == mavlink.MAV_TYPE_GCS
            else ComponentType.COMPANION_COMPUTER
        )
        configuration = Configuration.create_with_component_type(component_type)
        configuration.system_id = config.source_system
        configuration.component_id = config.source_component
        sdk = Mavsdk(configuration)
        try:
            sdk.add_any_connection_with_handle(self.mavsdk_url)
        except Exception as exc:  # MAVSDK's ConnectionError: refused, cannot bind, ...
            log.debug("cannot open %s: %s", self.mavsdk_url, exc)
            sdk.destroy()
            configuration.destroy()
            return False
        with self._sdk_lock:
            self._session = _Session(sdk, now, keep=[configuration])
        log.info("MAVSDK connection open: %s", self.mavsdk_url)
        return True

    def _close_session(self) -> None:
        with self._sdk_lock:
            session, self._session = self._session, None
            if session is None:
                return
            # Destroying a plugin whose command MAVSDK has not answered yet can crash MAVSDK
            # when the answer (or the timeout) comes: let them finish first.
            if not session.wait_answered(UNANSWERED_WAIT_S):
                log.debug("closing the MAVSDK session with %d calls unanswered", session.unanswered)
            for plugin in (session.telemetry, session.action, session.offboard, session.direct):
                session.hold_callbacks(plugin)
            with contextlib.suppress(Exception):
                session.sdk.destroy()  # joins MAVSDK's threads: no callback comes after it
            session.trampolines.clear()
            for item in session.keep:
                with contextlib.suppress(Exception):
                    item.destroy()

    def _find_vehicle(self, session: _Session) -> None:
        """Once MAVSDK has seen an autopilot: make the plugins and subscribe."""
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.telemetry import Telemetry

        with self._sdk_lock:
            if self._session is not session:
                return
            system = session.sdk.first_autopilot(0.05)
            if system is None:
                return
            session.system = system
            session.system_id = system.get_system_id()
            session.telemetry = Telemetry(system)
            session.action = Action(system)
            session.offboard = Offboard(system)
            session.direct = MavlinkDirect(system)
            session.direct.subscribe_message("HEARTBEAT", self._on_heartbeat, session.system_id)
            session.telemetry.subscribe_position_velocity_ned(self._on_position_ned)
            session.telemetry.subscribe_position(self._on_position)
            session.telemetry.subscribe_heading(self._on_heading)
            session.telemetry.subscribe_status_text(self._on_status_text)
            self._request_telemetry(session)
        log.info("MAVSDK found autopilot system %s", session.system_id)

    def _request_telemetry(self, session: _Session) -> None:
        rate_hz = self.config.telemetry_rate_hz
        telemetry = session.telemetry
        for name in ("set_rate_position_velocity_ned_async", "set_rate_position_async"):
            session.call_async(
                lambda answer, name=name: getattr(telemetry, name)(rate_hz, answer),
                self._on_rate_result,
            )

    @staticmethod
    def _on_rate_result(result: Any, _user_data: Any) -> None:
        log.debug("telemetry rate request: %s", getattr(result, "name", result))

    # ------------------------------------------------------------------ MAVSDK callbacks

    def _on_heartbeat(self, message: Any, system_id: int) -> None:
        try:
            fields = json.loads(message.fields_json)
            autopilot = int(fields["autopilot"])
            vehicle_type = int(fields["type"])
            base_mode = int(fields["base_mode"])
            custom_mode = int(fields["custom_mode"])
        except (ValueError, KeyError, TypeError):
            with self._cond:
                self.counters["bad_data"] += 1
            return
        if (
            message.system_id != system_id
            or message.component_id != MAV_COMP_ID_AUTOPILOT1
            or autopilot == mavlink.MAV_AUTOPILOT_INVALID
            or vehicle_type in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER)
        ):
            return
        now = time.monotonic()
        with self._cond:
            self._flavour = flavour_of(autopilot)
            self._custom_mode = custom_mode
            self._armed = bool(base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self._last_hb = now
            if self._health != "up":
                log.info("vehicle HEARTBEAT (%s): link up", self._flavour)
                self._health = "up"
            self._cond.notify_all()

    def _on_position_ned(self, position_velocity: Any, _user_data: Any) -> None:
        p = position_velocity.position
        with self._cond:
            self._ned = (p.north_m, p.east_m, p.down_m)
            self._position_at = time.monotonic()
            self._cond.notify_all()

    def _on_position(self, position: Any, _user_data: Any) -> None:
        relative_m = position.relative_altitude_m
        absolute_m = position.absolute_altitude_m
        if not (math.isfinite(relative_m) and math.isfinite(absolute_m)):
            return
        with self._cond:
            self._relative_alt_m = relative_m
            self._home_amsl_m = absolute_m - relative_m
            self._cond.notify_all()

    def _on_status_text(self, status_text: Any, _user_data: Any) -> None:
        # MAVSDK's StatusTextType names are MAV_SEVERITY's without the prefix.
        name = getattr(status_text.type, "name", "")
        severity = getattr(mavlink, f"MAV_SEVERITY_{name}", mavlink.MAV_SEVERITY_INFO)
        self._note_status_text(severity, status_text.text)

    def _on_heading(self, heading: Any, _user_data: Any) -> None:
        if math.isfinite(heading.heading_deg):
            with self._cond:
                self._heading_deg = heading.heading_deg

    # ------------------------------------------------------------------ the I/O loop

    def _run(self) -> None:
        config = self.config
        backoff_s = config.reconnect_min_s
        next_open = 0.0
        ever_opened = False
        next_setpoint = 0.0
        next_mode_request = 0.0
        setpoint_period_s = 1.0 / config.setpoint_rate_hz
        last_setpoint = -math.inf
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                self._check_heartbeat(now)
                session = self._session
                if session is None:
                    if now < next_open:
                        self._stop.wait(min(0.05, next_open - now))
                        continue
                    if self._open_session(now):
                        if ever_opened:
                            self.counters["reconnects"] += 1
                        ever_opened = True
                        backoff_s = config.reconnect_min_s
                    else:
                        self.counters["connect_failures"] += 1
                        next_open = now + backoff_s
                        backoff_s = min(backoff_s * 2, config.reconnect_max_s)
                    continue
                if session.system is None:
                    self._find_vehicle(session)
                health = self._check_heartbeat(now)
                with self._cond:
                    silent_since = max(session.opened_at, self._last_hb or 0.0)
                if health != "up" and now - silent_since > config.heartbeat_timeout_s:
                    if silent_since == session.opened_at:
                        # MAVSDK accepts a connection it cannot make yet (it retries by
                        # itself), so a session that never heard the vehicle is the failure.
                        self.counters["connect_failures"] += 1
                    log.info("no vehicle on %s: making the MAVSDK connection anew", self.mavsdk_url)
                    self._close_session()
                    next_open = now + backoff_s
                    backoff_s = min(backoff_s * 2, config.reconnect_max_s)
                    continue
                can_send = health == "up" and session.system is not None
                if can_send:
                    with self._cond:
                        dirty = self._target_dirty
                    if dirty and now - last_setpoint >= config.setpoint_min_gap_s:
                        # A new target: out now, and the steady schedule restarts from here.
                        next_setpoint = now + setpoint_period_s
                        last_setpoint = now
                        self._send_setpoint(session, now)
                    elif now >= next_setpoint:
                        next_setpoint = max(
                            next_setpoint + setpoint_period_s, now - setpoint_period_s
                        )
                        last_setpoint = now
                        self._send_setpoint(session, now)
                    if now >= next_mode_request:
                        next_mode_request = now + config.mode_retry_s
                        self._request_guided_mode(session, now)
                if health == "up":
                    wake_at = min(next_setpoint, next_mode_request)
                    with self._cond:
                        if can_send and self._target_dirty:
                            wake_at = min(wake_at, last_setpoint + config.setpoint_min_gap_s)
                        wait_s = wake_at - time.monotonic()
                        if not self._stop.is_set():  # set_target notifies: a new target wakes us
                            self._cond.wait(min(max(wait_s, 0.001), 0.05))
                else:
                    self._stop.wait(0.05)
        except Exception:
            log.exception("MAVSDK link thread failed")
            raise
        finally:
            self._close_session()

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

    def _send_setpoint(self, session: _Session, now: float) -> None:
        from mavsdk.plugins.offboard import PositionNedYaw

        with self._cond:
            self._target_dirty = False
            streaming = self._streaming_now()
            if not streaming:
                self._stream_since = None
            else:
                assert self._target_m is not None
                north_m, east_m, down_m = area_to_ned(*self._target_m, self.config.frames)
                if self._stream_since is None:
                    self._stream_since = now
                    self._stream_yaw_deg = self._heading_deg or 0.0
                yaw_deg = self._stream_yaw_deg
        if not streaming:
            if session.offboard_fed:
                self._drop_offboard_stream(session)
            return
        setpoint = PositionNedYaw(north_m, east_m, down_m, yaw_deg)
        with self._sdk_lock:
            if self._session is not session or session.offboard is None:
                return
            try:
                session.offboard.set_position_ned(setpoint)
            except Exception as exc:  # OffboardError: no system, connection error
                self.counters["setpoint_errors"] += 1
                log.debug("set_position_ned failed: %s", exc)
                return
            session.offboard_fed = True
        with self._cond:
            self.counters["setpoints_sent"] += 1

    def _drop_offboard_stream(self, session: _Session) -> None:
        """End MAVSDK's own re-sending without a mode change: a fresh Offboard plugin."""
        from mavsdk.plugins.offboard import Offboard

        with self._sdk_lock:
            if self._session is not session or session.system is None:
                return
            session.hold_callbacks(session.offboard)  # an Offboard.start may be pending
            session.offboard.destroy()
            session.offboard = Offboard(session.system)
            session.offboard_fed = False
        log.info("setpoint stream stopped")

    def _request_guided_mode(self, session: _Session, now: float) -> None:
        """``Offboard.start`` while a target streams and the request window is open (PX4: only
        after the stream has run ``px4_stream_lead_s``)."""
        if self._guided_mode_due(now) is None:
            return
        with self._sdk_lock:
            if self._session is not session or not session.offboard_fed:
                return
            session.call_async(session.offboard.start_async, self._on_offboard_start)

    @staticmethod
    def _on_offboard_start(result: Any, _user_data: Any) -> None:
        log.debug("offboard start: %s", getattr(result, "name", result))

    # ------------------------------------------------------------------ commands

    def _request(
        self, start: Callable[[_Session, Callable[..., None]], None], timeout_s: float
    ) -> tuple[Any, ...] | None:
        """Issue an asynchronous MAVSDK call on the current session; its callback's arguments,
        or None when there is no vehicle, the session goes away or ``timeout_s`` passes."""
        done = threading.Event()
        answer: list[tuple[Any, ...]] = []

        def callback(*args: Any) -> None:
            answer.append(args)
            done.set()

        with self._sdk_lock:
            session = self._session
            if session is None or session.system is None:
                return None
            session.call_async(lambda answer: start(session, answer), callback)
        deadline = time.monotonic() + timeout_s
        while not done.wait(0.1):
            if self._stop.is_set() or time.monotonic() > deadline or self._session is not session:
                return None
        return answer[0]

    def _send_command(self, command: int, params: Sequence[float], timeout_s: float) -> int | None:
        """COMMAND_LONG through MavlinkDirect; the MAV_RESULT of its final ACK, or None."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirectResult, MavlinkMessage

        values = list(params)
        with self._sdk_lock:
            session = self._session
            system_id = session.system_id if session is not None else None
        if system_id is None:
            return None
        fields: dict[str, Any] = {
            "target_system": system_id,
            "target_component": MAV_COMP_ID_AUTOPILOT1,
            "command": command,
            "confirmation": 0,
        }
        for index, value in enumerate(values, start=1):
            fields[f"param{index}"] = value if math.isfinite(value) else None  # null is NaN
        message = MavlinkMessage(
            "COMMAND_LONG", 0, 0, system_id, MAV_COMP_ID_AUTOPILOT1, json.dumps(fields)
        )
        answer = self._request(
            lambda s, cb: s.direct.send_command_async(message, lambda r, ack, _ud: cb(r, ack)),
            timeout_s,
        )
        if answer is None:
            return None
        result, ack = answer
        if result != MavlinkDirectResult.SUCCESS:
            log.debug("command %d: %s", command, getattr(result, "name", result))
            return None
        try:
            return int(json.loads(ack.fields_json)["result"])
        except (ValueError, KeyError, TypeError):
            return None

    def _ask_arm(self, timeout_s: float) -> int | None:
        """Arm through the Action plugin: MAV_RESULT_ACCEPTED, the MAV_RESULT MAVSDK's answer
        stands for when refused, or None when no answer came."""
        from mavsdk.plugins.action import ActionResult

        with self._cond:
            self.counters["commands_sent"] += 1
        answer = self._request(lambda s, cb: s.action.arm_async(lambda r, _ud: cb(r)), timeout_s)
        if answer is None:
            return None
        if answer[0] == ActionResult.SUCCESS:
            return mavlink.MAV_RESULT_ACCEPTED
        log.debug("arm: %s", getattr(answer[0], "name", answer[0]))
        return ACTION_RESULTS.get(getattr(answer[0], "name", ""), mavlink.MAV_RESULT_FAILED)

    def _ask(self, command: int, params: Sequence[float], timeout_s: float) -> int | None:
        with self._cond:
            self.counters["commands_sent"] += 1
        return self._send_command(command, params, timeout_s)
