"""The vehicle link on the native MAVSDK binding (``mavsdk`` >= 4, no mavsdk_server).

:class:`MavsdkLink` is the second backend behind :class:`~service.vehicle_link.VehicleLink`, for
PX4 users who already run MAVSDK: the same :class:`~service.vehicle_link.LinkConfig` in, the same
:class:`~service.vehicle_link.LinkState` out, the same methods with the same meaning::

    link = MavsdkLink(LinkConfig("udpin:0.0.0.0:14540", area=AreaConfig()))
    link.start()
    link.arm_and_takeoff().result(timeout=60)
    link.set_target((250.0, 250.0, 50.0))   # area frame; clamped to the geofence
    print(link.state())
    link.close()

The loop, heartbeat supervision, setpoint schedule, mode-request window and take-off sequence are
:class:`~service.vehicle_link.VehicleLinkBase`'s; this module maps its hooks onto MAVSDK:

* the connection string is a pymavlink one, translated by
  :func:`~service.mavsdk_session.mavsdk_url` (MAVSDK URLs pass through); one MAVSDK instance per
  connection (:class:`~service.mavsdk_session.Session`). MAVSDK sends our HEARTBEAT (system and
  component ids from the config; type GCS or, for anything else, MAVSDK's companion computer).
  MAVSDK accepts any URL and retries by itself, so a connection that never hears the vehicle
  within ``heartbeat_timeout_s`` counts as a failed one and is made anew with backoff.
* which system: the first autopilot MAVSDK discovers, until the vehicle's HEARTBEAT locks its
  system and component for the link's lifetime; a session made anew after a loss drives only
  that system, whatever other autopilots MAVSDK discovers (:meth:`MavsdkLink._pick_vehicle`).
  MAVSDK routes a system's messages to that system's plugins only, so other systems never reach
  the link; but its plugins take a system's telemetry from any of its components, which only
  the ``udpin`` path below can filter.
* ``udpin`` (PX4's 14540): MAVSDK's own UDP server sends everything to every address it has
  heard from, so a ``udpin`` session is instead a MAVSDK ``raw://`` connection over the link's
  own socket (:class:`~service.mavsdk_session.PeerUdp`): it sends to the vehicle's address only,
  drops other senders' datagrams unread (``foreign_datagrams``) and other systems' and
  components' packets (``foreign_messages``), and keeps nothing per sender. Over ``tcp`` and
  serial MAVSDK connects itself (one peer by construction); over ``udpout`` too, and there it
  also sends to anyone who sends to its ephemeral port (use ``tcp``, ``udpin`` or the pymavlink
  backend where that matters).
* the vehicle's HEARTBEATs come through the MavlinkDirect plugin, decoded by the base as the
  pymavlink backend's are; positions come from the Telemetry plugin (``position_velocity_ned``,
  ``position``), at ``telemetry_rate_hz`` asked once per connection with ``set_rate_*``, and the
  battery (``battery``) at :data:`BATTERY_RATE_HZ`; the
  vehicle's STATUSTEXTs from Telemetry's ``status_text``.
* setpoints: the Offboard plugin's ``set_position_ned``. MAVSDK itself also re-sends the latest
  setpoint every 50 ms (20 Hz) while its offboard stream is active, so the vehicle sees about
  ``max(setpoint_rate_hz, 20)`` setpoints a second; ``counters["setpoints_sent"]`` counts the
  link's own calls. MAVSDK always sends a yaw with a position setpoint, so the link sends the
  heading the vehicle had when the stream started (it does not turn the vehicle).
* the autopilot's fence (``autopilot_fence``): MAVSDK's Geofence plugin uploads the polygons
  and downloads them for comparison, its Param plugin sets and reads back the ceiling and the
  breach action (:mod:`service.mavsdk_fence`); the vehicle's origin comes from GPS_GLOBAL_ORIGIN
  through MavlinkDirect, asked for with MAV_CMD_REQUEST_MESSAGE.
* mode: ``Offboard.start`` (on ArduPilot MAVSDK maps it to GUIDED), when the base asks for it.
* :meth:`~service.vehicle_link.VehicleLink.clear_target` stops the stream without a mode change,
  as the pymavlink backend does, so that the vehicle's own offboard-loss failsafe acts. MAVSDK
  has no call for that, so the Offboard plugin is made anew, which ends its re-sending.
* take-off: arming through the Action plugin; MAV_CMD_NAV_TAKEOFF and DO_SET_MODE as COMMAND_LONG
  through MavlinkDirect, with the params of :mod:`service.mavlink_commands` (NaN as JSON null).
  This backend (meant for PX4) does not subscribe to ArduPilot's EKF_STATUS_REPORT: on ArduPilot
  it waits for LOCAL_POSITION_NED only, and ArduCopter's arming refusals until its EKF uses GPS
  are retried with backoff. ``Action.takeoff`` is not used: on PX4 it climbs to
  MIS_TAKEOFF_ALT, and ``Action.set_takeoff_altitude`` would rewrite that vehicle parameter,
  which a service must not do behind the operator's back.

Not supported: **MAVLink 2 signing**. The native binding (mavsdk 4.1) exposes no signing call
(none in its Python API nor among libcmavsdk's exported functions; MAVSDK declined to plan it in
mavlink/MAVSDK#1060), so a ``signing_key`` in the config raises ValueError naming it: use the
``pymavlink`` backend for a signed link; a link other machines can reach is warned about at
start. Without signing, a sender that copies the vehicle's ids (from its address, or from
anywhere before the vehicle is found) cannot be told from it, on either backend.

All MAVSDK calls happen in this module's threads, never in the caller's; MAVSDK's callbacks only
update the snapshot under a condition variable, and no MAVSDK call is made while holding it (a
MAVSDK unsubscribe waits for a running callback, which may be waiting for that lock). How a
session is torn down safely is :mod:`service.mavsdk_session`'s business.
"""

