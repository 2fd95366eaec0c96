"""The native MAVSDK plumbing under :class:`~service.mavsdk_link.MavsdkLink`: connection URLs,
MAVSDK's log lines, and the lifetime of one MAVSDK instance (:class:`Session`).

* :func:`mavsdk_url` turns a pymavlink connection string into a MAVSDK URL.
* :func:`route_mavsdk_logs_to_python` sends MAVSDK's own log lines to the ``mavsdk`` logger: its
  callback (on MAVSDK's native threads) only queues a line, and a thread of ours logs it, so no
  logging handler ever runs on a MAVSDK thread.
* :class:`PeerUdp`: the socket under a ``udpin`` session. MAVSDK's own UDP server sends every
  message to every address it has heard from; a ``udpin`` session is instead a MAVSDK ``raw://``
  connection over this socket, which talks to the vehicle's address only.
* :class:`Session`: one MAVSDK instance, its connection and plugins, made and torn down safely.
  Tearing a session down (link loss, close) first waits, up to ``UNANSWERED_WAIT_S``, for MAVSDK
  to answer the asynchronous calls still in flight (an ``Offboard.start`` is asked for every
  ``mode_retry_s``), and keeps their ctypes callbacks alive until the instance is destroyed:
  destroying the plugins with a command in flight crashed the process natively (SIGSEGV inside
  the plugins' destroy; see ``benchmarks/mavsdk_link_loss.py``).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import queue
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from service.vehicle_link import LinkConfig, mavlink

log = logging.getLogger(__name__)

UNANSWERED_WAIT_S = 3.0
"""How long closing a session waits for MAVSDK to answer the calls still open. MAVSDK answers an
unacknowledged command with a timeout after its own retries (3 tries by default); this bound is
meant to leave room for that, not to be reached."""

_MAVSDK_LOG_LEVELS = (logging.DEBUG, logging.DEBUG, logging.INFO, logging.WARNING)
"""MAVSDK's levels (debug, info, warn, err) one step down: it reports every failed connection
attempt as an error, and the link retries an unreachable vehicle for as long as it runs (its own
state says so)."""
_mavsdk_log_lines: queue.SimpleQueue[tuple[int, str, str | None, int]] = queue.SimpleQueue()
_log_thread: threading.Thread | None = None
_log_route_lock = threading.Lock()


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


DATAGRAMS_PER_READ = 256
"""The most datagrams one :meth:`PeerUdp.read` takes in: a flood never holds the I/O loop."""
HEARTBEAT_SOURCES_KEPT = 256
"""How many (system, component) → address entries :class:`PeerUdp` keeps before the peer is
chosen (it forgets them all past that, so a spray of ids cannot grow it)."""


def packets(datagram: bytes) -> list[tuple[int, int, int, int, int]]:
    """``(start, end, system, component, message id)`` of each MAVLink 1 or 2 packet in a
    datagram, read from the headers (neither checksums nor signatures are checked: MAVSDK does
    that); the walk stops at the first byte that starts no whole packet."""
    found = []
    at, size = 0, len(datagram)
    while at + 8 <= size:
        magic, length = datagram[at], datagram[at + 1]
        if magic == 0xFD and at + 12 <= size:
            signed = datagram[at + 2] & mavlink.MAVLINK_IFLAG_SIGNED
            end = at + 12 + length + (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if signed else 0)
            ids = (datagram[at + 5], datagram[at + 6])
            message_id = int.from_bytes(datagram[at + 7 : at + 10], "little")
        elif magic == 0xFE:
            end = at + 8 + length
            ids, message_id = (datagram[at + 3], datagram[at + 4]), datagram[at + 5]
        else:
            break
        if end > size:
            break
        found.append((at, end, *ids, message_id))
        at = end
    return found


class PeerUdp:
    """The socket under a ``udpin`` session, a MAVSDK ``raw://`` connection: it receives on
    ``host:port`` and hands what it receives to MAVSDK, and sends what MAVSDK sends to one
    address, :attr:`peer`, the vehicle's (see :meth:`choose_peer`).

    Until the peer is chosen every datagram goes to MAVSDK (so that it can discover the vehicle)
    and nothing is sent. From then on datagrams from other addresses are dropped unread
    (:attr:`foreign_datagrams`), and of the peer's only the packets of the vehicle's system and
    component go to MAVSDK (:attr:`foreign_packets` counts the others): MAVSDK's plugins take a
    system's telemetry from any of its components. Nothing is kept per sender but the address of
    the latest HEARTBEAT of each (system, component), at most ``HEARTBEAT_SOURCES_KEPT`` of them
    and only until the peer is chosen. The socket is bound without ``SO_REUSEADDR``: no other
    local socket can share the port.
    """

    def __init__(self, host: str, port: int) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((host, port))
        except OSError:
            sock.close()
            raise
        sock.setblocking(False)
        self.sock = sock
        self.peer: tuple[str, int] | None = None
        self.vehicle_ids: tuple[int, int] | None = None
        self.foreign_datagrams = 0
        self.foreign_packets = 0
        self._heartbeat_sources: dict[tuple[int, int], tuple[str, int]] = {}

    def fileno(self) -> int:
        return self.sock.fileno()

    def read(self) -> list[bytes]:
        """What MAVSDK should parse of the datagrams waiting (at most ``DATAGRAMS_PER_READ`` are
        taken in): anyone's before the peer is chosen, then the vehicle's packets only."""
        datagrams = []
        for _ in range(DATAGRAMS_PER_READ):
            try:
                data, address = self.sock.recvfrom(65535)
            except OSError as exc:
                if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                    break
                raise
            if self.peer is None:
                if len(self._heartbeat_sources) >= HEARTBEAT_SOURCES_KEPT:
                    self._heartbeat_sources.clear()
                for _, _, system_id, component_id, message_id in packets(data):
                    if message_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                        self._heartbeat_sources[(system_id, component_id)] = address
            elif address != self.peer:
                self.foreign_datagrams += 1
                continue
            else:
                data = self._vehicles_packets(data)
            if data:
                datagrams.append(data)
        return datagrams

    def _vehicles_packets(self, data: bytes) -> bytes:
        """The packets of ``data`` from the vehicle's system and component, in order."""
        found = packets(data)
        kept = [(a, b) for a, b, *ids, _ in found if tuple(ids) == self.vehicle_ids]
        self.foreign_packets += len(found) - len(kept)
        if len(kept) == len(found) and found and found[-1][1] == len(data):
            return data
        return b"".join(data[a:b] for a, b in kept)

    def choose_peer(self, system_id: int, component_id: int) -> bool:
        """Talk only to the address the latest HEARTBEAT of ``system_id``/``component_id`` came
        from, and take in only that system and component's packets; False (and no peer) when no
        such HEARTBEAT came."""
        address = self._heartbeat_sources.get((system_id, component_id))
        if address is None:
            return False
        self.peer, self.vehicle_ids = address, (system_id, component_id)
        self._heartbeat_sources.clear()
        log.info("udpin: the vehicle is at %s:%d; no other sender is heard", *address)
        return True

    def send(self, data: bytes) -> None:
        """MAVSDK's outgoing bytes (on a MAVSDK thread): to the peer, dropped before it."""
        peer = self.peer
        if peer is not None:
            with contextlib.suppress(OSError):
                self.sock.sendto(data, peer)

    def close(self) -> None:
        self.sock.close()


