"""The transport: serve one simulated vehicle over TCP (several clients at once) or UDP.

:class:`MockAutopilot` is the programmatic entry point (the ``tupa sitl-mock`` command is a thin
wrapper around it)::

    with MockAutopilot("tcp:127.0.0.1:0", flavour="ardupilot", config=VehicleConfig(...)) as mock:
        connect_to(f"tcp:127.0.0.1:{mock.port}")
        ...
        assert mock.stats["signing_rejected"] == 0

One background thread runs a ``selectors`` loop: it accepts TCP clients, reads what every peer
sends, steps the vehicle at ``physics_rate_hz`` (50 Hz) of wall-clock time and sends the telemetry
that is due. The vehicle's own clock (its physics, its telemetry rates, its failsafe and arming
timers: everything but the transport) runs ``speedup`` times the wall clock, as ArduPilot SITL's
``--speedup`` does; 1 (the default) is real time. All vehicle and protocol state is touched
under one lock, so tests may read :meth:`MockAutopilot.state` or call
:meth:`MockAutopilot.with_vehicle` from their own thread.

Listen specs (pymavlink-style):

* ``tcp:HOST:PORT`` — TCP server (ArduPilot SITL's 5760); any number of clients.
* ``udp:HOST:PORT`` — bind a UDP port and talk to whoever sends to it (each remote address is a
  separate client; silent ones are forgotten after 10 s).
* ``udpout:HOST:PORT`` — send to a fixed remote address from an ephemeral port, as PX4 SITL sends
  to 14540/14550 (clients listen with ``udpin:``).

Port 0 picks a free port; :attr:`MockAutopilot.port` tells which.
"""

from __future__ import annotations

import contextlib
import logging
import math
import selectors
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar

from sitl_mock.config import VehicleConfig
from sitl_mock.flavours import Flavour, get_flavour
from sitl_mock.protocol import Link, MavlinkProtocol
from sitl_mock.vehicle import Vehicle, VehicleState

log = logging.getLogger(__name__)

T = TypeVar("T")

KEY_COUNTERS = (
    "clients_total",
    "gcs_heartbeats",
    "messages_received",
    "bad_data",
    "unknown_messages",
    "signing_rejected",
    "not_for_us",
    "commands",
    "commands_unsupported",
    "handler_errors",
    "setpoints_received",
    "setpoints_accepted",
    "setpoints_buffered",
    "setpoints_rejected_invalid",
    "setpoints_rejected_fence",
    "setpoints_ignored_mode",
    "takeoffs_cancelled",
    "failsafe_offboard",
    "failsafe_gcs",
    "failsafe_battery",
    "failsafe_fence",
    "fence_uploads",
    "fence_uploads_refused",
    "fence_breaches",
)
"""Counters :attr:`MockAutopilot.stats` always has (0 until something happens)."""
MAX_OUTBUF_BYTES = 1 << 20
"""A TCP client that lets more than this pile up unread is disconnected (it is not reading)."""
UDP_PEER_TIMEOUT_S = 10.0
MAX_STEP_S = 0.02
MAX_CATCH_UP_S = 0.5
MAX_SPEEDUP = 10.0
"""The fastest a vehicle's clock may run against the wall clock (:attr:`MockAutopilot.speedup`)."""


@dataclass(frozen=True)
class ListenSpec:
    """A parsed ``--listen`` value."""

    kind: str
    """``tcp``, ``udp`` (bind and answer senders) or ``udpout`` (send to a fixed address)."""
    host: str
    port: int

    def __str__(self) -> str:
        return f"{self.kind}:{self.host}:{self.port}"