from __future__ import annotations

import json
import logging
import math
import select
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Self

from service.fence import FencePlan
from service.frames import GeoPoint
from service.mavlink_link import warn_if_unsigned
from service.mavsdk_fence import apply_fence_plan_mavsdk
from service.mavsdk_session import Session, mavsdk_url, route_mavsdk_logs_to_python
from service.mission_protocol import FenceReport, MissionError
from service.modes import Flavour
from service.vehicle_link import LinkConfig, VehicleLinkBase, mavlink

log = logging.getLogger(__name__)

MAV_COMP_ID_AUTOPILOT1 = 1
RAW_WAIT_S = 0.005
"""``udpin``: the longest a poll waits for a datagram (a new target goes out within a few ms)."""
BATTERY_RATE_HZ = 1.0
"""The battery's rate asked for (BATTERY_STATUS): ArduPilot sends none on a link that does not
ask, and the battery reserve needs it."""
FENCE_CALL_TIMEOUT_S = 30.0
"""The longest one fence call (upload, download, one parameter) may take; MAVSDK's own retries
end well before it."""
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
SIGNING_UNSUPPORTED = (
    "signing_key: the mavsdk backend cannot sign MAVLink 2 (the native mavsdk binding has no "
    "signing API); use mavlink_backend 'pymavlink' for a signed link, or no key"
)


