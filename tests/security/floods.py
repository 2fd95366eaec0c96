"""Hostile HTTP clients for the flood tests and ``benchmarks/http_floods.py``: raw sockets, each
bound to a loopback source address of its own (``127.0.0.2``, ``127.0.0.3``, ...: Linux routes
all of ``127.0.0.0/8`` to the loopback interface), so that one test machine plays many clients.

Every flood runs in one thread, is bounded in time and in the connections it opens, and is
stopped (its sockets closed) on ``stop()`` or at the end of a ``with`` block.
"""

from __future__ import annotations

import contextlib
import random
import re
import selectors
import socket
import string
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import httpx


def loopback_sources(first: int, count: int) -> list[str]:
    """``count`` loopback addresses from ``127.0.0.<first>`` on."""
    return [f"127.0.0.{first + i}" for i in range(count)]


def connect_from(source: str, port: int, timeout_s: float = 2.0) -> socket.socket:
    """A TCP connection to ``127.0.0.1:port`` from ``source`` (any free port there)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.settimeout(timeout_s)
        sock.bind((source, 0))
        sock.connect(("127.0.0.1", port))
    except OSError:
        sock.close()
        raise
    return sock


_TCP_CLOSE, _TCP_CLOSE_WAIT = 7, 8  # Linux's tcp_states.h


def is_closed_by_peer(sock: socket.socket) -> bool:
    """Whether the server closed (FIN) or reset ``sock``, read from the kernel's TCP state
    (Linux: whatever is still unread in its buffer); never waits."""
    state = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 1)[0]
    return state in (_TCP_CLOSE, _TCP_CLOSE_WAIT)


def http_get(port: int, path: str, source: str = "127.0.0.1", timeout_s: float = 5.0) -> bytes:
    """``GET path`` on a new connection from ``source`` (``Connection: close``): the whole
    answer. ``OSError`` if the connection fails or is cut."""
    with connect_from(source, port, timeout_s) as sock:
        sock.sendall(f"GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n".encode())
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


def scrape(port: int) -> dict[str, float]:
    """The HTTP connection metrics of ``/metrics`` (``name`` or ``name{labels}`` → value) and
    the size of the text (``bytes``)."""
    text = http_get(port, "/metrics").split(b"\r\n\r\n", 1)[1].decode()
    values = {"bytes": float(len(text))}
    for line in text.splitlines():
        if line.startswith(("tupa_http_connections", "tupa_http_clients")):
            name, value = line.rsplit(" ", 1)
            values[name] = float(value)
    return values


def closed_by(values: dict[str, float], reason: str) -> float:
    return values.get(f'tupa_http_connections_closed_total{{reason="{reason}"}}', 0.0)


def percentile(values: Sequence[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


class Worker:
    """A thread running ``self.run`` until ``stop()``; a ``with`` block starts and stops it."""

    def __init__(self, name: str) -> None:
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self.run, name=name, daemon=True)

    def run(self) -> None:
        raise NotImplementedError

    def start(self) -> None:
        self.thread.start()

    def stop(self) -> None:
        self.stopping.set()
        self.thread.join(15.0)
        assert not self.thread.is_alive(), f"{self.thread.name} did not stop"

    def __enter__(self) -> Worker:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class HealthProbe(Worker):
    """``GET /healthz`` on a new connection (as an orchestrator's probe) every ``interval_s``,
    recording each answer's latency and every failure (not 200, or the connection cut)."""

    def __init__(self, port: int, interval_s: float = 0.02, source: str = "127.0.0.1") -> None:
        super().__init__("health-probe")
        self.port = port
        self.interval_s = interval_s
        self.source = source
        self.latencies_s: list[float] = []
        self.failures: list[str] = []

    def run(self) -> None:
        while not self.stopping.is_set():
            began = time.perf_counter()
            try:
                answer = http_get(self.port, "/healthz", self.source)
                if not answer.startswith(b"HTTP/1.1 200"):
                    self.failures.append(answer[:40].decode(errors="replace"))
            except OSError as exc:
                self.failures.append(type(exc).__name__)
            self.latencies_s.append(time.perf_counter() - began)
            self.stopping.wait(self.interval_s)


def report_body(timestamp: float) -> dict[str, object]:
    users = [
        {
            "id": f"ue-{i}",
            "x_m": 100.0 + 50 * i,
            "y_m": 200.0,
            "offered_bps": 5e6,
            "throughput_bps": 4e6,
            "delay_s": 0.05,
            "plr": 0.01,
        }
        for i in range(3)
    ]
    return {"timestamp": timestamp, "users": users}


class Reporter(Worker):
    """The network controller: ``POST /v1/reports`` every ``interval_s`` on a keep-alive
    connection, recording each status (or the transport error) and latency."""

    def __init__(self, port: int, token: str, interval_s: float = 0.2) -> None:
        super().__init__("reporter")
        self.port = port
        self.token = token
        self.interval_s = interval_s
        self.statuses: list[str] = []
        self.latencies_s: list[float] = []

    def run(self) -> None:
        with httpx.Client(
            base_url=f"http://127.0.0.1:{self.port}",
            headers={"Authorization": f"Bearer {self.token}"},
            timeout=5.0,
        ) as http:
            while not self.stopping.is_set():
                began = time.perf_counter()
                try:
                    response = http.post("/v1/reports", json=report_body(time.time()))
                    status = str(response.status_code)
                except httpx.HTTPError as exc:
                    status = type(exc).__name__
                self.statuses.append(status)
                self.latencies_s.append(time.perf_counter() - began)
                self.stopping.wait(self.interval_s)


@dataclass
class FloodCounts:
    opened: int = 0
    closed_by_server: int = 0
    failed: int = 0
    requests: int = 0
    answers: dict[str, int] = field(default_factory=dict)


class IdleFlood(Worker):
    """Holds up to ``per_source`` idle connections from each of ``sources`` (sending nothing),
    and opens a new one as soon as the server closes one; at most ``max_opens`` in all."""

    def __init__(
        self, port: int, sources: Sequence[str], per_source: int, max_opens: int = 20_000
    ) -> None:
        super().__init__("idle-flood")
        self.port = port
        self.sources = list(sources)
        self.per_source = per_source
        self.max_opens = max_opens
        self.counts = FloodCounts()

    def run(self) -> None:
        selector = selectors.DefaultSelector()
        held = dict.fromkeys(self.sources, 0)
        try:
            while not self.stopping.is_set():
                for source in self.sources:
                    while held[source] < self.per_source and self.counts.opened < self.max_opens:
                        try:
                            sock = connect_from(source, self.port, 1.0)
                        except OSError:
                            self.counts.failed += 1
                            break
                        self.counts.opened += 1
                        held[source] += 1
                        sock.setblocking(False)
                        selector.register(sock, selectors.EVENT_READ, source)
                for key, _ in selector.select(0.05):
                    if is_closed_by_peer(key.fileobj):  # type: ignore[arg-type]
                        selector.unregister(key.fileobj)
                        key.fileobj.close()  # type: ignore[union-attr]
                        held[key.data] -= 1
                        self.counts.closed_by_server += 1
        finally:
            for key in list(selector.get_map().values()):
                key.fileobj.close()  # type: ignore[union-attr]
            selector.close()


def odd_method(rng: random.Random, length: int) -> str:
    return "".join(rng.choices(string.ascii_uppercase, k=length))


class OddMethodFlood(Worker):
    """Requests with made-up methods of ``method_bytes`` letters on made-up paths (and on
    ``/healthz``), one per connection, as fast as the server answers; at most ``max_requests``."""

    def __init__(
        self,
        port: int,
        source: str,
        method_bytes: int = 16_384,
        max_requests: int = 1000,
        seed: int = 1,
    ) -> None:
        super().__init__("odd-method-flood")
        self.port = port
        self.source = source
        self.method_bytes = method_bytes
        self.max_requests = max_requests
        self.rng = random.Random(seed)
        self.counts = FloodCounts()

    def run(self) -> None:
        while not self.stopping.is_set() and self.counts.requests < self.max_requests:
            method = odd_method(self.rng, self.method_bytes)
            path = "/healthz" if self.counts.requests % 2 else f"/{odd_method(self.rng, 12)}/x"
            head = f"{method} {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
            self.counts.requests += 1
            try:
                with connect_from(self.source, self.port) as sock:
                    sock.sendall(head.encode())
                    answer = sock.recv(64)
            except OSError:
                self.counts.failed += 1
                continue
            match = re.match(rb"HTTP/1.1 (\d+)", answer)
            status = match.group(1).decode() if match else "?"
            self.counts.answers[status] = self.counts.answers.get(status, 0) + 1


class PipelineNonReader(Worker):
    """``connections`` connections from ``source``, each with a small receive buffer, that
    pipeline ``GET path`` until their sends would block (at most ``max_bytes`` each) and never
    read an answer. ``stalled_at`` is when the last of them stopped sending."""

    def __init__(
        self,
        port: int,
        source: str,
        connections: int,
        path: str = "/openapi.json",
        max_bytes: int = 4 * 1024 * 1024,
    ) -> None:
        super().__init__("pipeline-non-reader")
        self.port = port
        self.source = source
        self.connections = connections
        self.request = f"GET {path} HTTP/1.1\r\nHost: x\r\n\r\n".encode()
        self.max_bytes = max_bytes
        self.sockets: list[socket.socket] = []
        self.stalled_at: float | None = None
        self.sent = 0

    def run(self) -> None:
        try:
            for _ in range(self.connections):
                sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
                sock.bind((self.source, 0))
                sock.connect(("127.0.0.1", self.port))
                sock.setblocking(False)
                self.sockets.append(sock)
            for sock in self.sockets:
                sent = 0
                deadline = time.monotonic() + 5.0
                while sent < self.max_bytes and time.monotonic() < deadline:
                    try:
                        sent += sock.send(self.request)
                    except BlockingIOError:
                        if self.stopping.wait(0.05):
                            return
                        if not _writable(sock):
                            break
                    except OSError:
                        break
                self.sent += sent
            self.stalled_at = time.monotonic()
            self.stopping.wait(3600.0)  # never reads; until stopped
        finally:
            for sock in self.sockets:
                with contextlib.suppress(OSError):
                    sock.close()


def _writable(sock: socket.socket) -> bool:
    with selectors.DefaultSelector() as selector:
        selector.register(sock, selectors.EVENT_WRITE)
        return bool(selector.select(0.2))