def parse_listen(spec: str) -> ListenSpec:
    """Parse ``tcp:HOST:PORT``, ``udp:HOST:PORT`` or ``udpout:HOST:PORT`` (ValueError if bad)."""
    aliases = {"tcp": "tcp", "tcpin": "tcp", "udp": "udp", "udpin": "udp", "udpout": "udpout"}
    parts = spec.split(":")
    if len(parts) != 3 or parts[0].lower() not in aliases:
        raise ValueError(f"expected tcp:HOST:PORT, udp:HOST:PORT or udpout:HOST:PORT, got {spec!r}")
    kind, host, port_text = aliases[parts[0].lower()], parts[1], parts[2]
    if not host:
        raise ValueError(f"missing host in {spec!r}")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"port must be a number, got {port_text!r}") from None
    if not 0 <= port <= 65535 or (kind == "udpout" and port == 0):
        raise ValueError(f"port out of range in {spec!r}")
    return ListenSpec(kind, host, port)


class _TcpClient:
    def __init__(self, sock: socket.socket, name: str) -> None:
        self.sock = sock
        self.name = name
        self.outbuf = bytearray()
        self.link: Link | None = None
        self.closed = False

    def write(self, data: bytes) -> None:
        if not self.closed:
            self.outbuf += data


class _UdpPeer:
    def __init__(self, address: tuple[str, int], link: Link, fixed: bool, now: float) -> None:
        self.address = address
        self.link = link
        self.fixed = fixed
        self.last_rx = now


