"""The operator view's HTTP side: ``/`` and ``/ui`` (the page), ``GET /v1/live`` and the
``GET /v1/live/events`` stream, served by a real uvicorn server (``api.server``, the one ``tupa
serve`` runs: a stream needs real sockets and flow control) on a free loopback port, in a
thread, over an in-memory vehicle (:class:`tests.fakes.FakeLink`) and a fast decision period.

The stream: 401 without the token; well-formed Server-Sent Events whose frames match the
documented model; at most ``live_max_streams`` (503 and ``Retry-After`` beyond); a client that
vanishes or stops reading never blocks the decision loop, its queue stays bounded (oldest frames
dropped), and a stalled one is cut off after ``live_stall_s``; shutdown ends open streams.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest

from api.app import create_app
from api.live import end_streams
from api.live_schemas import LiveFrameOut
from api.server import Server, server_config
from service.placement import PlacementService
from service.policy_runtime import load_policy
from service.settings import ServiceSettings
from sim.utility import network_utility
from tests.fakes import FakeLink
from tests.helpers import wait_for

TOKEN = "live-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
STEP_S = 0.05


@dataclass
class Running:
    base: str
    port: int
    app: Any
    server: Server
    thread: threading.Thread

    @property
    def service(self) -> PlacementService:
        return self.app.state.service

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10.0)


def serve(**overrides: Any) -> Running:
    settings = ServiceSettings(
        api_token=TOKEN,
        policy="load-weighted",
        step_s=STEP_S,
        report_max_age_s=600.0,
        live_max_streams=3,
        live_stall_s=2.0,
        **overrides,
    )

    def factory(s: ServiceSettings) -> PlacementService:
        link = FakeLink(position_m=(250.0, 250.0, 50.0), realtime=True, speed_mps=30.0)
        return PlacementService(s, link, load_policy(s.policy, s.policy_world()))

    app = create_app(settings, service_factory=factory)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    config = server_config(app, settings, log_level="warning", lifespan="on")
    server = Server(config, before_shutdown=lambda: end_streams(app))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    wait_for(lambda: server.started, 15.0, message="the server to start")
    return Running(f"http://127.0.0.1:{port}", port, app, server, thread)


@pytest.fixture
def running() -> Iterator[Running]:
    server = serve()
    try:
        yield server
    finally:
        server.stop()


def users_body(n: int, timestamp: float, heavy_bps: float = 30e6) -> dict[str, Any]:
    rng = np.random.default_rng(n)
    users = []
    for i in range(n):
        offered = heavy_bps if i == 0 else 2e6
        users.append(
            {
                "id": f"ue-{i + 1}",
                "x_m": float(rng.uniform(0, 500)),
                "y_m": float(rng.uniform(0, 500)),
                "offered_bps": offered,
                "throughput_bps": offered * 0.8,
                "delay_s": 0.12,
                "plr": 0.02,
            }
        )
    return {"timestamp": timestamp, "users": users}


def read_events(lines: Iterator[str], count: int) -> list[dict[str, str]]:
    """The next ``count`` events of an SSE response's lines, each as its fields (comments
    skipped)."""
    events: list[dict[str, str]] = []
    fields: dict[str, str] = {}
    for line in lines:
        if line == "":
            if fields:
                events.append(fields)
                fields = {}
                if len(events) == count:
                    return events
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        assert name in {"id", "event", "data", "retry"}, line
        assert name not in fields, f"{name} twice in one event"
        fields[name] = value.removeprefix(" ")
    raise AssertionError(f"the stream ended after {len(events)} events")


# --------------------------------------------------------------------------- the page


def test_the_page_loads_without_a_token_and_locks_itself_down(running: Running) -> None:
    for path in ("/", "/ui"):
        page = httpx.get(running.base + path)
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert '<script src="/ui/app.js"' in page.text and "<svg" in page.text
        csp = page.headers["content-security-policy"]
        assert "script-src 'self'" in csp and "connect-src 'self'" in csp
        assert "frame-ancestors 'none'" in csp
    script = httpx.get(running.base + "/ui/app.js")
    assert script.status_code == 200 and "javascript" in script.headers["content-type"]
    assert "Authorization" in script.text and "sessionStorage" in script.text
    assert "EventSource" not in script.text.split('"use strict"')[1]  # fetch(): a header
    assert httpx.get(running.base + "/ui/style.css").headers["content-type"].startswith("text/css")
    for missing in ("/ui/index.html", "/ui/../app.py", "/ui/secrets"):
        assert httpx.get(running.base + missing).status_code == 404


# --------------------------------------------------------------------------- auth


@pytest.mark.parametrize("path", ["/v1/live", "/v1/live/events"])
@pytest.mark.parametrize("headers", [{}, {"Authorization": f"Bearer {TOKEN}x"}, {"X": "y"}])
def test_the_data_needs_the_token(running: Running, path: str, headers: dict[str, str]) -> None:
    response = httpx.get(running.base + path, headers=headers, timeout=5.0)
    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"
    assert len(running.service.live.hub) == 0


# --------------------------------------------------------------------------- frames


def test_events_are_well_formed_and_follow_the_service(running: Running) -> None:
    with httpx.Client(base_url=running.base, headers=AUTH, timeout=5.0) as client:
        client.post("/v1/reports", json=users_body(3, time.time())).raise_for_status()
        started = time.monotonic()
        with client.stream("GET", "/v1/live/events") as response:
            assert response.status_code == 200
            assert response.headers["content-type"].startswith("text/event-stream")
            assert response.headers["cache-control"] == "no-store"
            events = read_events(response.iter_lines(), 6)
            elapsed = time.monotonic() - started
    assert events[0]["retry"] == "2000"
    assert elapsed < 5 * 6 * STEP_S + 2.0  # at the decision rate, not slower
    seqs = [int(event["id"]) for event in events]
    assert seqs == sorted(set(seqs))
    for event in events:
        assert event["event"] == "frame"
        frame = LiveFrameOut.model_validate_json(event["data"])
        assert frame.seq == int(event["id"])
    last = LiveFrameOut.model_validate_json(events[-1]["data"])
    assert [u.id for u in last.users] == ["ue-1", "ue-2", "ue-3"]
    assert last.users[0].served == pytest.approx(0.8)
    (vehicle,) = last.vehicles
    assert vehicle.id == "uav1" and vehicle.link == "up" and vehicle.position_m is not None
    assert vehicle.decision is not None and vehicle.target_m is not None
    assert last.geofence.z_m == [25.0, 100.0] and last.area.zone_m == 25.0
    utility = last.utility
    assert utility is not None
    body = users_body(3, 0.0)["users"]
    expected = network_utility(
        *(np.array([u[k] for u in body]) for k in ("throughput_bps", "delay_s", "plr")),
        np.array([u["offered_bps"] for u in body]),
    )
    assert utility.value == pytest.approx(float(expected), abs=1e-4)
    assert utility.throughput + utility.delay + utility.loss == pytest.approx(
        utility.value, abs=3e-4
    )
    assert last.utility_history and last.utility_history[-1][1] == utility.value


def test_get_live_is_one_frame(running: Running) -> None:
    response = httpx.get(running.base + "/v1/live", headers=AUTH)
    assert response.status_code == 200 and response.headers["cache-control"] == "no-store"
    frame = LiveFrameOut.model_validate(response.json())
    assert frame.format == "tupa-live/1" and frame.report is None and frame.users == []


def test_the_track_grows_as_the_vehicle_flies(running: Running) -> None:
    with httpx.Client(base_url=running.base, headers=AUTH, timeout=5.0) as client:
        client.post("/v1/reports", json=users_body(3, time.time())).raise_for_status()

        def track_length() -> int:
            frame = LiveFrameOut.model_validate(client.get("/v1/live").json())
            return len(frame.vehicles[0].track_m)

        wait_for(lambda: track_length() >= 5, 10.0, message="a track of 5 points")


# --------------------------------------------------------------------------- limits


def test_streams_over_the_limit_get_503_and_a_place_frees_when_one_closes(
    running: Running,
) -> None:
    limit = running.service.settings.live_max_streams
    with httpx.Client(base_url=running.base, headers=AUTH, timeout=5.0) as client:
        streams = [client.stream("GET", "/v1/live/events") for _ in range(limit)]
        opened = [s.__enter__() for s in streams]
        try:
            assert all(r.status_code == 200 for r in opened)
            over = client.get("/v1/live/events")
            assert over.status_code == 503 and over.headers["retry-after"] == "5"
            assert "streams open" in over.json()["detail"]
            metrics = client.get("/metrics").text
            assert f"tupa_live_streams {float(limit)}" in metrics
        finally:
            streams[0].__exit__(None, None, None)
        wait_for(lambda: len(running.service.live.hub) == limit - 1, 5.0, message="a place")
        with client.stream("GET", "/v1/live/events") as again:
            assert again.status_code == 200
        for stream in streams[1:]:
            stream.__exit__(None, None, None)
    wait_for(lambda: len(running.service.live.hub) == 0, 5.0, message="no streams")


def test_a_vanished_client_leaves_nothing_behind(running: Running) -> None:
    sock = socket.create_connection(("127.0.0.1", running.port))
    sock.sendall(
        f"GET /v1/live/events HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n\r\n".encode()
    )
    assert sock.recv(4096).startswith(b"HTTP/1.1 200")
    assert len(running.service.live.hub) == 1
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
    sock.close()  # a reset, as a killed browser tab would leave
    wait_for(lambda: len(running.service.live.hub) == 0, 5.0, message="the stream to end")


def test_a_client_that_stops_reading_never_blocks_the_decision_loop(running: Running) -> None:
    """A client reads the response head, then nothing: its socket buffers fill with frames (of
    1,000 users each), the server's writes to it wait, its queue fills and drops its oldest
    frames, the decisions go on at their period all the while, and after ``live_stall_s`` the
    stream is cut off."""
    service = running.service
    with httpx.Client(base_url=running.base, headers=AUTH, timeout=5.0) as client:
        client.post("/v1/reports", json=users_body(1000, time.time())).raise_for_status()
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # fills after a frame or two
    sock.connect(("127.0.0.1", running.port))
    try:
        sock.sendall(
            f"GET /v1/live/events HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {TOKEN}\r\n\r\n"
            .encode()
        )  # fmt: skip
        assert sock.recv(1024).startswith(b"HTTP/1.1 200")
        (subscription,) = service.live.hub._subscribers
        decisions_at_stall = wait_for(
            lambda: subscription.dropped > 0 and service.snapshot_counters()["decisions"],
            15.0,
            message="the stalled client's queue to overflow",
        )
        assert subscription.pending() <= service.live.hub.max_frames
        started = time.monotonic()
        wait_for(lambda: len(service.live.hub) == 0, 10.0, message="the stalled stream to close")
        stalled_s = time.monotonic() - started
        decided = service.snapshot_counters()["decisions"] - decisions_at_stall
        assert decided >= 0.5 * stalled_s / STEP_S, (decided, stalled_s)
        assert subscription.pending() == 0  # its frames are released
        assert subscription.dropped > 0
        # ... and the server closed the connection: what was in flight, then the end.
        sock.settimeout(5.0)
        deadline = time.monotonic() + 10.0
        while sock.recv(65536):
            assert time.monotonic() < deadline, "the connection stays open"
    finally:
        sock.close()


def test_shutdown_ends_open_streams_at_once() -> None:
    server = serve()
    try:
        with (
            httpx.Client(base_url=server.base, headers=AUTH, timeout=5.0) as client,
            client.stream("GET", "/v1/live/events") as response,
        ):
            lines = response.iter_lines()
            read_events(lines, 1)
            started = time.monotonic()
            server.server.should_exit = True
            for _ in lines:  # ends when the server ends the stream
                pass
        server.thread.join(10.0)
        assert not server.thread.is_alive()
        assert time.monotonic() - started < 5.0
    finally:
        server.stop()


def test_frames_carry_no_nan(running: Running) -> None:
    frame = running.service.live_frame()
    json.loads(frame.data, parse_constant=lambda name: pytest.fail(f"{name} in a frame"))