def udpin_address(url: str) -> tuple[str, int] | None:
    """``(host, port)`` of a MAVSDK ``udpin://HOST:PORT`` (or ``udp://``) URL; None for others."""
    scheme, sep, rest = url.partition("://")
    if not sep or scheme.lower() not in ("udpin", "udp"):
        return None
    host, _, port = rest.rpartition(":")
    return (host, int(port)) if host and port.isdigit() else None


@dataclass
class Session:
    """One MAVSDK instance, its connection and (once the vehicle is found) its plugins."""

    sdk: Any
    opened_at: float
    system: Any = None
    system_id: int | None = None
    telemetry: Any = None
    action: Any = None
    offboard: Any = None
    direct: Any = None
    geofence: Any = None
    param: Any = None
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
    udp: PeerUdp | None = None
    """For ``udpin``: the socket under the instance's ``raw://`` connection (the link feeds it
    to MAVSDK); None for other URLs, which MAVSDK connects itself."""

    @classmethod
    def open(cls, url: str, config: LinkConfig, now: float) -> Session | None:
        """A MAVSDK instance connecting to ``url`` (a MAVSDK URL) with our ids and HEARTBEAT
        type from ``config``; None when the connection cannot be made (cannot bind, ...).
        ``udpin`` becomes a ``raw://`` connection over a :class:`PeerUdp`."""
        from mavsdk import ComponentType, Configuration, Mavsdk

        component_type = (
            ComponentType.GROUND_STATION
            if config.heartbeat_type == mavlink.MAV_TYPE_GCS
            else ComponentType.COMPANION_COMPUTER
        )
        configuration = Configuration.create_with_component_type(component_type)
        configuration.system_id = config.source_system
        configuration.component_id = config.source_component
        sdk = Mavsdk(configuration)
        udp: PeerUdp | None = None
        try:
            address = udpin_address(url)
            if address is None:
                sdk.add_any_connection_with_handle(url)
            else:
                udp = PeerUdp(*address)
                sdk.subscribe_raw_bytes_to_be_sent(udp.send)  # first: MAVSDK sends at once
                sdk.add_any_connection_with_handle("raw://")
        except Exception as exc:  # cannot bind; MAVSDK's ConnectionError: refused, ...
            log.debug("cannot open %s: %s", url, exc)
            sdk.destroy()
            configuration.destroy()
            if udp is not None:
                udp.close()
            return None
        return cls(sdk, now, keep=[configuration], udp=udp)

    def make_plugins(self, system: Any) -> None:
        """The plugins the link uses, for the autopilot ``system`` MAVSDK found."""
        from mavsdk.plugins.action import Action
        from mavsdk.plugins.geofence import Geofence
        from mavsdk.plugins.mavlink_direct import MavlinkDirect
        from mavsdk.plugins.offboard import Offboard
        from mavsdk.plugins.param import Param
        from mavsdk.plugins.telemetry import Telemetry

        self.system = system
        self.system_id = system.get_system_id()
        self.telemetry = Telemetry(system)
        self.action = Action(system)
        self.offboard = Offboard(system)
        self.direct = MavlinkDirect(system)
        self.geofence = Geofence(system)
        self.param = Param(system)

    def renew_offboard(self) -> None:
        """A fresh Offboard plugin: ends MAVSDK's own re-sending of the last setpoint without a
        mode change (``Offboard.stop`` would also switch to Hold)."""
        from mavsdk.plugins.offboard import Offboard

        self.hold_callbacks(self.offboard)  # an Offboard.start may be pending
        self.offboard.destroy()
        self.offboard = Offboard(self.system)
        self.offboard_fed = False

    def close(self) -> None:
        """Tear the instance down once MAVSDK has answered the calls in flight (see the module
        docstring); no MAVSDK callback comes after it."""
        # Destroying a plugin whose command MAVSDK has not answered yet can crash MAVSDK when
        # the answer (or the timeout) comes: let them finish first.
        if not self.wait_answered(UNANSWERED_WAIT_S):
            log.debug("closing the MAVSDK session with %d calls unanswered", self.unanswered)
        for plugin in (
            self.telemetry,
            self.action,
            self.offboard,
            self.direct,
            self.geofence,
            self.param,
        ):
            self.hold_callbacks(plugin)
        with contextlib.suppress(Exception):
            self.sdk.destroy()  # joins MAVSDK's threads: no callback comes after it
        if self.udp is not None:
            self.udp.close()  # after: MAVSDK sends nothing more into it
        self.trampolines.clear()
        for item in self.keep:
            with contextlib.suppress(Exception):
                item.destroy()

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
