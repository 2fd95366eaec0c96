"""The vehicle link on pymavlink: the default backend, and the only one that signs MAVLink 2.

:class:`MavlinkLink` owns one pymavlink connection (any connection string pymavlink knows:
``tcp:HOST:PORT``, ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, a serial device) and runs all of
its I/O in background threads, so that callers (the placement loop, the HTTP side) never block::

    link = MavlinkLink(LinkConfig("tcp:127.0.0.1:5760", area=AreaConfig()))
    link.start()
    link.arm_and_takeoff()            # only when asked: a service never arms by surprise
    link.set_target((250.0, 250.0, 50.0))  # area frame, metres; clamped to the geofence
    print(link.state())               # position in the area frame, mode, armed, link health
    link.close()

The loop, the heartbeat supervision, the setpoint schedule, the guided-mode requests and the
take-off sequence are :class:`~service.vehicle_link.VehicleLinkBase`'s; this module is the I/O:

* our own HEARTBEAT at 1 Hz (an onboard controller or a GCS; autopilot INVALID);
* it reads the vehicle's HEARTBEAT (decoded by the base; the vehicle's system and component ids
  are addressed from then on), GLOBAL_POSITION_INT, LOCAL_POSITION_NED, EXTENDED_SYS_STATE,
  EKF_STATUS_REPORT (ArduPilot), COMMAND_ACK and STATUSTEXT;
* it asks for that telemetry with SET_MESSAGE_INTERVAL (and, on ArduPilot, the older
  REQUEST_DATA_STREAM if no SET_MESSAGE_INTERVAL is accepted);
* setpoints are SET_POSITION_TARGET_LOCAL_NED, position only (:data:`POSITION_ONLY_TYPE_MASK`),
  MAV_FRAME_LOCAL_NED; the guided mode is asked for with MAV_CMD_DO_SET_MODE; every command goes
  out with all seven params as the MAVLink message set defines them
  (:mod:`service.mavlink_commands`), re-sent every ``COMMAND_RESEND_S`` until answered;
* it counts the vehicle's messages that fail the MAVLink 2 signature check (``signing_failures``:
  a wrong key on one side, or an unsigned vehicle while we sign); such messages are dropped, so
  a vehicle we cannot authenticate never comes ``up`` and is never commanded. A vehicle that
  signs while we have no key is counted in ``signed_vehicle_without_key``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from service import mavlink_commands
from service.modes import GUIDED_MODE_NAME, Flavour, set_mode_numbers
from service.vehicle_link import LinkConfig, VehicleLinkBase

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink loads its dialect (signing needs v2)
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

log = logging.getLogger(__name__)

COMMAND_RESEND_S = 1.0
"""A command not answered within this is sent again (the same command: all are idempotent)."""
RECEIVE_WAIT_S = 0.005
"""The longest a poll blocks on the socket: a new target goes out within a few ms."""

POSITION_ONLY_TYPE_MASK = (
    mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
)
"""SET_POSITION_TARGET_LOCAL_NED type_mask: use x, y, z only (ignore velocity, accel, yaw)."""


class MavlinkLink(VehicleLinkBase):
    """The vehicle link and setpoint streamer on pymavlink. See the module docstring."""

    _thread_name = "mavlink-link"

    def __init__(self, config: LinkConfig) -> None:
        super().__init__(config)
        self._send_lock = threading.Lock()
        self._conn: Any = None
        self._t0 = time.monotonic()
        self.counters["signing_failures"] = 0
        self._target_sys = 1
        self._target_comp = 1
        self._landed_state: int | None = None
        self._acks: dict[int, tuple[int, int]] = {}
        self._ack_seq = 0
        self._interval_accepted = False
        self._fallback_streams_sent = False

    # ------------------------------------------------------------------ connection

    def _open_transport(self, now: float) -> bool:
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
        log.info("MAVLink connection open: %s", config.url)
        return True

    def _transport_open(self) -> bool:
        return self._conn is not None

    def _on_transport_dead(self) -> None:
        self._transport_dead = True

    def _close_transport(self) -> None:
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

    # ------------------------------------------------------------------ input

    def _poll(self, wait_s: float) -> None:
        conn = self._conn
        timeout_s = min(max(wait_s, 0.001), RECEIVE_WAIT_S)
        message = conn.recv_match(blocking=True, timeout=timeout_s)
        count = 0
        while message is not None and count < 200:
            self._handle(message)
            count += 1
            message = conn.recv_msg()

    def _handle(self, message: Any) -> None:
        kind = message.get_type()
        now = time.monotonic()
        if kind == "STATUSTEXT":
            if self._from_vehicle(message):
                self._note_status_text(message.severity, message.text)
            return
        with self._cond:
            if kind == "HEARTBEAT":
                fields = (message.autopilot, message.type, message.base_mode, message.custom_mode)
                if not self._note_heartbeat(*fields, system_id=message.get_srcSystem()):
                    return  # another ground station or companion, not the vehicle
                header = message.get_header()
                if (
                    self.config.signing_key is None
                    and getattr(header, "incompat_flags", 0) & mavlink.MAVLINK_IFLAG_SIGNED
                ):
                    # It signs, we cannot: it will most likely ignore what we send.
                    self.counters["signed_vehicle_without_key"] += 1
                self._target_sys, self._target_comp = header.srcSystem, header.srcComponent
            elif kind == "LOCAL_POSITION_NED":
                self._ned = (message.x, message.y, message.z)
                self._position_at = now
            elif kind == "GLOBAL_POSITION_INT":
                self._relative_alt_m = message.relative_alt / 1000.0
                self._home_amsl_m = (message.alt - message.relative_alt) / 1000.0
                # UINT16_MAX: the vehicle does not know its heading.
                self._heading_deg = None if message.hdg == 65535 else message.hdg / 100.0
            elif kind == "EXTENDED_SYS_STATE":
                self._landed_state = message.landed_state
            elif kind == "EKF_STATUS_REPORT":
                self._ekf_flags = message.flags
            elif kind == "COMMAND_ACK":
                if message.result == mavlink.MAV_RESULT_IN_PROGRESS:
                    return  # not the final answer
                self._ack_seq += 1
                self._acks[message.command] = (self._ack_seq, message.result)
                if (
                    message.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
                    and message.result == mavlink.MAV_RESULT_ACCEPTED
                ):
                    self._interval_accepted = True
            elif kind == "BAD_DATA":
                self.counters["bad_data"] += 1
                if "signature" in str(getattr(message, "reason", "")).lower():
                    self.counters["signing_failures"] += 1
                return
            else:
                return
            self._cond.notify_all()

    def _on_link_up(self, now: float) -> None:
        self._interval_accepted = False
        self._fallback_streams_sent = False

    def _from_vehicle(self, message: Any) -> bool:
        """The message comes from the vehicle's system (any of its components)."""
        with self._cond:
            return message.get_srcSystem() == self._target_sys and self._last_hb is not None

    # ------------------------------------------------------------------ output

    def _send_heartbeat(self) -> None:
        heartbeat_type = self.config.heartbeat_type
        self._send(
            lambda mav: mav.heartbeat_send(
                heartbeat_type, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            )
        )

    def _request_telemetry(self, now: float) -> None:
        """SET_MESSAGE_INTERVAL for what we need (every 2 s until it all comes); on ArduPilot
        also EKF_STATUS_REPORT (the take-off waits on its flags), and the older
        REQUEST_DATA_STREAM once if no SET_MESSAGE_INTERVAL was accepted 1.5 s after the link
        came up (an old firmware, or a router that filters it). A real ArduCopter accepts at once
        but sends no LOCAL_POSITION_NED until its EKF has an origin (~20 s): missing positions
        alone are no reason to fall back."""
        with self._cond:
            flavour = self._flavour
            positions_fresh = self._position_at is not None and now - self._position_at < 1.0
            ekf_missing = flavour == "ardupilot" and self._ekf_flags is None
            use_fallback = (
                flavour == "ardupilot"
                and not self._interval_accepted
                and not self._fallback_streams_sent
                and now - self._up_since > 1.5
            )
            if use_fallback:
                self._fallback_streams_sent = True
            sys_id, comp_id = self._target_sys, self._target_comp
        if positions_fresh and not ekf_missing and not use_fallback:
            return
        rate_hz = self.config.telemetry_rate_hz
        wanted = [
            (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, rate_hz),
            (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, rate_hz),
            (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2.0),
        ]
        if flavour == "ardupilot":
            wanted.append((mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT, 2.0))
        for message_id, hz in wanted:
            self._send_command_long(
                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                mavlink_commands.set_message_interval(message_id, hz),
            )
        if use_fallback:
            log.info("SET_MESSAGE_INTERVAL not accepted: REQUEST_DATA_STREAM fallback")
            for stream in (mavlink.MAV_DATA_STREAM_POSITION, mavlink.MAV_DATA_STREAM_EXTRA3):
                self._send(
                    lambda mav, s=stream: mav.request_data_stream_send(
                        sys_id, comp_id, s, int(rate_hz), 1
                    )
                )

    def _send_setpoint(self, ned_m: tuple[float, float, float], now: float, new: bool) -> bool:
        with self._cond:
            sys_id, comp_id = self._target_sys, self._target_comp
        time_boot_ms = int((now - self._t0) * 1000) & 0xFFFFFFFF
        fields = (
            time_boot_ms,
            sys_id,
            comp_id,
            mavlink.MAV_FRAME_LOCAL_NED,
            POSITION_ONLY_TYPE_MASK,
            *ned_m,
            *([0.0] * 8),  # velocity, acceleration, yaw, yaw rate: ignored by the type_mask
        )
        return self._send(lambda mav: mav.set_position_target_local_ned_send(*fields))

    def _send_guided_mode_request(self, flavour: Flavour) -> None:
        numbers = set_mode_numbers(flavour, GUIDED_MODE_NAME[flavour])
        self._send_command_long(mavlink.MAV_CMD_DO_SET_MODE, mavlink_commands.set_mode(*numbers))

    def _send_command_long(self, command: int, params: Sequence[float]) -> bool:
        """Send COMMAND_LONG ``command`` with its seven ``params`` to the vehicle."""
        values = list(params)
        with self._cond:
            sys_id, comp_id = self._target_sys, self._target_comp
        return self._send(lambda mav: mav.command_long_send(sys_id, comp_id, command, 0, *values))

    # ------------------------------------------------------------------ commands and answers

    def _ask(self, command: int, params: Sequence[float], timeout_s: float) -> int | None:
        """COMMAND_LONG, re-sent every ``COMMAND_RESEND_S`` until the vehicle answers (a lossy
        radio loses commands and ACKs) or ``timeout_s`` passes: the first final COMMAND_ACK's
        result, or None."""
        with self._cond:
            seq_before = self._ack_seq  # only an ACK newer than this answers us
        ask_until = time.monotonic() + timeout_s
        while not self._stop.is_set():
            with self._cond:
                self.counters["commands_sent"] += 1
            self._send_command_long(command, params)
            resend_at = min(ask_until, time.monotonic() + COMMAND_RESEND_S)
            with self._cond:
                while not self._stop.is_set():
                    seq, result = self._acks.get(command, (0, -1))
                    if seq > seq_before:
                        return result
                    remaining = resend_at - time.monotonic()
                    if remaining <= 0:
                        break
                    self._cond.wait(remaining)
            if time.monotonic() >= ask_until:
                return None
        return None

    def _ask_arm(self, timeout_s: float) -> int | None:
        return self._ask(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink_commands.arm(), timeout_s)
