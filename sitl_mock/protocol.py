"""MAVLink on top of the vehicle: decode what clients send, answer as the autopilot would, stream
telemetry at the rates each client asked for.

Transport-agnostic: the server hands every peer (a TCP connection, a UDP remote address) over as a
:class:`Link`, which owns that peer's pymavlink parser/encoder (sequence numbers and MAVLink 2
signing are per link, as on a real autopilot's channels) and its message intervals. The server
feeds received bytes to :meth:`MavlinkProtocol.receive` and calls :meth:`MavlinkProtocol.tick`
after every physics step.

Nothing that arrives can raise out of here: malformed bytes, unknown message ids, badly signed
packets, NaN setpoints and handler bugs are counted in :attr:`MavlinkProtocol.stats` and logged
(rate-limited) at INFO.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from collections import Counter
from collections.abc import Callable, Iterable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl_mock.flavours import (
    MODE_FLAG_CUSTOM_MODE_ENABLED,
    MODE_FLAG_SAFETY_ARMED,
    MavResult,
    Severity,
)
from sitl_mock.geo import ned_to_global
from sitl_mock.mission import MISSION_MESSAGES, FenceMissionServer
from sitl_mock.params import INT_TYPES, parameter_table, set_parameter
from sitl_mock.vehicle import FORCE_MAGIC, Vehicle

log = logging.getLogger(__name__)

MAV = mavlink
MAX_STREAM_RATE_HZ = 50.0
STATUSTEXT_CHUNK = 50
UNSIGNED_ALLOWED = frozenset({MAV.MAVLINK_MSG_ID_HEARTBEAT, MAV.MAVLINK_MSG_ID_RADIO_STATUS})
"""With signing on, these may arrive unsigned (as on ArduPilot); anything else is dropped."""

SENSORS_PRESENT = (
    MAV.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | MAV.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | MAV.MAV_SYS_STATUS_SENSOR_3D_MAG
    | MAV.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | MAV.MAV_SYS_STATUS_SENSOR_GPS
    | MAV.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | MAV.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | MAV.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | MAV.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | MAV.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | MAV.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | MAV.MAV_SYS_STATUS_AHRS
    | MAV.MAV_SYS_STATUS_SENSOR_BATTERY
    | MAV.MAV_SYS_STATUS_PREARM_CHECK
)
SENSORS_NEED_POSITION = (
    MAV.MAV_SYS_STATUS_SENSOR_GPS
    | MAV.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | MAV.MAV_SYS_STATUS_AHRS
    | MAV.MAV_SYS_STATUS_PREARM_CHECK
)

# ArduPilot's REQUEST_DATA_STREAM groups, restricted to the messages the mock produces.
DATA_STREAM_GROUPS: dict[int, tuple[str, ...]] = {
    MAV.MAV_DATA_STREAM_EXTENDED_STATUS: (
        "SYS_STATUS",
        "GPS_RAW_INT",
        "EXTENDED_SYS_STATE",
        "POSITION_TARGET_GLOBAL_INT",
    ),
    MAV.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    MAV.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    MAV.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    MAV.MAV_DATA_STREAM_EXTRA3: ("BATTERY_STATUS", "EKF_STATUS_REPORT"),
}

# Versions reported in AUTOPILOT_VERSION (major, minor, patch), FIRMWARE_VERSION_TYPE_OFFICIAL.
FLIGHT_SW_VERSION = {"ardupilot": (4, 6, 0), "px4": (1, 15, 0)}
CAPABILITIES = (
    MAV.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | MAV.MAV_PROTOCOL_CAPABILITY_MISSION_INT  # the fence protocol (sitl_mock.mission) is INT
    | MAV.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | MAV.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | MAV.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | MAV.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | MAV.MAV_PROTOCOL_CAPABILITY_MAVLINK2
)


def msg_id(name: str) -> int:
    """The MAVLink message id of message ``name`` (e.g. "GLOBAL_POSITION_INT")."""
    return int(getattr(MAV, f"MAVLINK_MSG_ID_{name}"))


class StreamTable:
    """One link's telemetry intervals and when each message is next due (vehicle time, s)."""

    def __init__(self, intervals_s: dict[int, float], now_s: float) -> None:
        self.intervals_s: dict[int, float] = {}
        self._next_s: dict[int, float] = {}
        for message_id, interval_s in intervals_s.items():
            self.set_interval(message_id, interval_s, now_s)

    def set_interval(self, message_id: int, interval_s: float | None, now_s: float) -> None:
        """Send ``message_id`` every ``interval_s`` from now on (None: stop sending it)."""
        if interval_s is None:
            self.intervals_s.pop(message_id, None)
            self._next_s.pop(message_id, None)
            return
        interval_s = max(interval_s, 1.0 / MAX_STREAM_RATE_HZ)
        self.intervals_s[message_id] = interval_s
        self._next_s[message_id] = now_s

    def due(self, now_s: float) -> list[int]:
        """The messages due now; each is scheduled for its next interval."""
        due = []
        for message_id, next_s in self._next_s.items():
            if now_s + 1e-9 >= next_s:
                due.append(message_id)
                interval_s = self.intervals_s[message_id]
                following = next_s + interval_s
                self._next_s[message_id] = following if following > now_s else now_s + interval_s
        return due


