"""Load and soak of the placement service (issue 7): bounded figures over minutes, not seconds.

Starts, on loopback with free ports, a PX4-flavoured mock autopilot as its own process (the
``tests.faults.mock_process`` wrapper of ``tupa sitl-mock``, which also serves its counters over
HTTP) and ``tupa serve --arm-and-takeoff`` (default policy: the shipped DDQN), waits until the
vehicle is airborne and a first decision streams, then runs two phases of POST /v1/reports from
an open-loop asyncio generator (requests are due on a fixed schedule whatever the answers do, as
in benchmarks/service_latency.py, and go out on 32 keep-alive connections through a minimal
HTTP/1.1 client: httpx's connection pool costs more CPU than the service at 1,000 requests/s):

1. 1,000 requests/s for 60 s;
2. 200 requests/s for 10 minutes.

Every ``--sample-s`` seconds (default 5) a sampler records the service's resident memory
(``VmRSS`` in /proc/PID/status) and the mock's received-setpoint counter. Per phase: requests,
errors (non-2xx or transport errors), achieved rate, latency p50/p99/max, how late the generator
ran (its p99 lateness: when large, the client, not the service, was the limit), latency from
the time each request was due (so queueing in the generator is not hidden), and per window
p99 latency and setpoint rate at the vehicle (min/max). Overall: RSS at the start of the soak and
at the end (flat: within 10 %), OFFBOARD failsafes at the vehicle (must be 0).

With ``--pages N`` (default 10; issue 18) N operator pages stay open through both phases: each
a ``GET /v1/live/events`` stream read as frames come (benchmarks/live_pages.py); the frames each
received are counted (one per decision period expected), and the memory check covers them.

Every report of a phase carries the same timestamp (concurrent requests never count as out of
order); the service decides once a second (paced) from the latest one. The generator, the
service and the mock share the machine: say what else ran on it when quoting the figures.

    .venv/bin/python benchmarks/soak.py            # 60 s + 10 min -> benchmarks/results/soak.json
    .venv/bin/python benchmarks/soak.py --quick    # 10 s + 20 s, to check the script
    .venv/bin/python benchmarks/soak.py --soak-s 120 --out /tmp/soak.json   # a shorter soak
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import platform
import secrets
import sys
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # tests.faults.mock_process is not an installed package

from live_pages import LivePages  # noqa: E402
from loadgen import load_phase  # noqa: E402

from closed_loop.processes import start_service  # noqa: E402
from tests.faults.mock_process import start_mock_process  # noqa: E402
from tests.helpers import wait_for  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "soak.json"
USERS = [
    {"id": "ue-1", "x_m": 140.0, "y_m": 240.0, "offered_bps": 30e6, "throughput_bps": 21e6,
     "delay_s": 0.4, "plr": 0.15},
    {"id": "ue-2", "x_m": 360.0, "y_m": 260.0, "offered_bps": 5e6, "throughput_bps": 5e6,
     "delay_s": 0.004, "plr": 0.0},
    {"id": "ue-3", "x_m": 260.0, "y_m": 390.0, "offered_bps": 5e6, "throughput_bps": 5e6,
     "delay_s": 0.004, "plr": 0.0},
]  # fmt: skip


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


class Sampler:
    """Every ``period_s``: (monotonic time, service RSS kB, mock setpoints received)."""

    def __init__(self, pid: int, mock: Any, period_s: float) -> None:
        self.pid, self.mock, self.period_s = pid, mock, period_s
        self.samples: list[tuple[float, int, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sampler", daemon=True)

    def sample(self) -> tuple[float, int, int]:
        entry = (time.monotonic(), rss_kb(self.pid), self.mock.stats()["setpoints_received"])
        self.samples.append(entry)
        return entry

    def _run(self) -> None:
        next_at = time.monotonic()
        while not self._stop.is_set():
            try:
                self.sample()
            except Exception as exc:  # a failed sample is recorded, not fatal
                print(f"sample failed: {exc}", flush=True)
            next_at += self.period_s
            self._stop.wait(max(0.0, next_at - time.monotonic()))

    def start(self) -> Sampler:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(10.0)

    def between(self, t0: float, t1: float) -> list[tuple[float, int, int]]:
        return [s for s in self.samples if t0 <= s[0] <= t1]


def windows(
    phase: dict[str, Any], samples: list[tuple[float, int, int]], min_window_s: float
) -> tuple[list[dict[str, Any]], dict[str, float]]:
    """Per sampling window: p99 latency of the requests sent in it, errors, setpoint rate."""
    records = phase.pop("_records")
    t0 = phase.pop("_t0")
    out = []
    for (ta, _rss_a, sp_a), (tb, rss_b, sp_b) in itertools.pairwise(samples):
        if tb - ta < 0.5 * min_window_s:  # a late sample right before a prompt one
            continue
        in_window = [lat for t, lat in records if ta <= t < tb]
        ok = [lat for lat in in_window if lat is not None]
        out.append(
            {
                "t_s": round(tb - t0, 1),
                "requests": len(in_window),
                "errors": len(in_window) - len(ok),
                "p99_ms": round(float(np.percentile(np.array(ok) * 1e3, 99)), 2) if ok else None,
                "setpoint_rate_hz": round((sp_b - sp_a) / (tb - ta), 2),
                "rss_kb": rss_b,
            }
        )
    rates = [w["setpoint_rate_hz"] for w in out]
    summary = {
        "setpoint_rate_min_hz": min(rates) if rates else float("nan"),
        "setpoint_rate_max_hz": max(rates) if rates else float("nan"),
    }
    return out, summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="10 s + 20 s, to check the script")
    parser.add_argument("--sample-s", type=float, default=5.0, help="sampling period (default 5)")
    parser.add_argument("--policy", default=None, help="tupa serve --policy (default: shipped)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument(
        "--pages", type=int, default=10, help="operator pages open throughout (default 10)"
    )
    parser.add_argument(
        "--soak-s", type=float, default=None, help="length of the 200 requests/s phase"
    )
    args = parser.parse_args()
    phases = [(1000.0, 10.0), (200.0, 20.0)] if args.quick else [(1000.0, 60.0), (200.0, 600.0)]
    if args.soak_s is not None:
        phases[-1] = (200.0, args.soak_s)
    sample_s = min(args.sample_s, 2.0) if args.quick else args.sample_s
    token = secrets.token_urlsafe(24)
    out: dict[str, Any] = {
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "loadavg_at_start": list(os.getloadavg()),
        },
        "quick": args.quick,
        "sample_s": sample_s,
        "pages": args.pages,
    }
    mock = start_mock_process(
        ["--listen", "tcp:127.0.0.1:0", "--flavour", "px4", "--ready-delay-s", "1",
         "--climb-speed-mps", "8", "--battery-capacity-mah", "1000000"]
    )  # fmt: skip
    proc = None
    pages = None
    try:
        serve_args = [
            "--mavlink",
            f"tcp:127.0.0.1:{mock.port}",
            "--port",
            "0",
            "--arm-and-takeoff",
            "--log-level",
            "warning",
            # One load generator is one client: the per-client limits are not what is measured.
            "--rate-limit-rps",
            "0",
        ]
        if args.policy:
            serve_args += ["--policy", args.policy]
        proc, port = start_service(
            serve_args,
            env={
                "TUPA_API_TOKEN": token,
                "TUPA_HTTP_MAX_CONNECTIONS_PER_CLIENT": "512",
                "TUPA_AREA_ORIGIN_NORTH_M": "-250",
                "TUPA_AREA_ORIGIN_EAST_M": "-250",
            },
        )
        base = f"http://127.0.0.1:{port}"
        auth = {"Authorization": f"Bearer {token}"}
        with httpx.Client(base_url=base, headers=auth, timeout=10.0) as client:
            wait_for(lambda: client.get("/readyz").status_code == 200, 60, 0.2, "ready")
            wait_for(lambda: mock.state()["alt_m"] > 22.0, 60, 0.2, "airborne")
            client.post("/v1/reports", json={"timestamp": 1.0, "users": USERS}).raise_for_status()
            wait_for(lambda: client.get("/v1/setpoint").json()["target"], 10, 0.2, "a decision")
            wait_for(lambda: mock.state()["mode"] == "OFFBOARD", 15, 0.2, "OFFBOARD")
            out["policy"] = client.get("/v1/policy").json()["name"]
        pid = proc.proc.pid
        if args.pages:
            pages = LivePages("127.0.0.1", port, token, args.pages).start()
            pages_opened = time.monotonic()
            print(f"{args.pages} operator pages open", flush=True)
        sampler = Sampler(pid, mock, sample_s)
        sampler.start()
        first = wait_for(lambda: sampler.samples and sampler.samples[0], 10, 0.2, "a first sample")
        out["rss_kb_start"] = first[1]
        results = []
        for i, (rate, duration) in enumerate(phases):
            body = json.dumps({"timestamp": 10.0 + i, "users": USERS}).encode()
            print(f"phase {i + 1}: {rate:.0f} requests/s for {duration:.0f} s", flush=True)
            phase = asyncio.run(load_phase("127.0.0.1", port, token, rate, duration, body))
            t0, t1 = phase["_t0"], phase["_t1"]
            phase["windows"], summary = windows(phase, sampler.between(t0 - sample_s, t1), sample_s)
            phase.pop("_t1")
            phase.update(summary)
            phase["rss_kb_end"] = rss_kb(pid)
            results.append(phase)
            print(
                f"  ok {phase['ok']}/{phase['requests']}, errors {phase['errors']}, "
                f"p50 {phase['latency_ms']['p50']} p99 {phase['latency_ms']['p99']} ms, "
                f"achieved {phase['achieved_rps']}/s, generator late p99 "
                f"{phase['generator_lateness_p99_ms']} ms, setpoints "
                f"{phase['setpoint_rate_min_hz']}-{phase['setpoint_rate_max_hz']} Hz, "
                f"RSS {phase['rss_kb_end']} kB",
                flush=True,
            )
        sampler.stop()
        if pages is not None:
            pages.stop()
            open_s = time.monotonic() - pages_opened
            expected = open_s / 1.0  # one frame per decision period (1 s)
            out["pages"] = {
                "open_s": round(open_s, 1),
                "frames_min": min(pages.frames),
                "frames_max": max(pages.frames),
                "frames_expected": round(expected),
                "bytes_per_page_min": min(pages.bytes),
                "errors": pages.errors,
            }
            pages = None
        out["phases"] = results
        soak = results[-1]
        soak_start = soak["windows"][0]["rss_kb"] if soak["windows"] else first[1]
        out["memory"] = {
            "rss_kb_before_load": first[1],
            "rss_kb_soak_start": soak_start,
            "rss_kb_end": sampler.samples[-1][1],
            "change_over_soak_pct": round(100 * (sampler.samples[-1][1] / soak_start - 1), 2),
            "change_over_everything_pct": round(100 * (sampler.samples[-1][1] / first[1] - 1), 2),
        }
        stats = mock.stats()
        out["vehicle"] = {
            "failsafe_offboard": stats["failsafe_offboard"],
            "failsafe_gcs": stats["failsafe_gcs"],
            "setpoints_received": stats["setpoints_received"],
            "mode_at_end": mock.state()["mode"],
        }
        out["checks"] = {
            "errors": sum(p["error_count"] for p in results),
            "p99_ms_max_over_phases": max(p["latency_ms"]["p99"] for p in results),
            "memory_flat_within_10pct": abs(out["memory"]["change_over_soak_pct"]) <= 10.0,
            "setpoint_rate_min_hz": min(p["setpoint_rate_min_hz"] for p in results),
            "setpoint_rate_max_hz": max(p["setpoint_rate_max_hz"] for p in results),
            "setpoints_above_px4_minimum_2hz": min(p["setpoint_rate_min_hz"] for p in results)
            > 2.0,
            "no_offboard_failsafe": stats["failsafe_offboard"] == 0,
        }
        if "pages" in out:  # every page kept getting its frame each period
            out["checks"]["pages_live_throughout"] = (
                not out["pages"]["errors"]
                and out["pages"]["frames_min"] >= 0.9 * out["pages"]["frames_expected"]
            )
    finally:
        if pages is not None:
            pages.stop()
        if proc is not None:
            proc.stop()
        mock.stop()
    out["machine"]["loadavg_at_end"] = list(os.getloadavg())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out["checks"], indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
