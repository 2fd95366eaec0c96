"""What the fault-injection tests share: real processes on loopback, and how to talk to them.

:class:`Harness` starts mocks (:mod:`tests.faults.mock_process`), ``tupa serve`` processes and
UDP proxies on free ports and stops every one of them at the end (the ``harness`` fixture in
``conftest.py``). :class:`Api` is a small authenticated HTTP client for one service.

Frames: the area's south-west corner is 250 m south and west of home, so the vehicle takes off
at the area's centre (250, 250) and area (x, y, z) is NED (y - 250, x - 250, -z) around home.
"""

from __future__ import annotations

import math
import re
import secrets
import signal
import time
from typing import Any

import httpx

from closed_loop.processes import TupaProcess, start_service
from tests.faults.mock_process import MockProcess, start_mock_process
from tests.faults.udp_proxy import UdpProxy
from tests.helpers import wait_for

ORIGIN_M = -250.0
PX4_FAST = [
    "--flavour",
    "px4",
    "--ready-delay-s",
    "1",
    "--climb-speed-mps",
    "8",
    "--speed-mps",
    "12",
    "--accel-mps2",
    "5",
]
"""A PX4-flavoured mock that is ready after 1 s and climbs and flies briskly (shorter tests)."""

USERS_EAST = [
    {"id": "ue-1", "x_m": 270.0, "y_m": 255.0, "offered_bps": 30e6, "throughput_bps": 20e6,
     "delay_s": 0.3, "plr": 0.1},
    {"id": "ue-2", "x_m": 290.0, "y_m": 245.0, "offered_bps": 5e6, "throughput_bps": 5e6,
     "delay_s": 0.01, "plr": 0.0},
]  # fmt: skip
USERS_NORTH = [
    {"id": "ue-1", "x_m": 245.0, "y_m": 275.0, "offered_bps": 30e6, "throughput_bps": 20e6,
     "delay_s": 0.3, "plr": 0.1},
    {"id": "ue-3", "x_m": 255.0, "y_m": 290.0, "offered_bps": 8e6, "throughput_bps": 8e6,
     "delay_s": 0.01, "plr": 0.0},
]  # fmt: skip


def ned_to_area(ned: list[float]) -> tuple[float, float, float]:
    """The mock's NED position (around home) in the area frame, independently of service.frames."""
    n, e, d = ned
    return (e - ORIGIN_M, n - ORIGIN_M, -d)


def target_xyz(decision: dict[str, Any]) -> tuple[float, float, float]:
    t = decision["target"]
    return (t["x_m"], t["y_m"], t["z_m"])


class Api:
    """An authenticated client of one ``tupa serve`` process."""

    def __init__(self, proc: TupaProcess, port: int, token: str) -> None:
        self.proc = proc
        self.base = f"http://127.0.0.1:{port}"
        self.client = httpx.Client(
            base_url=self.base, headers={"Authorization": f"Bearer {token}"}, timeout=10.0
        )
        self._timestamp = time.time()

    def next_timestamp(self) -> float:
        self._timestamp = max(self._timestamp + 0.001, time.time())
        return self._timestamp

    def report(self, users: list[dict[str, Any]], timestamp: float | None = None) -> httpx.Response:
        ts = self.next_timestamp() if timestamp is None else timestamp
        return self.client.post("/v1/reports", json={"timestamp": ts, "users": users})

    def place(self, users: list[dict[str, Any]], timeout_s: float = 20.0) -> dict[str, Any]:
        """POST a report of ``users`` and return the decision it leads to: the answer itself, or,
        when the report had to wait for the MAVLink link (a lossy link can lose it for a few
        seconds), the decision the service takes once the link is back."""
        posted_at = time.time()
        response = self.report(users)
        response.raise_for_status()

        def fresh(decision: dict[str, Any]) -> dict[str, Any] | None:
            decided_at = decision["decided_at"]
            new = decision["source"] == "policy" and decided_at is not None
            return decision if new and decided_at >= posted_at else None

        return fresh(response.json()) or wait_for(
            lambda: fresh(self.setpoint()), timeout_s, 0.1, "a decision on the report"
        )

    def vehicle(self) -> dict[str, Any]:
        return self.client.get("/v1/vehicle").json()

    def setpoint(self) -> dict[str, Any]:
        return self.client.get("/v1/setpoint").json()

    def policy(self) -> dict[str, Any]:
        return self.client.get("/v1/policy").json()

    def readyz(self) -> httpx.Response:
        return self.client.get("/readyz")

    def metric(self, name: str, labels: str = "") -> float:
        """One sample of ``/metrics``: ``name`` with ``labels`` as written (``{result="x"}``)."""
        text = self.client.get("/metrics").text
        pattern = rf"^{re.escape(name + labels)} (\S+)$"
        match = re.search(pattern, text, re.MULTILINE)
        if match is None:
            raise AssertionError(f"no {name}{labels} in /metrics")
        return float(match.group(1))

    def wait_ready(self, timeout_s: float = 30.0) -> float:
        """Wait until ``/readyz`` answers 200; returns how long that took."""
        started = time.monotonic()
        wait_for(lambda: self.readyz().status_code == 200, timeout_s, 0.1, "service ready")
        return time.monotonic() - started

    def kill(self) -> None:
        """SIGKILL the service: no shutdown, nothing flushed."""
        if self.proc.alive():
            self.proc.proc.send_signal(signal.SIGKILL)
            self.proc.proc.wait(5.0)

    def close(self) -> None:
        self.client.close()


