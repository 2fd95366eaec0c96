"""Report latency with large reports: 1,000 users at 2 reports/s, ``on-report`` and ``paced``.

Starts an in-process sitl_mock (PX4 flavour, loopback, a free port) and ``tupa serve`` as a real
process (its default policy, the tracking oracle, unless ``--policy``; a free port), then POSTs a
report of ``--users`` users every ``1 / --rate`` seconds for ``--duration-s`` seconds, open loop
(report i is due at start + i / rate, each on a worker thread of its own, whatever the answers
do; every request has a ``--timeout-s`` limit). The users walk 1.5 m (standard deviation, per
axis) between reports, so that no decision is a repeat of the last. Each report is stamped with
this machine's clock when sent.

Per decision mode: the latency of every report (send -> answer), its ``report_outcome``, the
status codes, the fraction answered within two decision periods (the service's bound in
``on-report`` mode), and the service's own decision timing from ``GET /v1/policy`` (decisions
timed, last and longest duration, overruns: decisions longer than the period) with the mean
interval between decisions over the run.

``--src DIR`` runs the service from another source tree instead (e.g. the code before a change:
``git archive HEAD | tar -x -C /tmp/before``), to measure it the same way. Each run is recorded
under ``--label`` (default ``after``, or ``before`` with ``--src``) in
benchmarks/results/report_latency_load.json, beside the other labels already there.

    .venv/bin/python benchmarks/report_latency_load.py [--duration-s 60] [--modes on-report,paced]
    .venv/bin/python benchmarks/report_latency_load.py --src /tmp/before
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import secrets
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import numpy as np

# The repository first: benchmarks/closed_loop.py would hide the closed_loop package.
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from closed_loop.processes import TupaProcess
from sitl_mock.config import VehicleConfig
from sitl_mock.server import MockAutopilot

RESULTS = Path(__file__).parent / "results" / "report_latency_load.json"
WALK_M = 1.5


def start_service(
    mock_port: int, token: str, mode: str, policy: str | None, src: Path | None
) -> tuple[TupaProcess, str]:
    """``tupa serve`` (from ``src`` when given) in ``mode``; returns it once ready."""
    args = [
        "serve",
        "--mavlink",
        f"tcp:127.0.0.1:{mock_port}",
        "--port",
        "0",
        "--decision-mode",
        mode,
        "--log-level",
        "warning",
        *(["--policy", policy] if policy else []),
    ]
    env = {"TUPA_API_TOKEN": token}
    if src is not None:
        env["PYTHONPATH"] = str(src)
    proc = TupaProcess(args, "tupa-serve", env, cwd=src)
    try:
        match = proc.wait_for_line(r"tupa serve listening on http://\S+:(\d+)\s*$", 90.0)
        base = f"http://127.0.0.1:{int(match.group(1))}"
        deadline = time.monotonic() + 60.0
        while httpx.get(f"{base}/readyz").status_code != 200:
            if time.monotonic() > deadline:
                raise RuntimeError("the service did not become ready")
            time.sleep(0.2)
    except BaseException:
        proc.stop()
        raise
    return proc, base


class Users:
    """``n`` users with exponential loads summing to 40 Mbit/s, walking between reports."""

    def __init__(self, n: int, seed: int = 1) -> None:
        self.rng = np.random.default_rng(seed)
        self.xy = self.rng.uniform(0.0, 500.0, (n, 2))
        loads = self.rng.exponential(1.0, n)
        self.loads = loads / loads.sum() * 40e6
        self.served = self.rng.uniform(0.5, 1.0, n)
        self.delay = self.rng.uniform(0.001, 0.8, n)
        self.plr = self.rng.uniform(0.0, 0.3, n)

    def body(self) -> bytes:
        self.xy = np.clip(self.xy + self.rng.normal(0.0, WALK_M, self.xy.shape), 0.0, 500.0)
        users = [
            {
                "id": f"ue-{i}",
                "x_m": float(x),
                "y_m": float(y),
                "offered_bps": float(load),
                "throughput_bps": float(load * served),
                "delay_s": float(delay),
                "plr": float(plr),
            }
            for i, (x, y, load, served, delay, plr) in enumerate(
                zip(
                    self.xy[:, 0],
                    self.xy[:, 1],
                    self.loads,
                    self.served,
                    self.delay,
                    self.plr,
                    strict=True,
                )
            )
        ]
        return json.dumps({"timestamp": time.time(), "users": users}).encode()


def run_load(
    base: str, token: str, n_users: int, rate: float, duration_s: float, timeout_s: float
) -> dict[str, Any]:
    """Open loop: report i due at start + i / rate, each sent from a worker of its own."""
    n = int(rate * duration_s)
    users = Users(n_users)
    records: list[dict[str, Any]] = []
    lock = threading.Lock()
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    limits = httpx.Limits(max_connections=64, max_keepalive_connections=64)
    with (
        httpx.Client(base_url=base, headers=headers, timeout=timeout_s, limits=limits) as client,
        ThreadPoolExecutor(max_workers=min(n, 64) or 1) as pool,
    ):

        def send(i: int, body: bytes, due: float) -> None:
            sent = time.perf_counter()
            record: dict[str, Any] = {"i": i, "late_s": sent - due}
            try:
                response = client.post("/v1/reports", content=body)
                record["status"] = response.status_code
                if response.status_code == 200:
                    record["outcome"] = response.json().get("report_outcome", "(none)")
            except httpx.TimeoutException:
                record["status"] = "timeout"
            except httpx.HTTPError as exc:
                record["status"] = type(exc).__name__
            record["latency_s"] = time.perf_counter() - sent
            with lock:
                records.append(record)

        start = time.perf_counter()
        for i in range(n):
            due = start + i / rate
            time.sleep(max(0.0, due - time.perf_counter()))
            pool.submit(send, i, users.body(), due)
        sent_for_s = time.perf_counter() - start
    wall_s = time.perf_counter() - start
    return {"records": records, "sent_for_s": sent_for_s, "wall_s": wall_s}


def summarise(
    run: dict[str, Any], timing_before: dict[str, Any], timing: dict[str, Any], timeout_s: float
) -> dict[str, Any]:
    records = sorted(run["records"], key=lambda r: r["i"])
    latency = np.array([r["latency_s"] for r in records])
    statuses: dict[str, int] = {}
    outcomes: dict[str, int] = {}
    for r in records:
        statuses[str(r["status"])] = statuses.get(str(r["status"]), 0) + 1
        if "outcome" in r:
            outcomes[r["outcome"]] = outcomes.get(r["outcome"], 0) + 1
    period_s = timing["period_s"] if timing else 1.0
    bound_s = 2 * period_s
    decisions = (timing or {}).get("timed", 0) - (timing_before or {}).get("timed", 0)
    third = max(1, len(latency) // 3)
    return {
        "reports": len(records),
        "status": statuses,
        "report_outcome": outcomes,
        "latency_s": {
            "p50": round(float(np.percentile(latency, 50)), 3),
            "p90": round(float(np.percentile(latency, 90)), 3),
            "p99": round(float(np.percentile(latency, 99)), 3),
            "max": round(float(latency.max()), 3),
            "p50_first_third": round(float(np.median(latency[:third])), 3),
            "p50_last_third": round(float(np.median(latency[-third:])), 3),
        },
        "request_timeout_s": timeout_s,
        "bound_s": bound_s,
        "within_bound": round(float(np.mean(latency <= bound_s)), 4),
        "generator_late_s_max": round(max(r["late_s"] for r in records), 3),
        "sent_for_s": round(run["sent_for_s"], 1),
        "decisions": decisions,
        "mean_decision_interval_s": round(run["sent_for_s"] / decisions, 2) if decisions else None,
        "decision_timing": timing,
        "reports_in_order": [  # [i, status, outcome, latency_s]
            [r["i"], r["status"], r.get("outcome"), round(r["latency_s"], 3)] for r in records
        ],
    }


def measure(
    mock: MockAutopilot, token: str, mode: str, args: argparse.Namespace, src: Path | None
) -> dict[str, Any]:
    proc, base = start_service(mock.port, token, mode, args.policy, src)
    auth = {"Authorization": f"Bearer {token}"}
    try:
        policy = httpx.get(f"{base}/v1/policy", headers=auth).json()
        run = run_load(base, token, args.users, args.rate, args.duration_s, args.timeout_s)
        after = httpx.get(f"{base}/v1/policy", headers=auth, timeout=30).json()
        ready = httpx.get(f"{base}/readyz", timeout=30).json()
        metrics = httpx.get(f"{base}/metrics", timeout=30).text
    finally:
        proc.stop()
    result = summarise(run, policy.get("decisions"), after.get("decisions"), args.timeout_s)
    result["policy"] = policy["name"]
    result["mode"] = mode
    result["readyz_at_end"] = ready
    result["metrics_at_end"] = [
        line
        for line in metrics.splitlines()
        if line.startswith(("tupa_decisions_total", "tupa_reports_total", "tupa_link_reconnects"))
    ]
    lat = result["latency_s"]
    print(
        f"{args.label} {mode}: {result['reports']} reports, latency p50 "
        f"{lat['p50']} s, p99 {lat['p99']} s, max {lat['max']} s (bound {result['bound_s']} s: "
        f"{result['within_bound']:.1%} within), outcomes {result['report_outcome']}, status "
        f"{result['status']}, {result['decisions']} decisions, timing "
        f"{result['decision_timing']}",
        flush=True,
    )
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration-s", type=float, default=60.0)
    parser.add_argument("--rate", type=float, default=2.0, help="reports per second")
    parser.add_argument("--users", type=int, default=1000)
    parser.add_argument("--policy", default=None, help="default: the service's own")
    parser.add_argument("--modes", default="on-report,paced")
    parser.add_argument("--timeout-s", type=float, default=60.0, help="per request")
    parser.add_argument("--src", type=Path, default=None, help="run this source tree instead")
    parser.add_argument("--label", default=None, help="default: after, or before with --src")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    args.label = args.label or ("before" if args.src else "after")
    src = args.src.resolve() if args.src else None
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    token = secrets.token_urlsafe(24)
    mock = MockAutopilot("tcp:127.0.0.1:0", "px4", VehicleConfig(ready_delay_s=0.3)).start()
    run: dict[str, Any] = {
        "src": str(src) if src else "this tree",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "users": args.users,
        "rate_rps": args.rate,
        "duration_s": args.duration_s,
        "when": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    try:
        for mode in modes:
            run[mode] = measure(mock, token, mode, args, src)
    finally:
        mock.stop()
    out = json.loads(args.out.read_text()) if args.out.is_file() else {}
    out[args.label] = run
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.label} to {args.out}")


if __name__ == "__main__":
    main()