class MavsdkLink(VehicleLinkBase):
    """The vehicle link and setpoint streamer on MAVSDK. See the module docstring."""

    _thread_name = "mavsdk-link"
    _silence_is_connect_failure = True

    def __init__(self, config: LinkConfig) -> None:
        if config.signing_key is not None:
            raise ValueError(SIGNING_UNSUPPORTED)
        super().__init__(config)
        self.mavsdk_url = mavsdk_url(config.url)
        self._sdk_lock = threading.RLock()  # held by every MAVSDK call on the session
        self._session: Session | None = None
        self._heading_deg: float | None = None
        self._stream_yaw_deg = 0.0
        self.counters["foreign_messages"] = 0
        self.counters["foreign_datagrams"] = 0

    def start(self) -> Self:
        """Start the I/O thread (returns at once; the link comes up in the background); a
        WARNING first if other machines can reach the link (this backend never signs)."""
        warn_if_unsigned(self.config.url, False, "mavsdk")
        route_mavsdk_logs_to_python()
        return super().start()

    # ------------------------------------------------------------------ the MAVSDK session

    def _open_transport(self, now: float) -> bool:
        session = Session.open(self.mavsdk_url, self.config, now)
        if session is None:
            return False
        with self._sdk_lock:
            self._session = session
        log.info("MAVSDK connection open: %s", self.mavsdk_url)
        return True

    def _transport_open(self) -> bool:
        return self._session is not None

    def _close_transport(self) -> None:
        with self._sdk_lock:
            session, self._session = self._session, None
            if session is not None:
                session.close()

    def _poll(self, wait_s: float) -> None:
        """Callbacks bring the input: wait for one (or a new target), or on ``udpin`` for a
        datagram to hand to MAVSDK; then look for the vehicle if MAVSDK has not seen it yet."""
        session = self._session
        if session is not None and session.udp is not None:
            self._feed(session, min(wait_s, RAW_WAIT_S))
        else:
            with self._cond:
                if not self._stop.is_set():  # close() and set_target() notify: they wake us
                    self._cond.wait(wait_s)
        if session is not None and session.system is None:
            self._find_vehicle(session)

    def _feed(self, session: Session, wait_s: float) -> None:
        """``udpin``: hand what the vehicle sent (anyone, before it is found) to MAVSDK, waiting
        up to ``wait_s`` for it; datagrams from other addresses (``foreign_datagrams``) and
        packets of other systems or components (``foreign_messages``) are dropped."""
        udp = session.udp
        assert udp is not None
        if not select.select([udp], [], [], max(wait_s, 0.0))[0]:
            return
        with self._sdk_lock:
            if self._session is not session:
                return
            for datagram in udp.read():
                session.sdk.pass_received_raw_bytes(datagram)
            dropped, udp.foreign_datagrams = udp.foreign_datagrams, 0
            foreign, udp.foreign_packets = udp.foreign_packets, 0
        if dropped or foreign:
            with self._cond:
                self.counters["foreign_datagrams"] += dropped
                self.counters["foreign_messages"] += foreign

    def _ready_to_command(self) -> bool:
        session = self._session
        return session is not None and session.system is not None

    def _find_vehicle(self, session: Session) -> None:
        """Once MAVSDK has seen an autopilot: make the plugins, subscribe, ask for rates."""
        with self._sdk_lock:
            if self._session is not session:
                return
            system = self._pick_vehicle(session)
            if system is None:
                return
            if session.udp is not None and not session.udp.choose_peer(
                system.get_system_id(), MAV_COMP_ID_AUTOPILOT1
            ):
                return  # its HEARTBEAT's address is not known (yet): look again
            session.make_plugins(system)
            session.direct.subscribe_message("HEARTBEAT", self._on_heartbeat, session.system_id)
            session.direct.subscribe_message(
                "GPS_GLOBAL_ORIGIN", self._on_origin, session.system_id
            )
            session.telemetry.subscribe_position_velocity_ned(self._on_position_ned)
            session.telemetry.subscribe_position(self._on_position)
            session.telemetry.subscribe_heading(self._on_heading)
            session.telemetry.subscribe_battery(self._on_battery)
            session.telemetry.subscribe_status_text(self._on_status_text)
            rate_hz, telemetry = self.config.telemetry_rate_hz, session.telemetry
            for name, rate in (
                ("set_rate_position_velocity_ned_async", rate_hz),
                ("set_rate_position_async", rate_hz),
                ("set_rate_battery_async", BATTERY_RATE_HZ),
            ):
                session.call_async(
                    lambda answer, name=name, rate=rate: getattr(telemetry, name)(rate, answer),
                    self._on_answer,
                )
        log.info("MAVSDK found autopilot system %s", session.system_id)

    def _pick_vehicle(self, session: Session) -> Any:
        """The MAVSDK system to drive on ``session``, None while there is none: the first
        autopilot MAVSDK discovers until the vehicle's HEARTBEAT has locked its system (see
        :meth:`~service.vehicle_link.VehicleLinkBase._vehicle_ids_match`); from then on (a
        session made anew after a loss) only that system, whatever other autopilots MAVSDK
        discovers (each logged once)."""
        with self._cond:
            locked = self._vehicle_ids
        if locked is None:
            return session.sdk.first_autopilot(0.05)
        found = None
        for system in session.sdk.get_systems():
            system_id = system.get_system_id()
            if system_id == locked[0]:
                if system.has_autopilot():
                    found = system
            elif system.has_autopilot() and system_id not in self._foreign_logged:
                with self._cond:
                    self._foreign_logged.add(system_id)
                log.warning(
                    "MAVSDK discovered autopilot system %s; the link stays with system %s",
                    system_id,
                    locked[0],
                )
        return found

    @staticmethod
    def _on_answer(result: Any, _user_data: Any) -> None:
        log.debug("MAVSDK answered: %s", getattr(result, "name", result))

    # ------------------------------------------------------------------ MAVSDK callbacks

    def _on_heartbeat(self, message: Any, system_id: int) -> None:
        try:
            fields = json.loads(message.fields_json)
            heartbeat = [int(fields[k]) for k in ("autopilot", "type", "base_mode", "custom_mode")]
        except (ValueError, KeyError, TypeError):
            with self._cond:
                self.counters["bad_data"] += 1
            return
        if message.system_id == system_id and message.component_id == MAV_COMP_ID_AUTOPILOT1:
            status = fields.get("system_status")
            self._note_heartbeat(
                *heartbeat,
                system_id=system_id,
                system_status=int(status) if isinstance(status, int | float) else None,
                component_id=message.component_id,
            )

    def _on_origin(self, message: Any, system_id: int) -> None:
        if message.system_id != system_id or message.component_id != MAV_COMP_ID_AUTOPILOT1:
            return
        try:
            f = json.loads(message.fields_json)
            origin = GeoPoint(f["latitude"] / 1e7, f["longitude"] / 1e7, f["altitude"] / 1e3)
        except (ValueError, KeyError, TypeError):
            with self._cond:
                self.counters["bad_data"] += 1
            return
        with self._cond:
            self._note_origin(origin)

    def _on_position_ned(self, position_velocity: Any, _user_data: Any) -> None:
        p, v = position_velocity.position, position_velocity.velocity
        with self._cond:
            self._ned = (p.north_m, p.east_m, p.down_m)
            self._ned_velocity = (v.north_m_s, v.east_m_s, v.down_m_s)
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

    def _on_battery(self, battery: Any, _user_data: Any) -> None:
        # MAVSDK's remaining_percent is 0-100 (NaN: unknown); voltage NaN: unknown.
        remaining = battery.remaining_percent
        voltage = battery.voltage_v
        with self._cond:
            self._note_battery(
                time.monotonic(),
                remaining if math.isfinite(remaining) else None,
                voltage if math.isfinite(voltage) else None,
            )

    # ------------------------------------------------------------------ setpoints and mode

    def _send_setpoint(self, ned_m: tuple[float, float, float], now: float, new: bool) -> bool:
        from mavsdk.plugins.offboard import PositionNedYaw

        if new:
            with self._cond:
                self._stream_yaw_deg = self._heading_deg or 0.0
        setpoint = PositionNedYaw(*ned_m, self._stream_yaw_deg)
        with self._sdk_lock:
            session = self._session
            if session is None or session.offboard is None:
                return False
            try:
                session.offboard.set_position_ned(setpoint)
            except Exception as exc:  # OffboardError: no system, connection error
                self.counters["setpoint_errors"] += 1
                log.debug("set_position_ned failed: %s", exc)
                return False
            session.offboard_fed = True
        return True

    def _stop_stream(self) -> None:
        """End MAVSDK's own re-sending without a mode change: a fresh Offboard plugin."""
        with self._sdk_lock:
            session = self._session
            if session is None or session.system is None or not session.offboard_fed:
                return
            session.renew_offboard()
        log.info("setpoint stream stopped")

    def _send_guided_mode_request(self, flavour: Flavour) -> None:
        """``Offboard.start`` (MAVSDK asks for GUIDED on ArduPilot), once setpoints flow."""
        with self._sdk_lock:
            session = self._session
            if session is None or not session.offboard_fed:
                return
            session.call_async(session.offboard.start_async, self._on_answer)

    # ------------------------------------------------------------------ the autopilot's fence

    def _request_origin(self) -> None:
        """MAV_CMD_REQUEST_MESSAGE for GPS_GLOBAL_ORIGIN (answered to :meth:`_on_origin`)."""
        from mavsdk.plugins.mavlink_direct import MavlinkMessage

        with self._sdk_lock:
            session = self._session
            if session is None or session.system_id is None:
                return
            fields = {
                "target_system": session.system_id,
                "target_component": MAV_COMP_ID_AUTOPILOT1,
                "command": mavlink.MAV_CMD_REQUEST_MESSAGE,
                "confirmation": 0,
                "param1": float(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN),
                **{f"param{i}": 0.0 for i in range(2, 8)},
            }
            message = MavlinkMessage(
                "COMMAND_LONG", 0, 0, session.system_id, MAV_COMP_ID_AUTOPILOT1, json.dumps(fields)
            )
            session.call_async(
                lambda answer: session.direct.send_command_async(
                    message, lambda result, _ack, user_data: answer(result, user_data)
                ),
                self._on_answer,
            )

    def _upload_fence(self, plan: FencePlan) -> FenceReport:
        """The fence through MAVSDK's Geofence and Param plugins
        (:func:`service.mavsdk_fence.apply_fence_plan_mavsdk`), each blocking call on a worker
        thread while this I/O thread goes on feeding MAVSDK the vehicle's datagrams."""
        with self._sdk_lock:
            session = self._session
        if session is None or session.geofence is None:
            raise MissionError("the connection closed before the fence upload")
        log.info("fence upload through MAVSDK (autopilot %s)", session.system.autopilot_type())
        return apply_fence_plan_mavsdk(
            session.geofence,
            session.param,
            plan,
            lambda call, what: self._call_blocking(session, call, what),
        )

    def _call_blocking(self, session: Session, call: Callable[[], Any], what: str) -> Any:
        """``call()`` (a blocking MAVSDK call) on a worker thread, counted among the session's
        unanswered calls so that no teardown destroys MAVSDK under it; meanwhile, on ``udpin``,
        the vehicle's datagrams go on reaching MAVSDK. Its result, or what it raised;
        MissionError after ``FENCE_CALL_TIMEOUT_S`` or when the link closes."""
        done = threading.Event()
        outcome: list[tuple[Any, BaseException | None]] = []

        def start(answer: Callable[..., None]) -> None:
            def work() -> None:
                try:
                    value: tuple[Any, BaseException | None] = (call(), None)
                except Exception as exc:  # MAVSDK's errors: the caller names them
                    value = (None, exc)
                answer(*value)

            threading.Thread(target=work, name="mavsdk-fence-call", daemon=True).start()

        def finished(value: Any, error: BaseException | None) -> None:
            outcome.append((value, error))
            done.set()

        session.call_async(start, finished)
        deadline = time.monotonic() + FENCE_CALL_TIMEOUT_S
        while not done.is_set():
            if session.udp is not None:
                self._feed(session, RAW_WAIT_S * 4)
            else:
                done.wait(0.05)
            if self._stop.is_set():
                raise MissionError(f"{what}: the link is closing")
            if time.monotonic() > deadline and not done.is_set():
                raise MissionError(f"{what}: no answer in {FENCE_CALL_TIMEOUT_S:g} s")
        value, error = outcome[0]
        if error is not None:
            raise error
        return value

    # ------------------------------------------------------------------ commands

    def _request(
        self, start: Callable[[Session, Callable[..., None]], None], timeout_s: float
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

    def _ask(self, command: int, params: Sequence[float], timeout_s: float) -> int | None:
        """COMMAND_LONG through MavlinkDirect; the MAV_RESULT of its final ACK, or None."""
        from mavsdk.plugins.mavlink_direct import MavlinkDirectResult, MavlinkMessage

        with self._cond:
            self.counters["commands_sent"] += 1
        with self._sdk_lock:
            system_id = self._session.system_id if self._session is not None else None
        if system_id is None:
            return None
        fields: dict[str, Any] = {
            "target_system": system_id,
            "target_component": MAV_COMP_ID_AUTOPILOT1,
            "command": command,
            "confirmation": 0,
        }
        for index, value in enumerate(params, start=1):
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

    def _param_float(self, name: str, value: float | None, timeout_s: float) -> float | None:
        """Set ``value`` (None: only read) through the Param plugin, then read it back: the
        value the vehicle reports, or None (no answer, refused, or ``timeout_s`` passed). The
        plugin's calls block: they run on a thread of their own, counted as the session's
        unanswered calls (no teardown destroys MAVSDK under them)."""

        def call(session: Session) -> float | None:
            try:
                if value is not None:
                    session.param.set_param_float(name, float(value))
                return float(session.param.get_param_float(name))
            except Exception as exc:  # ParamError, or the session going away under the call
                log.debug("%s: %s", name, exc)
                return None

        def start(session: Session, answer: Callable[..., None]) -> None:
            threading.Thread(
                target=lambda: answer(call(session)), name="mavsdk-param", daemon=True
            ).start()

        reply = self._request(start, timeout_s)
        return None if reply is None else reply[0]

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
