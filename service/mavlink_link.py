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
* only from the vehicle: its system and component are locked at its first HEARTBEAT for the
  link's lifetime (:meth:`~service.vehicle_link.VehicleLinkBase._vehicle_ids_match`); the same
  messages from anyone else change nothing and are counted in ``foreign_messages``, and another
  system's HEARTBEAT never changes the mode, the armed state or whom the link addresses;
* on ``udpin`` (and pymavlink's ``udp:``) the transport is a :class:`VehicleUdp`: it talks to the
  vehicle's address only, and drops every other sender's datagrams unparsed
  (``foreign_datagrams``), whatever their number;
* at start, a WARNING when the link runs unsigned and other machines can reach it
  (:func:`unsigned_exposure`: a serial link, a non-loopback host, ``udpin`` on ``0.0.0.0``);
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
import errno
import ipaddress
import logging
import math
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, Self, TypeVar

from service import mavlink_commands
from service.fence import FencePlan
from service.frames import GeoPoint
from service.mission_protocol import (
    FenceReport,
    MavPort,
    MissionError,
    apply_fence_plan,
    param_name,
)
from service.modes import GUIDED_MODE_NAME, Flavour, set_mode_numbers
from service.vehicle_link import HEARTBEAT_PERIOD_S, LinkConfig, VehicleLinkBase

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

T = TypeVar("T")

VEHICLE_MESSAGES = frozenset(
    {
        "HEARTBEAT",
        "LOCAL_POSITION_NED",
        "GLOBAL_POSITION_INT",
        "EXTENDED_SYS_STATE",
        "EKF_STATUS_REPORT",
        "SYS_STATUS",
        "GPS_GLOBAL_ORIGIN",
        "COMMAND_ACK",
        "PARAM_VALUE",
        "STATUSTEXT",
    }
)
"""What the link reads from the vehicle; the same from any other system or component changes
nothing and is counted in ``foreign_messages``."""
DATAGRAMS_PER_READ = 256
"""The most datagrams one read of a :class:`VehicleUdp` takes in (those from other addresses are
dropped unparsed): a flood of them never holds the I/O loop for longer than that."""


class VehicleUdp(mavutil.mavudp):
    """A ``udpin`` transport that talks to one peer, the vehicle; pymavlink's ``mavudp`` extended
    at its ``recv_msg``/``write`` seams.

    pymavlink's own UDP server remembers every address that ever sent it a datagram and sends
    every message to all of them: one datagram from anyone makes it a receiver of every setpoint,
    and thousands of source ports make every send thousands of ``sendto`` calls. This one:

    * sends nothing until :attr:`peer` is set (the link sets it to the address of the vehicle's
      first HEARTBEAT on this transport), then to :attr:`peer` only;
    * once :attr:`peer` is set, drops datagrams from any other address unparsed, counting them in
      :attr:`foreign_datagrams`, at most ``DATAGRAMS_PER_READ`` per read; it remembers no
      sender, so neither memory nor the cost of a send grows with the number of senders;
    * parses each datagram on its own (MAVLink over UDP puts whole packets in a datagram): the
      bytes of a truncated packet never join the next datagram's, and :attr:`source` is the
      sender of the datagram the message just returned came from;
    * binds without ``SO_REUSEADDR`` (pymavlink sets it), so no other local socket can bind the
      same port and take the vehicle's datagrams while this one is open.

    The peer lasts as long as this transport: when the link recreates it (after a loss), the
    vehicle's next HEARTBEAT (from its locked system and component) sets it again, so a vehicle
    that restarted from another source port is found again.
    """

    def __init__(self, host_port: str, source_system: int, source_component: int) -> None:
        host, _, port = host_port.rpartition(":")
        if not host or not port.isdigit():
            raise ValueError(f"udpin: expected HOST:PORT, got {host_port!r}")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((host, int(port)))
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        mavutil.set_close_on_exec(sock.fileno())
        # What mavudp.__init__ sets, for pymavlink's own methods.
        self.port = sock
        self.udp_server = True
        self.broadcast = False
        self.last_address = None
        self.timeout = 0
        self.clients: set[tuple[str, int]] = set()  # pymavlink's list of receivers: stays empty
        self.clients_last_alive: dict[tuple[str, int], float] = {}
        self.resolved_destination_addr = None
        self.peer: tuple[str, int] | None = None
        """The only address sent to and heard from (None: nobody yet)."""
        self.source: tuple[str, int] | None = None
        """The sender of the datagram the last message returned came from."""
        self.foreign_datagrams = 0
        """Datagrams dropped because they came from another address than :attr:`peer`."""
        self._pending: deque[tuple[Any, tuple[str, int]]] = deque()
        mavutil.mavfile.__init__(
            self,
            sock.fileno(),
            host_port,
            source_system=source_system,
            source_component=source_component,
            input=True,
        )

    def recv(self, n: int | None = None) -> bytes:
        """One datagram's bytes from :attr:`peer` (or anyone before it is set); ``b""`` if none
        is waiting."""
        datagram = self._receive()
        return datagram[0] if datagram is not None else b""

    def _receive(self) -> tuple[bytes, tuple[str, int]] | None:
        """The next datagram from :attr:`peer` (from anyone before it is set) and its sender;
        None when none is waiting (after dropping up to ``DATAGRAMS_PER_READ`` others)."""
        for _ in range(DATAGRAMS_PER_READ):
            try:
                data, address = self.port.recvfrom(mavutil.UDP_MAX_PACKET_LEN)
            except OSError as exc:
                # ECONNREFUSED: an ICMP error for something we sent; nothing to read.
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                    return None
                raise
            if self.peer is not None and address != self.peer:
                self.foreign_datagrams += 1
                continue
            return data, address
        return None

    def recv_msg(self) -> Any:
        """The next message from :attr:`peer` (from anyone before it is set), or None (also
        after ``DATAGRAMS_PER_READ`` datagrams without one)."""
        for _ in range(DATAGRAMS_PER_READ):
            if self._pending:
                break
            datagram = self._receive()
            if datagram is None:
                return None
            data, address = datagram
            if self.first_byte:
                self.auto_mavlink_version(data)
            mav = self.mav
            message = mav.parse_char(data)
            while message is not None:
                self.post_message(message)
                self._pending.append((message, address))
                message = mav.parse_char(b"")
            if mav.buf_len() > 0:  # a truncated packet: dropped with its datagram
                mav.buf = bytearray()
                mav.buf_index = 0
                mav.expected_length = mavlink.HEADER_LEN_V1 + 2
                mav.have_prefix_error = False
        if not self._pending:
            return None
        message, self.source = self._pending.popleft()
        return message

    def write(self, buf: bytes) -> None:
        """Send ``buf`` to :attr:`peer`; dropped while there is none."""
        peer = self.peer
        if peer is not None:
            with contextlib.suppress(OSError):  # pymavlink's mavudp ignores them too
                self.port.sendto(buf, peer)


def unsigned_exposure(url: str) -> str | None:
    """Who besides this machine can reach a link on ``url`` (a pymavlink connection string or a
    MAVSDK URL): None when only this machine can (a loopback address), else a phrase that says
    why (``listens on every network interface``, ``talks to 10.0.0.2``, ``is a serial link``)."""
    text = url.strip()
    scheme, sep, rest = text.partition(":")
    scheme = scheme.lower()
    if not sep or text.startswith("/") or scheme == "serial" or text.upper().startswith("COM"):
        return "is a serial link (whatever else is on that radio or cable can inject messages)"
    host = rest.removeprefix("//").rpartition(":")[0].strip("[]")
    listens = scheme in ("udpin", "udp", "tcpin")
    if host in ("", "0.0.0.0", "::"):
        return "listens on every network interface" if listens else f"talks to {host or '?'}"
    if host.lower() == "localhost":
        return None
    try:
        if ipaddress.ip_address(host).is_loopback:
            return None
    except ValueError:
        pass  # a host name: it may resolve to anything
    return f"listens on {host}" if listens else f"talks to {host}"


def warn_if_unsigned(url: str, signed: bool, backend: str) -> bool:
    """Log a WARNING when a link on ``url`` that other machines can reach runs unsigned;
    True when it warned."""
    exposure = unsigned_exposure(url)
    if signed or exposure is None:
        return False
    fix = (
        "set TUPA_MAVLINK_SIGNING_KEY to the vehicle's key"
        if backend == "pymavlink"
        else "the mavsdk backend cannot sign: use the pymavlink backend with "
        "TUPA_MAVLINK_SIGNING_KEY"
    )
    log.warning(
        "UNSIGNED MAVLink link %s %s: anyone who can send to it can feed the service false "
        "telemetry and the vehicle false commands; %s (docs/reliability.md, 'Signing and peers')",
        url,
        exposure,
        fix,
    )
    return True


class MavlinkLink(VehicleLinkBase):
    """The vehicle link and setpoint streamer on pymavlink. See the module docstring."""

    _thread_name = "mavlink-link"

    def __init__(self, config: LinkConfig) -> None:
        super().__init__(config)
        self._send_lock = threading.Lock()
        self._conn: Any = None
        self._t0 = time.monotonic()
        self.counters["signing_failures"] = 0
        self.counters["foreign_messages"] = 0
        self.counters["foreign_datagrams"] = 0
        self._target_sys = 1
        self._target_comp = 1
        self._landed_state: int | None = None
        self._acks: dict[int, tuple[int, int]] = {}
        self._ack_seq = 0
        self._param_values: dict[str, tuple[int, float]] = {}  # name: (answer number, value)
        self._interval_accepted = False
        self._fallback_streams_sent = False

    def start(self) -> Self:
        """Start the I/O thread (returns at once); a WARNING first if the link is unsigned and
        other machines can reach it (:func:`unsigned_exposure`)."""
        warn_if_unsigned(self.config.url, self.config.signing_key is not None, "pymavlink")
        return super().start()

    # ------------------------------------------------------------------ connection

    def _open_transport(self, now: float) -> bool:
        config = self.config
        scheme, _, address = config.url.strip().partition(":")
        try:
            if scheme.lower() in ("udpin", "udp"):  # pymavlink's UDP servers
                mavutil.set_dialect("ardupilotmega")
                conn = VehicleUdp(address, config.source_system, config.source_component)
            else:
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
        if isinstance(conn, VehicleUdp) and conn.foreign_datagrams:
            with self._cond:
                self.counters["foreign_datagrams"] += conn.foreign_datagrams
            conn.foreign_datagrams = 0

    def _handle(self, message: Any) -> None:
        """One message from the link: the vehicle's HEARTBEAT, telemetry, ACKs and STATUSTEXTs
        are taken in; from any other system or component they change nothing
        (``foreign_messages``), and neither does anything else."""
        kind = message.get_type()
        now = time.monotonic()
        if kind == "BAD_DATA":
            with self._cond:
                self.counters["bad_data"] += 1
                if "signature" in str(getattr(message, "reason", "")).lower():
                    self.counters["signing_failures"] += 1
            return
        if kind not in VEHICLE_MESSAGES:
            return
        header = message.get_header()
        if kind == "STATUSTEXT":
            if self._from_vehicle(message):
                self._note_status_text(message.severity, message.text)
            return
        with self._cond:
            if kind == "HEARTBEAT":
                fields = (message.autopilot, message.type, message.base_mode, message.custom_mode)
                if not self._note_heartbeat(
                    *fields,
                    system_id=header.srcSystem,
                    system_status=message.system_status,
                    component_id=header.srcComponent,
                ):
                    return  # a ground station, a companion or another system: not the vehicle
                self._lock_udp_peer()
                if (
                    self.config.signing_key is None
                    and getattr(header, "incompat_flags", 0) & mavlink.MAVLINK_IFLAG_SIGNED
                ):
                    # It signs, we cannot: it will most likely ignore what we send.
                    self.counters["signed_vehicle_without_key"] += 1
                self._target_sys, self._target_comp = header.srcSystem, header.srcComponent
            elif not self._vehicle_ids_match(header.srcSystem, header.srcComponent):
                return  # not the vehicle's (counted), or before its first HEARTBEAT
            elif kind == "LOCAL_POSITION_NED":
                self._ned = (message.x, message.y, message.z)
                self._ned_velocity = (message.vx, message.vy, message.vz)
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
            elif kind == "GPS_GLOBAL_ORIGIN":
                m = message
                self._note_origin(GeoPoint(m.latitude / 1e7, m.longitude / 1e7, m.altitude / 1e3))
            elif kind == "SYS_STATUS":
                # battery_remaining: % (-1: unknown); voltage_battery: mV (UINT16_MAX: unknown).
                self._note_battery(
                    now,
                    message.battery_remaining if message.battery_remaining >= 0 else None,
                    None if message.voltage_battery == 65535 else message.voltage_battery / 1000.0,
                )
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
            elif kind == "PARAM_VALUE" and message.param_type == mavlink.MAV_PARAM_TYPE_REAL32:
                self._ack_seq += 1
                self._param_values[param_name(message)] = (self._ack_seq, message.param_value)
            self._cond.notify_all()

    def _on_link_up(self, now: float) -> None:
        self._interval_accepted = False
        self._fallback_streams_sent = False

    def _from_vehicle(self, message: Any) -> bool:
        """The message comes from the vehicle (its locked system and component); one from
        another is counted in ``foreign_messages``."""
        with self._cond:
            return self._vehicle_ids_match(message.get_srcSystem(), message.get_srcComponent())

    def _lock_udp_peer(self) -> None:
        """On ``udpin``: the vehicle's HEARTBEAT came from its address, the only one this
        transport talks to and hears from now on (call under ``self._cond``)."""
        conn = self._conn
        if isinstance(conn, VehicleUdp) and conn.peer is None and conn.source is not None:
            conn.peer = conn.source
            log.info("udpin: the vehicle is at %s:%d; no other sender is heard", *conn.peer)

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
            (mavlink.MAVLINK_MSG_ID_SYS_STATUS, 1.0),  # the battery (service.battery)
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

    def _request_origin(self) -> None:
        self._send_command_long(
            mavlink.MAV_CMD_REQUEST_MESSAGE,
            (float(mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        )

    def _upload_fence(self, plan: FencePlan) -> FenceReport:
        """The fence through :func:`service.mission_protocol.apply_fence_plan` on this link's
        own connection, borrowed by the I/O thread: what else arrives meanwhile is handled as
        usual, and our HEARTBEAT keeps going."""
        conn = self._conn
        if conn is None:
            raise MissionError("the connection closed before the fence upload")
        next_heartbeat = [time.monotonic() + HEARTBEAT_PERIOD_S]

        def send(message: Any) -> None:
            if not self._send(lambda mav: mav.send(message)):
                raise OSError("the connection to the vehicle is down")

        def idle() -> None:
            if time.monotonic() >= next_heartbeat[0]:
                next_heartbeat[0] = time.monotonic() + HEARTBEAT_PERIOD_S
                self._send_heartbeat()

        with self._cond:
            sys_id, comp_id = self._target_sys, self._target_comp
        port = MavPort(
            send=send,
            receive=lambda timeout_s: conn.recv_match(blocking=True, timeout=timeout_s),
            target_system=sys_id,
            target_component=comp_id,
            on_other=self._handle,
            on_idle=idle,
            own_system=self.config.source_system,
        )
        try:
            return apply_fence_plan(port, plan)
        except OSError as exc:
            raise MissionError(f"the fence upload lost the connection: {exc}") from None

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

        def send() -> None:
            with self._cond:
                self.counters["commands_sent"] += 1
            self._send_command_long(command, params)

        def answer() -> int | None:
            seq, result = self._acks.get(command, (0, -1))
            return result if seq > seq_before else None

        return self._resend_until(send, answer, timeout_s)

    def _param_float(self, name: str, value: float | None, timeout_s: float) -> float | None:
        """PARAM_SET of ``value`` (None: PARAM_REQUEST_READ), re-sent every
        ``COMMAND_RESEND_S`` until a PARAM_VALUE of ``name`` newer than the request answers or
        ``timeout_s`` passes: the value it reports, or None."""
        with self._cond:
            seq_before = self._ack_seq
            sys_id, comp_id = self._target_sys, self._target_comp
        if value is None:
            request = mavlink.MAVLink_param_request_read_message(sys_id, comp_id, name.encode(), -1)
        else:
            request = mavlink.MAVLink_param_set_message(
                sys_id, comp_id, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32
            )

        def answer() -> float | None:
            seq, reported = self._param_values.get(name, (0, math.nan))
            return float(reported) if seq > seq_before else None

        return self._resend_until(
            lambda: self._send(lambda mav: mav.send(request)), answer, timeout_s
        )

    def _resend_until(
        self, send: Callable[[], object], answer: Callable[[], T | None], timeout_s: float
    ) -> T | None:
        """``send()`` every ``COMMAND_RESEND_S`` until ``answer()`` (called under
        ``self._cond``, woken by every message taken in) is not None, or ``timeout_s`` passes
        (None)."""
        ask_until = time.monotonic() + timeout_s
        while not self._stop.is_set():
            send()
            resend_at = min(ask_until, time.monotonic() + COMMAND_RESEND_S)
            with self._cond:
                while not self._stop.is_set():
                    got = answer()
                    if got is not None:
                        return got
                    remaining = resend_at - time.monotonic()
                    if remaining <= 0:
                        break
                    self._cond.wait(remaining)
            if time.monotonic() >= ask_until:
                return None
        return None

    def _ask_arm(self, timeout_s: float) -> int | None:
        return self._ask(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink_commands.arm(), timeout_s)