class Harness:
    """Starts processes and proxies; :meth:`close` stops all of them (also on failure)."""

    def __init__(self) -> None:
        self.token = secrets.token_urlsafe(16)
        self._mocks: list[MockProcess] = []
        self._apis: list[Api] = []
        self._proxies: list[UdpProxy] = []

    def mock(self, *args: str) -> MockProcess:
        mock = start_mock_process(list(args))
        self._mocks.append(mock)
        return mock

    def proxy(self, server_port: int, loss: float, jitter_s: float, seed: int = 1) -> UdpProxy:
        proxy = UdpProxy(("127.0.0.1", server_port), loss, jitter_s, seed).start()
        self._proxies.append(proxy)
        return proxy

    def service(self, *args: str, env: dict[str, str] | None = None) -> Api:
        full_env = {
            "TUPA_API_TOKEN": self.token,
            "TUPA_AREA_ORIGIN_NORTH_M": str(ORIGIN_M),
            "TUPA_AREA_ORIGIN_EAST_M": str(ORIGIN_M),
            **(env or {}),
        }
        proc, port = start_service([*args, "--port", "0", "--log-level", "warning"], full_env)
        api = Api(proc, port, self.token)
        self._apis.append(api)
        return api

    def placing_service(
        self,
        mavlink: str,
        *args: str,
        arm_and_takeoff: bool = True,
        env: dict[str, str] | None = None,
    ) -> Api:
        """:meth:`service` on ``mavlink`` that places with ``load-weighted`` on every report
        (what the fault tests fly with), arming and taking off unless told not to."""
        takeoff = ("--arm-and-takeoff",) if arm_and_takeoff else ()
        return self.service(
            "--mavlink",
            mavlink,
            *takeoff,
            "--policy",
            "load-weighted",
            "--decision-mode",
            "on-report",
            *args,
            env=env,
        )

    def describe(self) -> str:
        """The last output lines of every process started and the proxies' counters (what a
        failed test prints, to tell what the service and the vehicle were doing)."""
        parts = [f"--- {api.proc.name} ({api.base}):\n{api.proc.tail(60)}" for api in self._apis]
        parts += [f"--- {mock.name} (port {mock.port}):\n{mock.tail(60)}" for mock in self._mocks]
        parts += [f"--- udp proxy (port {p.port}): {dict(p.counters)}" for p in self._proxies]
        return "\n".join(parts)

    def close(self) -> None:
        for api in self._apis:
            api.close()
            api.proc.stop()
        for proxy in self._proxies:
            proxy.stop()
        for mock in self._mocks:
            mock.stop()


def wait_airborne(mock: MockProcess, alt_m: float = 22.0, timeout_s: float = 45.0) -> None:
    wait_for(lambda: mock.state()["alt_m"] > alt_m, timeout_s, 0.2, f"airborne above {alt_m} m")


def wait_at(
    mock: MockProcess,
    target: tuple[float, float, float],
    tol_m: float = 1.5,
    timeout_s: float = 40.0,
) -> dict[str, Any]:
    """Wait until the mock's true position is within ``tol_m`` of ``target`` (area frame)."""
    return wait_for(
        lambda: (
            (s := mock.state())
            and math.dist(ned_to_area(s["position_ned_m"]), target) < tol_m
            and s
        ),
        timeout_s,
        0.1,
        f"the vehicle within {tol_m} m of {target}",
    )


def report_recovery(name: str, seconds: float, note: str = "") -> None:
    """One measured figure, printed for the log (run pytest with ``-s`` or ``-rP`` to see it)."""
    print(f"RECOVERY {name}: {seconds:.2f} s {note}".rstrip(), flush=True)
