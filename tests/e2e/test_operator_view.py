"""The operator view in a real browser (headless Chromium through Playwright) against a running
closed loop on loopback: ``tupa sitl-mock`` + ``tupa serve`` + a simulated network controller.

One scenario, step by step, each step a wait on a condition with a time limit: the page loads
and its first live frame arrives (the time is recorded); the UAV marker moves as the vehicle
flies; a user's marker grows when its load does; the service restarts and the page reconnects
by itself; the autopilot is killed and the link turns "lost". On failure a screenshot of the page
goes to the test's directory (``tmp_path``). The token reaches the page through an init script
that writes the tab's ``sessionStorage`` (as the page's own token form does): never a URL.

Playwright drives Debian's ``chromium`` (its own browser download is not reachable from these
machines): ``.ci/run`` installs it. Without it the test is skipped on a developer's machine, and
fails under CI (``CI`` set), where a missing browser is a broken install, not a reason to skip.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from closed_loop.controller import SimulatedNetwork, TruePosition
from closed_loop.processes import TupaProcess, start_service, start_sitl_mock
from service.frames import FrameConfig
from sim.scenarios import Scenario
from tests.tiers import needs

pytestmark = pytest.mark.slow

ORIGIN = {"TUPA_AREA_ORIGIN_NORTH_M": "-250", "TUPA_AREA_ORIGIN_EAST_M": "-250"}
FRAMES = FrameConfig(-250.0, -250.0)  # home (take-off) at the area's centre
SCENARIO = Scenario(
    "heavy-east",
    np.array([[450.0, 250.0], [60.0, 60.0], [60.0, 440.0]]),
    np.array([30e6, 2e6, 2e6]),
)
FIRST_FRAME_LIMIT_MS = 5000.0
"""A bound for a test on a busy 2-core machine; the target (1 s) is measured and reported."""


def chromium() -> str:
    """Debian's chromium, and Playwright to drive it: skipped without them, except under CI."""
    path = os.environ.get("TUPA_CHROMIUM") or shutil.which("chromium")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        path = None
    if path is None:
        reason = (
            "the browser test needs Debian's chromium and Playwright (pip install -e '.[dev]'; "
            "apt-get install -y chromium; make test installs both)"
        )
        if os.environ.get("CI"):
            pytest.fail(f"CI: {reason}")
        pytest.skip(reason)
    return path


def free_tcp_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Controller:
    """The simulated network controller in a thread: every second, the users' metrics at the
    vehicle's true position, POSTed as a report. Survives a service restart (a refused or failed
    POST is counted and the next one goes out on time)."""

    def __init__(self, base: str, token: str, vehicle: TruePosition) -> None:
        self.network = SimulatedNetwork(SCENARIO, seed=3)
        self.vehicle = vehicle
        self.client = httpx.Client(
            base_url=base, headers={"Authorization": f"Bearer {token}"}, timeout=5.0
        )
        self.failures = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="controller", daemon=True)

    def start(self) -> Controller:
        self._thread.start()
        return self

    def set_load(self, user: int, load_bps: float) -> None:
        loads = np.array(self.network.users.load_bps, dtype=float)
        loads[user] = load_bps
        self.network.users.load_bps = loads

    def _run(self) -> None:
        for _ in range(600):  # bounded: ten minutes at most
            if self._stop.wait(1.0):
                return
            position = self.vehicle.latest()
            if position is None:
                continue
            metrics = self.network.measure(np.asarray(position), 1.0)
            try:
                report = self.network.report(metrics, time.time())
                self.client.post("/v1/reports", json=report).raise_for_status()
            except httpx.HTTPError:
                self.failures += 1

    def stop(self) -> None:  # safe to call twice
        self._stop.set()
        self._thread.join(10.0)
        self.client.close()


@pytest.fixture
@needs("browser")
def browser_path() -> str:
    return chromium()


@pytest.fixture
@needs("process")
def loop(browser_path: str) -> Iterator[dict[str, Any]]:
    """The mock, the service (on a port chosen here, so a restart can take it again) and the
    controller; every process stopped at the end."""
    processes: list[TupaProcess] = []
    token = secrets.token_urlsafe(18)
    port = free_tcp_port()
    state: dict[str, Any] = {"token": token, "port": port, "processes": processes}
    vehicle = controller = None
    try:
        mock, mock_port = start_sitl_mock(
            ["--listen", "tcp:127.0.0.1:0", "--flavour", "px4", "--ready-delay-s", "1",
             "--climb-speed-mps", "8"]
        )  # fmt: skip
        processes.append(mock)
        serve_args = ["--mavlink", f"tcp:127.0.0.1:{mock_port}", "--port", str(port)]
        service, _ = start_service(
            [*serve_args, "--arm-and-takeoff"], {"TUPA_API_TOKEN": token, **ORIGIN}
        )
        processes.append(service)
        vehicle = TruePosition(f"tcp:127.0.0.1:{mock_port}", FRAMES).start()
        controller = Controller(f"http://127.0.0.1:{port}", token, vehicle).start()
        state.update(
            mock=mock, service=service, serve_args=serve_args, controller=controller,
            vehicle=vehicle, base=f"http://127.0.0.1:{port}",
        )  # fmt: skip
        yield state
    finally:
        if controller is not None:
            controller.stop()
        if vehicle is not None:
            vehicle.close()
        for process in reversed(processes):
            process.stop()


