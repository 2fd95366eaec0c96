"""Latency of the placement service under load, and decision-to-wire latency (issue 6 targets).

Starts ``tupa serve`` as a real process against an in-process sitl_mock (PX4 flavour, loopback,
free ports) and:

1. **Load**: POST /v1/reports at 200, 500 and 1,000 requests/s for 20 s each, with 3 and 100
   users, from the open-loop generator of ``benchmarks/loadgen.py`` (requests are due on a
   fixed schedule whatever the answers do; bounded count and time). Per run: p50/p99/max
   latency (send → response, and from the time the request was due), errors (non-2xx or
   transport errors), achieved rate, and how late the generator itself ran (its p99 lateness:
   when it is large the client, not the service, was the limit). Every report of
   a run carries the same timestamp, so concurrent requests never count as out of order.
2. **Decision-to-wire**: the service in ``on-report`` mode with the ``load-weighted`` policy
   (every report gives a new target at once); a report moving the heavy user is
   sent every 0.5 s; for each, the time from sending the POST to the first
   SET_POSITION_TARGET_LOCAL_NED carrying the new target received by the mock (target: at most
   one streamer period + 10 ms = 110 ms at 10 Hz).

The generator and the service share the machine: on 2 cores the 1,000 requests/s runs measure
both. Writes benchmarks/results/service_latency.json.

    .venv/bin/python benchmarks/service_latency.py [--duration-s 20] [--quick]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import platform
import secrets
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from loadgen import load_phase

from closed_loop.processes import start_service
from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot
from sitl_mock.vehicle import Vehicle

RESULTS = Path(__file__).parent / "results" / "service_latency.json"
STREAMER_PERIOD_S = 0.1


class SetpointTap:
    """Records (monotonic time, NED position) of every local setpoint the mock receives."""

    def __init__(self) -> None:
        self.events: list[tuple[float, tuple[float, float, float]]] = []
        self.lock = threading.Lock()
        original = Vehicle.set_position_target_local
        tap = self

        def recording(
            vehicle: Vehicle, frame: int, type_mask: int, x: float, y: float, z: float,
            *args: Any, **kwargs: Any,
        ) -> Any:  # fmt: skip
            with tap.lock:
                tap.events.append((time.monotonic(), (x, y, z)))
            return original(vehicle, frame, type_mask, x, y, z, *args, **kwargs)

        Vehicle.set_position_target_local = recording  # type: ignore[method-assign]

    def first_after(
        self, t0: float, ned: tuple[float, float, float], tol_m: float = 0.01
    ) -> float | None:
        with self.lock:
            for t, position in self.events:
                if t >= t0 and max(abs(a - b) for a, b in zip(position, ned, strict=True)) < tol_m:
                    return t
        return None


def users_body(n_users: int, rng: np.random.Generator, timestamp: float) -> dict[str, Any]:
    loads = rng.exponential(1.0, n_users)
    loads = loads / loads.sum() * 40e6
    return {
        "timestamp": timestamp,
        "users": [
            {
                "id": f"ue-{i}",
                "x_m": float(rng.uniform(0, 500)),
                "y_m": float(rng.uniform(0, 500)),
                "offered_bps": float(loads[i]),
                "throughput_bps": float(loads[i] * rng.uniform(0.5, 1.0)),
                "delay_s": float(rng.uniform(0.001, 0.8)),
                "plr": float(rng.uniform(0, 0.3)),
            }
            for i in range(n_users)
        ],
    }


def load_run(port: int, token: str, rate: float, duration_s: float, body: bytes) -> dict[str, Any]:
    """One open-loop run (:func:`loadgen.load_phase`), without its raw records."""
    result = asyncio.run(load_phase("127.0.0.1", port, token, rate, duration_s, body))
    return {k: v for k, v in result.items() if not k.startswith("_")}


def decision_to_wire(base: str, token: str, tap: SetpointTap, n: int) -> dict[str, Any]:
    rng = np.random.default_rng(5)
    samples = []
    missing = 0
    headers = {"Authorization": f"Bearer {token}"}
    with httpx.Client(base_url=base, headers=headers, timeout=5.0) as client:
        for i in range(n):
            body = users_body(3, rng, 2e9 + i)
            body["users"][0]["offered_bps"] = 38e6  # a heavy user that moves: new target
            sent = time.monotonic()
            response = client.post("/v1/reports", json=body)
            response.raise_for_status()
            target = response.json()["target"]
            if target is None:
                missing += 1
                continue
            ned = (target["y_m"], target["x_m"], -target["z_m"])  # area -> NED, origin at home
            deadline = sent + 2.0
            seen = None
            while seen is None and time.monotonic() < deadline:
                seen = tap.first_after(sent, ned)
                if seen is None:
                    time.sleep(0.001)
            if seen is None:
                missing += 1
            else:
                samples.append(seen - sent)
            time.sleep(0.5)
    ms = np.array(samples) * 1e3 if samples else np.array([np.nan])
    return {
        "reports": n,
        "not_seen_within_2s": missing,
        "ms": {
            "p50": round(float(np.percentile(ms, 50)), 2),
            "p90": round(float(np.percentile(ms, 90)), 2),
            "max": round(float(ms.max()), 2),
        },
        "target_ms": STREAMER_PERIOD_S * 1e3 + 10,
    }


def start(mock_port: int, token: str, mode: str, policy: str | None = None) -> tuple[Any, str, int]:
    extra = ["--policy", policy] if policy else []
    proc, port = start_service(
        [
            *extra,
            "--mavlink",
            f"tcp:127.0.0.1:{mock_port}",
            "--port",
            "0",
            "--decision-mode",
            mode,
            "--log-level",
            "warning",
        ],
        env={"TUPA_API_TOKEN": token},
    )
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if httpx.get(f"{base}/readyz").status_code == 200:
            return proc, base, port
        time.sleep(0.2)
    proc.stop()
    raise RuntimeError("the service did not become ready")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration-s", type=float, default=20.0)
    parser.add_argument("--quick", action="store_true", help="3 s per run, 10 wire samples")
    args = parser.parse_args()
    duration = 3.0 if args.quick else args.duration_s
    tap = SetpointTap()
    mock = MockAutopilot("tcp:127.0.0.1:0", "px4", VehicleConfig(ready_delay_s=0.3)).start()
    token = secrets.token_urlsafe(24)
    rng = np.random.default_rng(1)
    out: dict[str, Any] = {
        "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
        "duration_s": duration,
    }
    try:
        proc, base, port = start(mock.port, token, "paced")
        try:
            policy = httpx.get(
                f"{base}/v1/policy", headers={"Authorization": f"Bearer {token}"}
            ).json()["name"]
            out["policy"] = policy
            runs = []
            for n_users in (3, 100):
                body = json.dumps(users_body(n_users, rng, 1e9)).encode()
                for rate in (200, 500, 1000):
                    result = load_run(port, token, rate, duration, body)
                    result["users"] = n_users
                    runs.append(result)
                    print(
                        f"{n_users:>3} users {rate:>5} req/s: p50 {result['latency_ms']['p50']} "
                        f"p99 {result['latency_ms']['p99']} ms, errors {result['errors']}, "
                        f"achieved {result['achieved_rps']}/s",
                        flush=True,
                    )
            out["load_paced"] = runs
        finally:
            proc.stop()
        # load-weighted: every report (its heavy user moved) gives a new target at once; a DDQN
        # would hold its next move until the vehicle (here on the ground) reached the last one.
        proc, base, port = start(mock.port, token, "on-report", policy="load-weighted")
        try:
            body = json.dumps(users_body(3, rng, 1e9)).encode()
            on_report = load_run(port, token, 200, duration, body)
            on_report["users"] = 3
            out["load_on_report"] = [on_report]
            print(f"on-report 3 users 200 req/s: p99 {on_report['latency_ms']['p99']} ms")
            out["decision_to_wire"] = decision_to_wire(base, token, tap, 10 if args.quick else 40)
            print(f"decision to wire: {out['decision_to_wire']['ms']} ms")
        finally:
            proc.stop()
    finally:
        mock.stop()
    p99_500 = next(r for r in out["load_paced"] if r["users"] == 3 and r["rate_rps"] == 500)
    out["targets"] = {
        "p99_ms_at_500rps_3_users": p99_500["latency_ms"]["p99"],
        "p99_target_ms": 10.0,
        "errors_at_500rps_3_users": sum(p99_500["errors"].values()),
        "decision_to_wire_p90_ms": out["decision_to_wire"]["ms"]["p90"],
        "decision_to_wire_target_ms": out["decision_to_wire"]["target_ms"],
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out["targets"], indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
