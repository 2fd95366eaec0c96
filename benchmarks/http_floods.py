"""HTTP floods against ``tupa serve`` with its default limits: what the probes and the network
controller see meanwhile, and what the service holds.

Starts ``tupa serve`` on a free loopback port (no autopilot: the HTTP side works without one,
and reports are accepted) with its default settings, then, after a baseline without a flood,
runs each flood for ``--flood-s`` seconds (default 20) while a probe sends ``GET /healthz`` on
a new connection every 20 ms from ``127.0.0.1`` and the network controller POSTs a report every
200 ms on a keep-alive connection from ``127.0.0.1``:

1. ``odd-methods``: requests with 16 KB made-up methods on made-up paths and on ``/healthz``,
   no token, one per connection, as fast as one client thread can send them (from
   ``127.0.0.2``); ``/metrics`` size and scrape time are measured before and after;
2. ``idle-one-client``: 600 idle connections from ``127.0.0.3``, reopened as the server closes
   them;
3. ``idle-many-clients``: 600 idle connections from 30 addresses (20 each,
   ``127.0.0.10``-``127.0.0.39``), reopened likewise: more than the server's cap in all;
4. ``pipeline-non-readers``: 20 connections from ``127.0.0.4`` that pipeline
   ``GET /openapi.json`` until their sends block and never read; besides the flood's window,
   how long until the server has reset all of them (at most ``--settle-s``).

Per phase: probe latency p50/p99/max and failures, report statuses and p99, the most
connections the server held (``tupa_http_connections``, sampled every 0.5 s), the connections
it closed by reason, and its resident memory (``VmRSS``) before and after. The hostile clients
run in threads of this process and share the machine with the service: say what else ran on
it when quoting the figures.

    .venv/bin/python benchmarks/http_floods.py      # -> benchmarks/results/http_floods.json
    .venv/bin/python benchmarks/http_floods.py --flood-s 3 --out /tmp/floods.json   # a check
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import secrets
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))  # tests.security.floods is not an installed package

from closed_loop.processes import start_service  # noqa: E402
from tests.security.floods import (  # noqa: E402
    HealthProbe,
    IdleFlood,
    OddMethodFlood,
    PipelineNonReader,
    Reporter,
    http_get,
    loopback_sources,
    percentile,
    scrape,
)

REASONS = ("client_cap", "evicted", "full", "read_timeout", "write_timeout")


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def ms(values: list[float], q: float) -> float:
    return round(1000 * percentile(values, q), 2)


def scrape_timed(port: int) -> tuple[dict[str, float], float]:
    began = time.perf_counter()
    values = scrape(port)
    return values, time.perf_counter() - began


def run_phase(
    name: str, port: int, pid: int, token: str, flood: Any, flood_s: float, settle_s: float = 0.0
) -> dict[str, Any]:
    before, _ = scrape_timed(port)
    rss_before = rss_kb(pid)
    held: list[float] = []
    print(f"{name}: {flood_s:.0f} s", flush=True)
    with HealthProbe(port) as probe, Reporter(port, token) as reporter:
        if flood is not None:
            flood.start()
        try:
            end = time.monotonic() + flood_s
            while time.monotonic() < end:
                held.append(scrape(port)["tupa_http_connections"])
                time.sleep(0.5)
            settled_after_s = None
            if isinstance(flood, PipelineNonReader):
                # How long until the server has let go of every stalled connection.
                stalled = flood.stalled_at or time.monotonic()
                limit = time.monotonic() + settle_s
                while time.monotonic() < limit:
                    if scrape(port)["tupa_http_connections"] <= 2:
                        settled_after_s = round(time.monotonic() - stalled, 2)
                        break
                    time.sleep(0.2)
        finally:
            if flood is not None:
                flood.stop()
    after, scrape_s = scrape_timed(port)
    rss_after = rss_kb(pid)
    result: dict[str, Any] = {
        "phase": name,
        "flood_s": flood_s,
        "healthz": {
            "probes": len(probe.latencies_s),
            "failures": len(probe.failures),
            "failure_kinds": dict(Counter(probe.failures)),
            "p50_ms": ms(probe.latencies_s, 0.50),
            "p99_ms": ms(probe.latencies_s, 0.99),
            "max_ms": ms(probe.latencies_s, 1.0),
        },
        "reports": {
            "sent": len(reporter.statuses),
            "statuses": dict(Counter(reporter.statuses)),
            "p50_ms": ms(reporter.latencies_s, 0.50),
            "p99_ms": ms(reporter.latencies_s, 0.99),
            "max_ms": ms(reporter.latencies_s, 1.0),
        },
        "server": {
            "connections_max": max(held) if held else None,
            "closed": {
                reason: int(
                    after.get(f'tupa_http_connections_closed_total{{reason="{reason}"}}', 0)
                    - before.get(f'tupa_http_connections_closed_total{{reason="{reason}"}}', 0)
                )
                for reason in REASONS
            },
            "rss_kb_before": rss_before,
            "rss_kb_after": rss_after,
            "metrics_bytes_before": int(before["bytes"]),
            "metrics_bytes_after": int(after["bytes"]),
            "metrics_scrape_ms_after": round(1000 * scrape_s, 2),
        },
    }
    if flood is not None:
        counts = getattr(flood, "counts", None)
        result["flood"] = vars(counts) if counts is not None else {}
        if isinstance(flood, PipelineNonReader):
            result["flood"] = {
                "connections": flood.connections,
                "bytes_sent": flood.sent,
                "all_reset_after_s": settled_after_s,
            }
    h, r = result["healthz"], result["reports"]
    print(
        f"  /healthz p50 {h['p50_ms']} ms p99 {h['p99_ms']} ms max {h['max_ms']} ms, "
        f"{h['failures']} failures of {h['probes']}; reports {r['statuses']} "
        f"p99 {r['p99_ms']} ms; connections max {result['server']['connections_max']}, "
        f"closed {result['server']['closed']}; RSS {rss_before} -> {rss_after} kB; "
        f"metrics {result['server']['metrics_bytes_after']} B",
        flush=True,
    )
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flood-s", type=float, default=20.0)
    parser.add_argument("--baseline-s", type=float, default=10.0)
    parser.add_argument("--settle-s", type=float, default=60.0)
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks/results/http_floods.json")
    args = parser.parse_args()
    token = secrets.token_hex(16)
    proc, port = start_service(
        ["--port", "0", "--policy", "min-distance", "--mavlink", "tcp:127.0.0.1:1"],
        env={"TUPA_API_TOKEN": token},
    )
    pid = proc.proc.pid
    try:
        http_get(port, "/healthz")
        rss_start = rss_kb(pid)
        phases = [
            run_phase("baseline", port, pid, token, None, args.baseline_s),
            run_phase(
                "odd-methods",
                port,
                pid,
                token,
                OddMethodFlood(port, "127.0.0.2", max_requests=1_000_000),
                args.flood_s,
            ),
            run_phase(
                "idle-one-client",
                port,
                pid,
                token,
                IdleFlood(port, ["127.0.0.3"], per_source=600, max_opens=200_000),
                args.flood_s,
            ),
            run_phase(
                "idle-many-clients",
                port,
                pid,
                token,
                IdleFlood(port, loopback_sources(10, 30), per_source=20, max_opens=200_000),
                args.flood_s,
            ),
            run_phase(
                "pipeline-non-readers",
                port,
                pid,
                token,
                PipelineNonReader(port, "127.0.0.4", 20),
                args.flood_s,
                settle_s=args.settle_s,
            ),
        ]
        rss_end = rss_kb(pid)
    finally:
        proc.stop()
    out = {
        "command": "python benchmarks/http_floods.py "
        + " ".join(f"{k}={v}" for k, v in vars(args).items() if k != "out"),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "settings": "tupa serve defaults (no autopilot)",
        "rss_kb_start": rss_start,
        "rss_kb_end": rss_end,
        "rss_change_pct": round(100 * (rss_end - rss_start) / rss_start, 2),
        "phases": phases,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"RSS {rss_start} -> {rss_end} kB ({out['rss_change_pct']:+.2f} %); wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