class MockAutopilot:
    """A MAVLink autopilot simulator in a background thread. See the module docstring."""

    def __init__(
        self,
        listen: str = "tcp:127.0.0.1:0",
        flavour: str | Flavour = "ardupilot",
        config: VehicleConfig | None = None,
        signing_key: bytes | None = None,
        system_id: int = 1,
        component_id: int = 1,
        physics_rate_hz: float = 50.0,
        speedup: float = 1.0,
    ) -> None:
        if not 1 <= system_id <= 255 or not 1 <= component_id <= 255:
            raise ValueError("system_id and component_id must be in 1..255")
        if not physics_rate_hz > 0:
            raise ValueError("physics_rate_hz must be positive")
        if not (math.isfinite(speedup) and 0 < speedup <= MAX_SPEEDUP):
            raise ValueError(f"speedup: must be in (0, {MAX_SPEEDUP:g}], got {speedup!r}")
        self.speedup = float(speedup)
        """Simulated seconds per wall-clock second (ArduPilot SITL's ``--speedup``)."""
        self.listen = parse_listen(listen)
        self.flavour = get_flavour(flavour) if isinstance(flavour, str) else flavour
        self.vehicle = Vehicle(self.flavour, config)
        self.protocol = MavlinkProtocol(self.vehicle, system_id, component_id, signing_key)
        self._tick_s = 1.0 / physics_rate_hz
        self._lock = threading.RLock()
        self._links: list[Link] = []
        self.protocol.set_links(self._links)
        self._transport_stats: Counter[str] = Counter()
        self._selector: selectors.BaseSelector | None = None
        self._server_sock: socket.socket | None = None
        self._udp_sock: socket.socket | None = None
        self._tcp_clients: dict[int, _TcpClient] = {}
        self._udp_peers: dict[tuple[str, int], _UdpPeer] = {}
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()
        self._port = 0

    # ------------------------------------------------------------------ public API

    def start(self) -> MockAutopilot:
        """Bind the socket and start serving (OSError if the address cannot be bound)."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._selector = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, ("wake", None))
        try:
            if self.listen.kind == "tcp":
                self._open_tcp()
            else:
                self._open_udp()
        except OSError:
            self._close_all()
            raise
        self._thread = threading.Thread(
            target=self._run, name=f"sitl-mock-{self.listen.kind}-{self._port}", daemon=True
        )
        self._thread.start()
        log.info(
            "%s autopilot (sysid %d) serving on %s",
            self.flavour.name,
            self.protocol.system_id,
            self.address,
        )
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop serving, close every socket and wait for the thread (safe to call twice)."""
        self._stopping.set()
        if self._wake_w is not None:
            with contextlib.suppress(OSError):
                self._wake_w.send(b"x")
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("sitl-mock thread did not stop within %.1f s", timeout_s)
            self._thread = None
        self._close_all()

    def __enter__(self) -> MockAutopilot:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def port(self) -> int:
        """The bound local port (the real one when started with port 0)."""
        return self._port

    @property
    def address(self) -> str:
        """Where clients connect: e.g. ``tcp:127.0.0.1:5760``."""
        if self.listen.kind == "udpout":
            return f"udpout:{self.listen.host}:{self.listen.port} (from port {self._port})"
        return f"{self.listen.kind}:{self.listen.host}:{self._port}"

    @property
    def stats(self) -> dict[str, int]:
        """Counters of everything noteworthy: messages, rejections by reason, failsafes, links."""
        with self._lock:
            merged = Counter(dict.fromkeys(KEY_COUNTERS, 0))
            merged.update(self.protocol.stats)
            merged.update(self.vehicle.counters)
            merged.update(self._transport_stats)
            merged["links_open"] = len(self._links)
            return dict(merged)

    def state(self) -> VehicleState:
        """A consistent snapshot of the vehicle."""
        with self._lock:
            return self.vehicle.snapshot()

    def with_vehicle(self, fn: Callable[[Vehicle], T]) -> T:
        """Run ``fn(vehicle)`` under the server's lock (for tests that poke the vehicle)."""
        with self._lock:
            return fn(self.vehicle)

    # ------------------------------------------------------------------ sockets

    def _open_tcp(self) -> None:
        assert self._selector is not None
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._server_sock = sock
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((self.listen.host, self.listen.port))
        sock.listen(8)
        sock.setblocking(False)
        self._port = sock.getsockname()[1]
        self._selector.register(sock, selectors.EVENT_READ, ("accept", None))

    def _open_udp(self) -> None:
        assert self._selector is not None
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._udp_sock = sock
        if self.listen.kind == "udp":
            sock.bind((self.listen.host, self.listen.port))
        else:
            sock.bind(("0.0.0.0", 0))
        sock.setblocking(False)
        self._port = sock.getsockname()[1]
        self._selector.register(sock, selectors.EVENT_READ, ("udp", None))
        if self.listen.kind == "udpout":
            address = (socket.gethostbyname(self.listen.host), self.listen.port)
            self._add_udp_peer(address, fixed=True)

    def _close_all(self) -> None:
        with self._lock:
            for client in list(self._tcp_clients.values()):
                self._close_client(client, "server stopping")
            self._udp_peers.clear()
            self._links.clear()
        for sock in (self._server_sock, self._udp_sock, self._wake_r, self._wake_w):
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.close()
        self._server_sock = self._udp_sock = self._wake_r = self._wake_w = None
        if self._selector is not None:
            self._selector.close()
            self._selector = None

    def _accept(self) -> None:
        assert self._server_sock is not None and self._selector is not None
        try:
            sock, address = self._server_sock.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        name = f"tcp {address[0]}:{address[1]}"
        client = _TcpClient(sock, name)
        client.link = self.protocol.new_link(name, client.write)
        self._tcp_clients[sock.fileno()] = client
        self._links.append(client.link)
        self._selector.register(sock, selectors.EVENT_READ, ("tcp", client))
        self._transport_stats["clients_total"] += 1
        log.info("%s connected (%d open)", name, len(self._tcp_clients))

    def _read_tcp(self, client: _TcpClient) -> None:
        try:
            data = client.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._close_client(client, f"receive error: {exc}")
            return
        if not data:
            self._close_client(client, "closed by peer")
            return
        assert client.link is not None
        self.protocol.receive(client.link, data)

    def _flush_tcp(self, client: _TcpClient) -> None:
        if client.closed or not client.outbuf:
            return
        try:
            sent = client.sock.send(client.outbuf)
        except (BlockingIOError, InterruptedError):
            sent = 0
        except OSError as exc:
            self._close_client(client, f"send error: {exc}")
            return
        del client.outbuf[:sent]
        if len(client.outbuf) > MAX_OUTBUF_BYTES:
            self._transport_stats["clients_dropped_slow"] += 1
            self._close_client(client, "not reading (output buffer full)")

    def _close_client(self, client: _TcpClient, reason: str) -> None:
        if client.closed:
            return
        client.closed = True
        if self._selector is not None:
            with contextlib.suppress(KeyError, ValueError):
                self._selector.unregister(client.sock)
        self._tcp_clients = {k: c for k, c in self._tcp_clients.items() if c is not client}
        if client.link in self._links:
            self._links.remove(client.link)
        with contextlib.suppress(OSError):
            client.sock.close()
        log.info("%s disconnected: %s (%d open)", client.name, reason, len(self._tcp_clients))

    def _add_udp_peer(self, address: tuple[str, int], fixed: bool) -> _UdpPeer:
        sock = self._udp_sock
        assert sock is not None
        name = f"udp {address[0]}:{address[1]}"

        def write(data: bytes) -> None:
            try:
                sock.sendto(data, address)
            except OSError:
                self._transport_stats["udp_send_errors"] += 1

        link = self.protocol.new_link(name, write)
        peer = _UdpPeer(address, link, fixed, time.monotonic())
        self._udp_peers[address] = peer
        self._links.append(link)
        self._transport_stats["clients_total"] += 1
        log.info("%s %s", name, "is the fixed peer" if fixed else "appeared")
        return peer

    def _read_udp(self) -> None:
        sock = self._udp_sock
        assert sock is not None
        for _ in range(64):  # bounded: let the physics tick run under a flood
            try:
                data, address = sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                # e.g. ICMP port unreachable from a peer that went away
                self._transport_stats["udp_receive_errors"] += 1
                continue
            peer = self._udp_peers.get(address) or self._add_udp_peer(address, fixed=False)
            peer.last_rx = time.monotonic()
            self.protocol.receive(peer.link, data)

    def _expire_udp_peers(self, now: float) -> None:
        for address, peer in list(self._udp_peers.items()):
            if not peer.fixed and now - peer.last_rx > UDP_PEER_TIMEOUT_S:
                del self._udp_peers[address]
                self._links.remove(peer.link)
                log.info("%s silent for %.0f s: forgotten", peer.link.name, UDP_PEER_TIMEOUT_S)

    # ------------------------------------------------------------------ the loop

    def _run(self) -> None:
        last = time.monotonic()
        next_tick = last
        while not self._stopping.is_set():
            try:
                selector = self._selector
                if selector is None:
                    return
                timeout = max(0.0, next_tick - time.monotonic())
                events = selector.select(timeout)
                with self._lock:
                    for key, _mask in events:
                        kind, client = key.data
                        if kind == "accept":
                            self._accept()
                        elif kind == "tcp":
                            self._read_tcp(client)
                        elif kind == "udp":
                            self._read_udp()
                        else:
                            self._drain_wake()
                    now = time.monotonic()
                    if now >= next_tick:
                        self._physics(min(now - last, MAX_CATCH_UP_S) * self.speedup)
                        last = now
                        next_tick += self._tick_s
                        if next_tick < now:
                            next_tick = now + self._tick_s
                        self._expire_udp_peers(now)
                    self._flush_all()
            except Exception:
                self._transport_stats["loop_errors"] += 1
                log.exception("sitl-mock loop error (carrying on)")
                time.sleep(self._tick_s)

    def _physics(self, elapsed_s: float) -> None:
        vehicle = self.vehicle
        while elapsed_s > 1e-9:
            dt_s = min(elapsed_s, MAX_STEP_S)
            vehicle.step(dt_s)
            elapsed_s -= dt_s
        self.protocol.tick(self._links)

    def _flush_all(self) -> None:
        for client in list(self._tcp_clients.values()):
            self._flush_tcp(client)
            if client.closed or self._selector is None:
                continue
            events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.outbuf else 0)
            key = self._selector.get_key(client.sock)
            if key.events != events:
                self._selector.modify(client.sock, events, key.data)

    def _drain_wake(self) -> None:
        assert self._wake_r is not None
        try:
            while self._wake_r.recv(4096):
                pass
        except (BlockingIOError, InterruptedError, OSError):
            pass