def test_the_page_follows_the_closed_loop(
    loop: dict[str, Any], browser_path: str, tmp_path: Path
) -> None:
    from playwright.sync_api import sync_playwright

    token = loop["token"]
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=browser_path)
        context = browser.new_context(viewport={"width": 1400, "height": 900})
        # What the page's token form does, before the page's own script runs.
        context.add_init_script(f"sessionStorage.setItem('tupa.token', {json.dumps(token)})")
        page = context.new_page()
        try:
            _walk_through(page, loop, tmp_path)
        except BaseException:
            page.screenshot(path=str(tmp_path / "operator-view-failure.png"))
            (tmp_path / "service-output.txt").write_text(loop["service"].tail(200))
            raise
        finally:
            browser.close()
    for process in loop["processes"]:  # the token is in no log line of any process
        assert token not in process.tail(2000)


def _walk_through(page: Any, loop: dict[str, Any], tmp_path: Path) -> None:
    base = loop["base"]
    vehicle = 'g.vehicle[data-vehicle-id="uav1"]'

    # 1. The page loads without a token in its address; the first live frame arrives.
    page.goto(f"{base}/ui")
    page.wait_for_function("() => window.tupaView && window.tupaView.frames > 0", timeout=10_000)
    first_frame_ms = page.evaluate("window.tupaView.firstFrameMs")
    (tmp_path / "first_frame_ms.json").write_text(json.dumps({"ms": first_frame_ms}))
    print(f"page load to first live frame: {first_frame_ms:.0f} ms")
    assert first_frame_ms < FIRST_FRAME_LIMIT_MS
    assert loop["token"] not in page.url
    assert page.locator("#map rect.fence").count() == 1  # the geofence is drawn
    assert page.locator("#layer-grid line").count() == 2 * (500 // 25 + 1)  # zones of 25 m

    # 2. The UAV marker moves as the vehicle flies (take-off, then towards the heavy user).
    page.wait_for_selector(f"{vehicle}[data-x]", timeout=60_000)
    start = page.eval_on_selector(vehicle, "g => [Number(g.dataset.x), Number(g.dataset.y)]")
    page.wait_for_function(
        """([sel, x0, y0]) => {
            const g = document.querySelector(sel);
            return g && Math.hypot(g.dataset.x - x0, g.dataset.y - y0) > 20;
        }""",
        arg=[vehicle, *start],
        timeout=90_000,
        polling=200,
    )
    assert page.locator('circle[data-user-id="ue-1"]').count() == 1
    assert page.locator("#layer-targets g.target").is_visible()

    # 3. A user's marker grows when its load does (2 -> 24 Mbit/s).
    user = 'circle[data-user-id="ue-2"]'
    r_before = float(page.get_attribute(user, "r") or 0)
    loop["controller"].set_load(1, 24e6)
    page.wait_for_function(
        "([sel, r0]) => Number(document.querySelector(sel).getAttribute('r')) > r0 + 5",
        arg=[user, r_before],
        timeout=15_000,
        polling=200,
    )

    # 4. The service restarts: it stops at once (its streams end first), the page reconnects.
    frames_before = page.evaluate("window.tupaView.frames")
    service = loop["service"]
    started = time.monotonic()
    # uvicorn shuts down gracefully, then raises the SIGTERM again (-15); -9 would mean it had
    # to be killed, waiting for a stream that never ends.
    assert service.stop(grace_s=10.0) in (0, -15)
    assert time.monotonic() - started < 8.0
    assert "Waiting for connections to close" not in service.tail(50)
    page.wait_for_function("() => window.tupaView.connection !== 'live'", timeout=10_000)
    restarted, _ = start_service(loop["serve_args"], {"TUPA_API_TOKEN": loop["token"], **ORIGIN})
    loop["processes"].append(restarted)
    loop["service"] = restarted
    page.wait_for_function(
        "([n]) => window.tupaView.connection === 'live' && window.tupaView.frames > n",
        arg=[frames_before],
        timeout=30_000,
    )
    assert page.evaluate("window.tupaView.reconnects") >= 1
    link = page.locator('[data-testid="link-uav1"]')
    page.wait_for_function(
        "() => document.querySelector('[data-testid=\"link-uav1\"]')?.dataset.state === 'up'",
        timeout=30_000,
    )

    # 5. The autopilot dies: the link turns "lost". (The controller's own MAVLink client goes
    # first: its reconnects would fail loudly in its thread.)
    loop["controller"].stop()
    loop["vehicle"].close()
    loop["mock"].proc.kill()
    page.wait_for_function(
        "() => document.querySelector('[data-testid=\"link-uav1\"]')?.dataset.state === 'lost'",
        timeout=20_000,
        polling=200,
    )
    assert "lost" in link.inner_text()