class Link:
    """One peer of the autopilot (see the module docstring). ``write`` sends raw bytes to it."""

    def __init__(self, name: str, mav: mavlink.MAVLink, write: Callable[[bytes], None]) -> None:
        self.name = name
        self.mav = mav
        mav.file = self
        self._write = write
        self.streams = StreamTable({}, 0.0)
        self.peer: tuple[int, int] | None = None

    def write(self, data: bytes) -> None:
        """Called by pymavlink's ``MAVLink.send`` with a packed message."""
        self._write(data)

    def send(self, message: mavlink.MAVLink_message) -> None:
        self.mav.send(message)


class _RateLimitedLog:
    """INFO lines at most once per key and second of vehicle time, with a count of the rest."""

    def __init__(self) -> None:
        self._last_s: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def info(self, now_s: float, key: str, text: str, *args: object) -> None:
        last = self._last_s.get(key)
        if last is not None and now_s - last < 1.0:
            self._suppressed[key] += 1
            return
        suppressed = self._suppressed.pop(key, 0)
        suffix = f" (and {suppressed} more like it)" if suppressed else ""
        log.info(text + suffix, *args)
        self._last_s[key] = now_s


class MavlinkProtocol:
    """The autopilot's MAVLink side of one vehicle. Not thread-safe: the server serialises calls."""

    def __init__(
        self,
        vehicle: Vehicle,
        system_id: int = 1,
        component_id: int = 1,
        signing_key: bytes | None = None,
    ) -> None:
        if signing_key is not None and len(signing_key) != 32:
            raise ValueError(f"signing key must be 32 bytes, got {len(signing_key)}")
        self.vehicle = vehicle
        self.flavour = vehicle.flavour
        self.system_id = system_id
        self.component_id = component_id
        self.signing_key = signing_key
        self.stats: Counter[str] = Counter()
        self._encoder = mavlink.MAVLink(None, system_id, component_id)
        self._rate_log = _RateLimitedLog()
        self._links_for_broadcast: list[Link] = []
        self._home_announced = False
        self._next_link_id = 0
        self._statustext_id = 0
        self._builders: dict[int, Callable[[], mavlink.MAVLink_message | None]] = {
            msg_id(name[len("_build_") :].upper()): getattr(self, name)
            for name in dir(self)
            if name.startswith("_build_")
        }
        if not self.flavour.sends_ekf_status:
            del self._builders[MAV.MAVLINK_MSG_ID_EKF_STATUS_REPORT]
        self._handlers: dict[int, Callable[[Link, mavlink.MAVLink_message], None]] = {
            MAV.MAVLINK_MSG_ID_HEARTBEAT: self._on_heartbeat,
            MAV.MAVLINK_MSG_ID_COMMAND_LONG: self._on_command_long,
            MAV.MAVLINK_MSG_ID_COMMAND_INT: self._on_command_int,
            MAV.MAVLINK_MSG_ID_SET_MODE: self._on_set_mode,
            MAV.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED: self._on_setpoint_local,
            MAV.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT: self._on_setpoint_global,
            MAV.MAVLINK_MSG_ID_REQUEST_DATA_STREAM: self._on_request_data_stream,
            MAV.MAVLINK_MSG_ID_PARAM_REQUEST_LIST: self._on_param_request_list,
            MAV.MAVLINK_MSG_ID_PARAM_REQUEST_READ: self._on_param_request_read,
            MAV.MAVLINK_MSG_ID_PARAM_SET: self._on_param_set,
            MAV.MAVLINK_MSG_ID_TIMESYNC: self._on_timesync,
            MAV.MAVLINK_MSG_ID_PING: self._on_ping,
        }
        self.missions = FenceMissionServer(
            vehicle.autopilot_fence,
            self.flavour.fence_style == "ardupilot",
            self.flavour.fence_max_items,
            self._encoder,
            vehicle.say,
            self.stats,
        )
        for name in MISSION_MESSAGES:
            self._handlers[msg_id(name)] = self._on_mission

    # ------------------------------------------------------------------ links

    def new_link(self, name: str, write: Callable[[bytes], None]) -> Link:
        """A link for a new peer: own parser, signing state and the flavour's default streams."""
        mav = mavlink.MAVLink(None, self.system_id, self.component_id)
        mav.robust_parsing = True
        if self.signing_key is not None:
            signing = mav.signing
            signing.secret_key = self.signing_key
            signing.sign_outgoing = True
            signing.link_id = self._next_link_id % 256
            signing.allow_unsigned_callback = _allow_unsigned
            # Timestamps count 10 µs units since 2015-01-01, like pymavlink's setup_signing.
            signing.timestamp = _signing_timestamp_now()
        self._next_link_id += 1
        link = Link(name, mav, write)
        now_s = self.vehicle.time_s
        intervals = {MAV.MAVLINK_MSG_ID_HEARTBEAT: 1.0}
        if not self.flavour.streams_on_request_only:
            for name_, rate_hz in self.flavour.default_rates_hz.items():
                intervals[msg_id(name_)] = 1.0 / rate_hz
        link.streams = StreamTable(intervals, now_s)
        self.stats["links_opened"] += 1
        return link

    def receive(self, link: Link, data: bytes) -> None:
        """Bytes from ``link``: parse them and act on every complete message."""
        try:
            messages = link.mav.parse_buffer(data) or []
        except Exception as exc:  # pymavlink raises on some corruptions even when robust
            self.stats["bad_data"] += 1
            self._rate_log.info(
                self.vehicle.time_s, "bad", "%s: unparsable bytes (%s)", link.name, exc
            )
            _reset_parser(link.mav)
            return
        for message in messages:
            self.handle(link, message)

    def handle(self, link: Link, message: mavlink.MAVLink_message) -> None:
        """Act on one decoded message from ``link``."""
        now_s = self.vehicle.time_s
        message_type = message.get_type()
        if message_type == "BAD_DATA":
            if getattr(message, "reason", "") == "Invalid signature":
                self.stats["signing_rejected"] += 1
                self._rate_log.info(
                    now_s, "sig", "%s: unsigned or badly signed message ignored", link.name
                )
            else:
                self.stats["bad_data"] += 1
                self._rate_log.info(
                    now_s, "bad", "%s: malformed MAVLink ignored (%s)", link.name, message.reason
                )
            return
        self.stats["messages_received"] += 1
        if message_type.startswith("UNKNOWN_"):
            self.stats["unknown_messages"] += 1
            self._rate_log.info(now_s, "unknown", "%s: unknown message %s", link.name, message_type)
            return
        handler = self._handlers.get(message.get_msgId())
        if handler is None:
            self.stats["unhandled_messages"] += 1
            return
        try:
            handler(link, message)
        except Exception:
            self.stats["handler_errors"] += 1
            log.exception("%s: error handling %s", link.name, message_type)
        self._flush_statustexts()

    def tick(self, links: Iterable[Link]) -> None:
        """After a physics step: STATUSTEXTs to everyone, then each link's due telemetry."""
        self.missions.tick(self.vehicle.time_s)
        self._flush_statustexts(links)
        if self.vehicle.ready and not self._home_announced:
            # Both autopilots tell every ground station when home gets set.
            self._home_announced = True
            for link in links:
                self.send_message(link, MAV.MAVLINK_MSG_ID_HOME_POSITION)
        now_s = self.vehicle.time_s
        for link in links:
            for message_id in link.streams.due(now_s):
                self.send_message(link, message_id)

    def send_message(self, link: Link, message_id: int) -> bool:
        """Build message ``message_id`` from the vehicle state and send it; False if unavailable."""
        builder = self._builders.get(message_id)
        message = builder() if builder is not None else None
        if message is None:
            return False
        link.send(message)
        return True

    # ------------------------------------------------------------------ STATUSTEXT

    def _flush_statustexts(self, links: Iterable[Link] | None = None) -> None:
        events = self.vehicle.drain_events()
        if not events:
            return
        targets = list(links) if links is not None else list(self._links_for_broadcast)
        for event in events:
            log.info("STATUSTEXT %s: %s", event.severity.name, event.text)
            for message in self._statustext_messages(event.severity, event.text):
                for link in targets:
                    link.send(message)

    def set_links(self, links: list[Link]) -> None:
        """Tell the protocol which links are open (the server keeps this list current)."""
        self._links_for_broadcast = links

    def _statustext_messages(self, severity: Severity, text: str) -> list[mavlink.MAVLink_message]:
        raw = text.encode("ascii", errors="replace")
        if len(raw) <= STATUSTEXT_CHUNK:
            return [self._encoder.statustext_encode(severity, raw)]
        self._statustext_id = self._statustext_id % 65535 + 1
        chunks = [raw[i : i + STATUSTEXT_CHUNK] for i in range(0, len(raw), STATUSTEXT_CHUNK)]
        return [
            self._encoder.statustext_encode(severity, chunk, self._statustext_id, seq)
            for seq, chunk in enumerate(chunks)
        ]

    # ------------------------------------------------------------------ incoming messages

    def _addressed_to_us(self, target_system: int, target_component: int) -> bool:
        return target_system in (0, self.system_id) and target_component in (0, self.component_id)

    def _on_heartbeat(self, link: Link, message: mavlink.MAVLink_message) -> None:
        header = message.get_header()
        if (header.srcSystem, header.srcComponent) == (self.system_id, self.component_id):
            return  # our own heartbeat looped back (a companion on our system id is fine)
        link.peer = (header.srcSystem, header.srcComponent)
        if message.autopilot == MAV.MAV_AUTOPILOT_INVALID:
            self.vehicle.note_gcs_heartbeat()
            self.stats["gcs_heartbeats"] += 1

    def _on_command_long(self, link: Link, message: mavlink.MAVLink_message) -> None:
        m = message
        params = (m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7)
        self._command(link, message, m.target_system, m.target_component, m.command, params)

    def _on_command_int(self, link: Link, message: mavlink.MAVLink_message) -> None:
        m = message
        # x, y carry latitude/longitude in degE7 in the global frames (the only use we serve).
        params = (m.param1, m.param2, m.param3, m.param4, m.x * 1e-7, m.y * 1e-7, m.z)
        self._command(link, message, m.target_system, m.target_component, m.command, params)

    def _command(
        self,
        link: Link,
        message: mavlink.MAVLink_message,
        target_system: int,
        target_component: int,
        command: int,
        params: tuple[float, ...],
    ) -> None:
        if not self._addressed_to_us(target_system, target_component):
            self.stats["not_for_us"] += 1
            return
        self.stats["commands"] += 1
        result, reason = self._run_command(link, command, params)
        if result is MavResult.UNSUPPORTED:
            self.stats["commands_unsupported"] += 1
        name = MAV.enums["MAV_CMD"].get(command)
        cmd_name = name.name if name is not None else str(command)
        log.info(
            "%s: %s -> %s%s", link.name, cmd_name, result.name, f" ({reason})" if reason else ""
        )
        # Statustexts explaining a refusal go out before the ACK, as on the real autopilots.
        self._flush_statustexts()
        header = message.get_header()
        ack = self._encoder.command_ack_encode(
            command, int(result), 0, 0, header.srcSystem, header.srcComponent
        )
        link.send(ack)
        self._after_ack(link, command, params, result)

    def _run_command(self, link: Link, command: int, p: tuple[float, ...]) -> tuple[MavResult, str]:
        vehicle = self.vehicle
        if command == MAV.MAV_CMD_COMPONENT_ARM_DISARM:
            force = p[1] == FORCE_MAGIC
            if p[0] == 1:
                outcome = vehicle.arm(force)
            elif p[0] == 0:
                outcome = vehicle.disarm(force)
            else:
                return MavResult.DENIED, f"param1 {p[0]}"
            return outcome.result, outcome.reason
        if command == MAV.MAV_CMD_DO_SET_MODE:
            if not (math.isfinite(p[0]) and int(p[0]) & MODE_FLAG_CUSTOM_MODE_ENABLED):
                return MavResult.UNSUPPORTED, "only custom modes"
            custom_mode = self.flavour.custom_mode_from_command(p[1], p[2])
            if custom_mode is None:
                return self.flavour.result_refused, "bad mode number"
            outcome = vehicle.set_mode(custom_mode)
            return outcome.result, outcome.reason
        if command == MAV.MAV_CMD_NAV_TAKEOFF:
            outcome = vehicle.takeoff(p[6], p[4], p[5])
            return outcome.result, outcome.reason
        if command == MAV.MAV_CMD_NAV_LAND:
            outcome = vehicle.land()
            return outcome.result, outcome.reason
        if command == MAV.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            outcome = vehicle.return_to_launch()
            return outcome.result, outcome.reason
        if command == MAV.MAV_CMD_DO_CHANGE_SPEED:
            outcome = vehicle.change_speed(p[0], p[1])
            return outcome.result, outcome.reason
        if command == MAV.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_message_interval(link, p[0], p[1])
        if command in (MAV.MAV_CMD_GET_MESSAGE_INTERVAL, MAV.MAV_CMD_REQUEST_MESSAGE):
            return self._check_requestable(p[0])
        if command == MAV.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return MavResult.ACCEPTED, ""
        if command == MAV.MAV_CMD_GET_HOME_POSITION:
            return self._check_requestable(float(MAV.MAVLINK_MSG_ID_HOME_POSITION))
        return MavResult.UNSUPPORTED, ""

    def _after_ack(self, link: Link, command: int, p: tuple[float, ...], result: MavResult) -> None:
        """Messages that follow an accepted request (they come after the ACK on the real ones)."""
        if result is not MavResult.ACCEPTED:
            return
        if command == MAV.MAV_CMD_REQUEST_MESSAGE:
            self._send_requested(link, int(p[0]))
        elif command == MAV.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._send_requested(link, MAV.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        elif command == MAV.MAV_CMD_GET_HOME_POSITION:
            self._send_requested(link, MAV.MAVLINK_MSG_ID_HOME_POSITION)
        elif command == MAV.MAV_CMD_GET_MESSAGE_INTERVAL:
            message_id = int(p[0])
            interval_s = link.streams.intervals_s.get(message_id)
            interval_us = -1 if interval_s is None else round(interval_s * 1e6)
            link.send(self._encoder.message_interval_encode(message_id, interval_us))

    def _check_requestable(self, message_id_f: float) -> tuple[MavResult, str]:
        if not math.isfinite(message_id_f) or message_id_f < 0:
            return MavResult.DENIED, "bad message id"
        message_id = int(message_id_f)
        if message_id == MAV.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return MavResult.ACCEPTED, ""
        if message_id not in self._builders:
            return MavResult.UNSUPPORTED, f"message {message_id} not available"
        if message_id == MAV.MAVLINK_MSG_ID_HOME_POSITION and not self.vehicle.ready:
            return MavResult.FAILED, "home not set"
        return MavResult.ACCEPTED, ""

    def _send_requested(self, link: Link, message_id: int) -> None:
        if message_id == MAV.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            link.send(self._autopilot_version())
        else:
            self.send_message(link, message_id)

    def _set_message_interval(
        self, link: Link, message_id_f: float, interval_us: float
    ) -> tuple[MavResult, str]:
        if not (math.isfinite(message_id_f) and math.isfinite(interval_us)):
            return MavResult.DENIED, "NaN parameter"
        message_id = int(message_id_f)
        if message_id not in self._builders:
            text = self.flavour.text_interval_refused.format(message_id=message_id)
            self.vehicle.say(Severity.WARNING, text)
            return self.flavour.result_interval_refused, f"message {message_id} not available"
        now_s = self.vehicle.time_s
        if interval_us < 0:
            link.streams.set_interval(message_id, None, now_s)
        elif interval_us == 0:
            name = MAV.mavlink_map[message_id].msgname
            rate_hz = self.flavour.default_rates_hz.get(name, 1.0)
            link.streams.set_interval(message_id, 1.0 / rate_hz, now_s)
        else:
            link.streams.set_interval(message_id, interval_us / 1e6, now_s)
        return MavResult.ACCEPTED, ""

    def _on_request_data_stream(self, link: Link, message: mavlink.MAVLink_message) -> None:
        m = message
        if not self.flavour.honours_request_data_stream:
            self.stats["unhandled_messages"] += 1
            return
        if not self._addressed_to_us(m.target_system, m.target_component):
            self.stats["not_for_us"] += 1
            return
        if m.req_stream_id == MAV.MAV_DATA_STREAM_ALL:
            names = [name for group in DATA_STREAM_GROUPS.values() for name in group]
        else:
            names = list(DATA_STREAM_GROUPS.get(m.req_stream_id, ()))
        rate_hz = min(float(m.req_message_rate), MAX_STREAM_RATE_HZ)
        interval_s = 1.0 / rate_hz if m.start_stop and rate_hz > 0 else None
        for name in names:
            link.streams.set_interval(msg_id(name), interval_s, self.vehicle.time_s)
        log.info(
            "%s: data stream %d at %s Hz", link.name, m.req_stream_id, rate_hz if interval_s else 0
        )

    def _on_set_mode(self, link: Link, message: mavlink.MAVLink_message) -> None:
        m = message
        if m.target_system != self.system_id:
            self.stats["not_for_us"] += 1
            return
        self.stats["commands"] += 1
        if m.base_mode & MODE_FLAG_CUSTOM_MODE_ENABLED:
            outcome = self.vehicle.set_mode(m.custom_mode)
            result, reason = outcome.result, outcome.reason
        else:
            result, reason = MavResult.UNSUPPORTED, "only custom modes"
        log.info("%s: SET_MODE %d -> %s %s", link.name, m.custom_mode, result.name, reason)
        self._flush_statustexts()
        header = message.get_header()
        link.send(
            self._encoder.command_ack_encode(
                MAV.MAVLINK_MSG_ID_SET_MODE,
                int(result),
                0,
                0,
                header.srcSystem,
                header.srcComponent,
            )
        )

    def _on_setpoint_local(self, link: Link, message: mavlink.MAVLink_message) -> None:
        m = message
        if not self._addressed_to_us(m.target_system, m.target_component):
            self.stats["not_for_us"] += 1
            return
        outcome = self.vehicle.set_position_target_local(
            m.coordinate_frame, m.type_mask, m.x, m.y, m.z, m.vx, m.vy, m.vz, m.yaw
        )
        self._note_setpoint_outcome(link, outcome, message)

    def _on_setpoint_global(self, link: Link, message: mavlink.MAVLink_message) -> None:
        m = message
        if not self._addressed_to_us(m.target_system, m.target_component):
            self.stats["not_for_us"] += 1
            return
        outcome = self.vehicle.set_position_target_global(
            m.coordinate_frame,
            m.type_mask,
            m.lat_int / 1e7,
            m.lon_int / 1e7,
            m.alt,
            m.vx,
            m.vy,
            m.vz,
            m.yaw,
        )
        self._note_setpoint_outcome(link, outcome, message)

    def _note_setpoint_outcome(
        self, link: Link, outcome: str, message: mavlink.MAVLink_message
    ) -> None:
        if outcome in ("accepted", "buffered"):
            return
        self._rate_log.info(
            self.vehicle.time_s,
            f"setpoint-{outcome}",
            "%s: setpoint %s in %s: %s",
            link.name,
            outcome,
            self.vehicle.mode.name,
            message,
        )

    def _on_param_request_list(self, link: Link, message: mavlink.MAVLink_message) -> None:
        if not self._addressed_to_us(message.target_system, message.target_component):
            return
        table = parameter_table(self.vehicle, self.system_id)
        for index in range(len(table)):
            link.send(self._param_value(table, index))

    def _on_param_request_read(self, link: Link, message: mavlink.MAVLink_message) -> None:
        if self._addressed_to_us(message.target_system, message.target_component):
            self._send_param(link, message.param_id, message.param_index)

    def _on_param_set(self, link: Link, message: mavlink.MAVLink_message) -> None:
        # The fence's parameters are taken; the rest is the command line's: answered with the
        # value we keep, as an autopilot does for a refused set.
        m = message
        if self._addressed_to_us(m.target_system, m.target_component):
            if set_parameter(self.vehicle, m.param_id, m.param_value, m.param_type):
                self.stats["param_sets"] += 1
                log.info("%s: PARAM_SET %s", link.name, m.param_id)
            else:
                self.stats["param_sets_ignored"] += 1
            self._send_param(link, m.param_id, -1)

    def _on_mission(self, link: Link, message: mavlink.MAVLink_message) -> None:
        target = (message.target_system, message.target_component)
        if not self._addressed_to_us(*target):
            self.stats["not_for_us"] += 1
            return
        self.missions.handle(link, message, self.vehicle.time_s)

    def _send_param(self, link: Link, name: str, index: int) -> None:
        table = parameter_table(self.vehicle, self.system_id)
        if index < 0:
            names = [entry[0] for entry in table]
            if name not in names:
                self.stats["unknown_params"] += 1
                return
            index = names.index(name)
        if index < len(table):
            link.send(self._param_value(table, index))

    def _param_value(
        self, table: list[tuple[str, float, int]], index: int
    ) -> mavlink.MAVLink_message:
        name, value, kind = table[index]
        if kind in INT_TYPES and self.flavour.params_bytewise:
            value = struct.unpack("<f", struct.pack("<i", round(value)))[0]
        return self._encoder.param_value_encode(name.encode(), value, kind, len(table), index)

    def _on_timesync(self, link: Link, message: mavlink.MAVLink_message) -> None:
        if message.tc1 == 0:
            now_ns = round(self.vehicle.time_s * 1e9)
            link.send(self._encoder.timesync_encode(now_ns, message.ts1))

    def _on_ping(self, link: Link, message: mavlink.MAVLink_message) -> None:
        m = message
        if m.target_system == 0 and m.target_component == 0:
            header = m.get_header()
            link.send(
                self._encoder.ping_encode(m.time_usec, m.seq, header.srcSystem, header.srcComponent)
            )

    # ------------------------------------------------------------------ outgoing messages

    @property
    def _time_boot_ms(self) -> int:
        return round(self.vehicle.time_s * 1000) & 0xFFFFFFFF

    def _base_mode(self) -> int:
        vehicle = self.vehicle
        flags = MODE_FLAG_CUSTOM_MODE_ENABLED | vehicle.mode.base_mode_flags
        return flags | (MODE_FLAG_SAFETY_ARMED if vehicle.armed else 0)

    def _build_heartbeat(self) -> mavlink.MAVLink_message:
        vehicle = self.vehicle
        if vehicle.failsafe_active:
            state = MAV.MAV_STATE_CRITICAL
        elif vehicle.armed:
            state = MAV.MAV_STATE_ACTIVE
        else:
            state = MAV.MAV_STATE_STANDBY
        return self._encoder.heartbeat_encode(
            MAV.MAV_TYPE_QUADROTOR,
            self.flavour.autopilot_type,
            self._base_mode(),
            vehicle.mode.custom_mode,
            state,
        )

    def _build_sys_status(self) -> mavlink.MAVLink_message:
        vehicle = self.vehicle
        health = SENSORS_PRESENT
        if not vehicle.ready:
            health &= ~SENSORS_NEED_POSITION
        failsafe_pct = vehicle.config.battery_failsafe_pct
        if failsafe_pct and vehicle.battery_remaining_pct <= failsafe_pct:
            health &= ~(MAV.MAV_SYS_STATUS_SENSOR_BATTERY | MAV.MAV_SYS_STATUS_PREARM_CHECK)
        return self._encoder.sys_status_encode(
            SENSORS_PRESENT,
            SENSORS_PRESENT,
            health,
            250,
            round(vehicle.battery_voltage_v * 1000),
            round(vehicle.battery_current_a * 100),
            round(vehicle.battery_remaining_pct),
            0,
            0,
            0,
            0,
            0,
            0,
        )

    def _build_gps_raw_int(self) -> mavlink.MAVLink_message:
        vehicle = self.vehicle
        position = vehicle.global_position
        v = vehicle.velocity
        ground_speed = math.hypot(v.n, v.e)
        course_cdeg = round(math.degrees(math.atan2(v.e, v.n)) % 360 * 100) % 36000
        ready = vehicle.ready
        return self._encoder.gps_raw_int_encode(
            round(vehicle.time_s * 1e6),
            MAV.GPS_FIX_TYPE_3D_FIX if ready else MAV.GPS_FIX_TYPE_NO_FIX,
            round(position.lat_deg * 1e7) if ready else 0,
            round(position.lon_deg * 1e7) if ready else 0,
            round(position.alt_amsl_m * 1000) if ready else 0,
            121 if ready else 9999,
            200 if ready else 9999,
            round(ground_speed * 100),
            course_cdeg if ground_speed > 0.5 else 65535,
            12 if ready else 3,
        )

    def _build_extended_sys_state(self) -> mavlink.MAVLink_message:
        return self._encoder.extended_sys_state_encode(
            MAV.MAV_VTOL_STATE_UNDEFINED, self.vehicle.landed_state
        )

    def _build_global_position_int(self) -> mavlink.MAVLink_message | None:
        vehicle = self.vehicle
        if not vehicle.ready:
            if self.flavour.streams_on_request_only:
                # ArduPilot sends it anyway, with an empty position.
                return self._encoder.global_position_int_encode(
                    self._time_boot_ms, 0, 0, 0, 0, 0, 0, 0, 65535
                )
            return None
        position = vehicle.global_position
        v = vehicle.velocity
        heading_cdeg = round(math.degrees(vehicle.yaw_rad) % 360 * 100) % 36000
        return self._encoder.global_position_int_encode(
            self._time_boot_ms,
            round(position.lat_deg * 1e7),
            round(position.lon_deg * 1e7),
            round(position.alt_amsl_m * 1000),
            round(vehicle.alt_m * 1000),
            round(v.n * 100),
            round(v.e * 100),
            round(v.d * 100),
            heading_cdeg,
        )

    def _build_ekf_status_report(self) -> mavlink.MAVLink_message:
        ready = self.vehicle.ready
        variance = 0.02 if ready else 1.0
        return self._encoder.ekf_status_report_encode(
            self.vehicle.ekf_flags, variance, variance, 0.02, 0.02, 0.0
        )

    def _build_local_position_ned(self) -> mavlink.MAVLink_message | None:
        vehicle = self.vehicle
        if not vehicle.origin_set:
            return None  # neither autopilot has a local frame before its EKF origin
        p, v = vehicle.position, vehicle.velocity
        return self._encoder.local_position_ned_encode(
            self._time_boot_ms, p.n, p.e, p.d, v.n, v.e, v.d
        )

    def _build_attitude(self) -> mavlink.MAVLink_message:
        roll, pitch, yaw = self.vehicle.attitude_rad()
        return self._encoder.attitude_encode(
            self._time_boot_ms, roll, pitch, yaw, 0.0, 0.0, self.vehicle.yaw_rate_rps
        )

    def _build_vfr_hud(self) -> mavlink.MAVLink_message:
        vehicle = self.vehicle
        v = vehicle.velocity
        ground_speed = math.hypot(v.n, v.e)
        heading_deg = round(math.degrees(vehicle.yaw_rad)) % 360
        throttle_pct = 0 if not vehicle.armed else (15 if vehicle.landed else 50)
        return self._encoder.vfr_hud_encode(
            ground_speed,
            ground_speed,
            heading_deg,
            throttle_pct,
            vehicle.global_position.alt_amsl_m,
            -v.d,
        )

    def _build_battery_status(self) -> mavlink.MAVLink_message:
        vehicle = self.vehicle
        voltages = [round(vehicle.battery_voltage_v * 1000)] + [65535] * 9
        return self._encoder.battery_status_encode(
            0,
            MAV.MAV_BATTERY_FUNCTION_ALL,
            MAV.MAV_BATTERY_TYPE_LIPO,
            32767,
            voltages,
            round(vehicle.battery_current_a * 100),
            round(vehicle.battery_consumed_mah),
            -1,
            round(vehicle.battery_remaining_pct),
        )

    def _build_home_position(self) -> mavlink.MAVLink_message | None:
        vehicle = self.vehicle
        if not vehicle.ready:
            return None
        home = vehicle.home
        return self._encoder.home_position_encode(
            round(home.lat_deg * 1e7),
            round(home.lon_deg * 1e7),
            round(home.alt_amsl_m * 1000),
            0.0,
            0.0,
            0.0,
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
        )

    def _build_gps_global_origin(self) -> mavlink.MAVLink_message | None:
        """The local frame's origin (the mock's home: its local NED hangs off it)."""
        vehicle = self.vehicle
        if not vehicle.ready:
            return None
        home = vehicle.home
        return self._encoder.gps_global_origin_encode(
            round(home.lat_deg * 1e7),
            round(home.lon_deg * 1e7),
            round(home.alt_amsl_m * 1000),
            round(vehicle.time_s * 1e6),
        )

    def _build_position_target_local_ned(self) -> mavlink.MAVLink_message | None:
        target = self.vehicle.echo_target()
        if target is None:
            return None
        p = target.position if target.position is not None else (0.0, 0.0, 0.0)
        v = target.velocity if target.velocity is not None else (0.0, 0.0, 0.0)
        yaw = target.yaw_rad if target.yaw_rad is not None else 0.0
        return self._encoder.position_target_local_ned_encode(
            self._time_boot_ms,
            MAV.MAV_FRAME_LOCAL_NED,
            target.type_mask,
            *p,
            *v,
            0.0,
            0.0,
            0.0,
            yaw,
            0.0,
        )

    def _build_position_target_global_int(self) -> mavlink.MAVLink_message | None:
        vehicle = self.vehicle
        target = vehicle.echo_target()
        if target is None or target.position is None:
            return None
        point = ned_to_global(vehicle.home, *target.position)
        v = target.velocity if target.velocity is not None else (0.0, 0.0, 0.0)
        return self._encoder.position_target_global_int_encode(
            self._time_boot_ms,
            MAV.MAV_FRAME_GLOBAL_INT,
            target.type_mask,
            round(point.lat_deg * 1e7),
            round(point.lon_deg * 1e7),
            point.alt_amsl_m,
            *v,
            0.0,
            0.0,
            0.0,
            target.yaw_rad if target.yaw_rad is not None else 0.0,
            0.0,
        )

    def _autopilot_version(self) -> mavlink.MAVLink_message:
        major, minor, patch = FLIGHT_SW_VERSION[self.flavour.name]
        version = major << 24 | minor << 16 | patch << 8 | MAV.FIRMWARE_VERSION_TYPE_OFFICIAL
        return self._encoder.autopilot_version_encode(
            CAPABILITIES,
            version,
            0,
            0,
            0,
            [0] * 8,
            [0] * 8,
            [0] * 8,
            0,
            0,
            0x5349544C4D4F434B + self.system_id,  # "SITLMOCK"
        )


def _allow_unsigned(_mav: mavlink.MAVLink, message_id: int) -> bool:
    return message_id in UNSIGNED_ALLOWED


def _signing_timestamp_now() -> int:
    epoch_offset_s = 1420070400  # 2015-01-01T00:00:00Z
    return int(max(time.time() - epoch_offset_s, 0) * 100_000)


def _reset_parser(mav: mavlink.MAVLink) -> None:
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = mavlink.HEADER_LEN_V1 + 2
