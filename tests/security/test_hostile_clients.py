"""Hostile HTTP clients against a real ``tupa serve`` (issue 21, items 4 and 5).

``tupa serve`` processes on free loopback ports (no autopilot: the HTTP side works without one),
with a 1 s request-read timeout; one without a rate limit, one with a small one for the test of
the limit, so that no test's outcome depends on another having spent the budget. Both are
stopped at the end of the module.
The clients speak raw sockets where a well-behaved library would not do what an attacker does:
a 100 MB header sent in chunks, a request that stops half-way, a body shorter than announced.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
import pytest

from closed_loop.processes import TupaProcess, start_service
from tests.helpers import wait_for
from tests.tiers import needs

TOKEN = "hostile-clients-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
READ_TIMEOUT_S = 1.0
MiB = 1024 * 1024


@dataclass
class Served:
    proc: TupaProcess
    port: int

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"


def _serve(*options: str) -> Iterator[Served]:
    proc, port = start_service(
        [
            "--port",
            "0",
            "--policy",
            "min-distance",
            "--mavlink",
            "tcp:127.0.0.1:1",  # nothing listens there: no autopilot
            *options,
        ],
        env={
            "TUPA_API_TOKEN": TOKEN,
            "TUPA_HTTP_REQUEST_TIMEOUT_S": str(READ_TIMEOUT_S),
            "FORWARDED_ALLOW_IPS": "127.0.0.1",  # uvicorn's own default, made explicit
        },
    )
    try:
        yield Served(proc, port)
    finally:
        proc.stop()


@pytest.fixture(scope="module")
@needs("process", group="timing")
def served() -> Iterator[Served]:
    """No rate limit: what these tests see must not depend on what ran before them."""
    yield from _serve("--rate-limit-rps", "0")


@pytest.fixture(scope="module")
@needs("process", group="timing")
def served_rate_limited() -> Iterator[Served]:
    """A small rate limit (1 request/s, burst 5), for the test of the limit itself."""
    yield from _serve("--rate-limit-rps", "1", "--rate-limit-burst", "5")


def _read_until_closed(sock: socket.socket, timeout_s: float) -> bytes:
    """Everything the server sends until it closes the connection (ECONNRESET counts as
    closed); ``TimeoutError`` if it is still open after ``timeout_s``."""
    sock.settimeout(timeout_s)
    received = b""
    try:
        while chunk := sock.recv(65536):
            received += chunk
    except ConnectionResetError:
        pass
    return received


class HealthProbe:
    """``GET /healthz`` every 50 ms from a thread, recording each answer's latency."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.latencies_s: list[float] = []
        self.failures: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="health-probe", daemon=True)

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=5.0) as http:
            while not self._stop.is_set():
                began = time.perf_counter()
                try:
                    status = http.get("/healthz").status_code
                    if status != 200:
                        self.failures.append(str(status))
                except httpx.HTTPError as exc:
                    self.failures.append(type(exc).__name__)
                self.latencies_s.append(time.perf_counter() - began)
                self._stop.wait(0.05)

    def __enter__(self) -> HealthProbe:
        self._thread.start()
        wait_for(lambda: len(self.latencies_s) >= 3, 10.0, message="the first probes")
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(10.0)


# --------------------------------------------------------------------------- 4: headers


def test_a_100_mb_header_is_refused_fast_while_healthz_answers(served: Served) -> None:
    total = 100 * MiB
    chunk = b"a" * MiB
    sent = 0
    closed_early = False
    with (
        HealthProbe(served.url) as probe,
        socket.create_connection(("127.0.0.1", served.port), timeout=5.0) as sock,
    ):
        began = time.monotonic()
        try:
            sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: ")
            while sent < total and time.monotonic() - began < 20.0:
                sock.sendall(chunk)
                sent += len(chunk)
            sock.sendall(b"\r\n\r\n")
        except (BrokenPipeError, ConnectionResetError):
            closed_early = True  # the server closed the connection while we were sending
        answer = _read_until_closed(sock, 5.0)
        elapsed = time.monotonic() - began
        count = len(probe.latencies_s)
        wait_for(lambda: len(probe.latencies_s) >= count + 2, 5.0, message="probes after it")
    assert closed_early or answer.startswith((b"HTTP/1.1 400", b"HTTP/1.1 431")), answer[:200]
    assert sent < total, "the whole 100 MB header was accepted"
    assert elapsed < 5.0, f"refusing it took {elapsed:.1f} s"
    assert not probe.failures, probe.failures
    assert max(probe.latencies_s) < 1.0, max(probe.latencies_s)


def test_too_many_headers_get_431(served: Served) -> None:
    headers = {f"x-h{i}": "1" for i in range(500)}
    with httpx.Client(base_url=served.url, timeout=5.0) as http:
        response = http.get("/healthz", headers=headers)
        assert response.status_code == 431, response.text
        assert "headers" in response.json()["detail"]
        assert http.get("/healthz", headers={"x-one": "1"}).status_code == 200


@pytest.mark.parametrize(
    "sent",
    [
        b"",
        b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n",  # the head never ends
        b"POST /v1/reports HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer "
        + TOKEN.encode()
        + b'\r\nContent-Type: application/json\r\nContent-Length: 1000\r\n\r\n{"ti',  # lies
    ],
    ids=["silent", "partial-head", "short-body"],
)
def test_a_stalled_connection_is_closed_within_the_read_timeout(
    served: Served, sent: bytes
) -> None:
    with socket.create_connection(("127.0.0.1", served.port), timeout=5.0) as sock:
        began = time.monotonic()
        sock.sendall(sent)
        answer = _read_until_closed(sock, READ_TIMEOUT_S + 4.0)  # TimeoutError: held open
        elapsed = time.monotonic() - began
    assert elapsed < READ_TIMEOUT_S + 2.0, elapsed
    assert answer == b"" or answer.startswith(b"HTTP/1.1 408"), answer[:200]
    with httpx.Client(base_url=served.url, timeout=5.0) as http:
        assert http.get("/healthz").status_code == 200


# --------------------------------------------------------------------------- 5: proxies


def test_x_forwarded_for_from_loopback_does_not_dodge_the_rate_limit(
    served_rate_limited: Served,
) -> None:
    """uvicorn trusts ``X-Forwarded-For`` from 127.0.0.1 unless told not to: a client that
    sends a new address each time would get a new bucket each time."""
    with httpx.Client(base_url=served_rate_limited.url, timeout=5.0) as http:
        codes = [
            http.get(
                "/v1/setpoint", headers={**AUTH, "X-Forwarded-For": f"198.51.100.{i}"}
            ).status_code
            for i in range(1, 21)
        ]
    assert 429 in codes, codes
    assert set(codes) <= {200, 429}, codes
