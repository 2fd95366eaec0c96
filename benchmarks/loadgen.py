"""An open-loop HTTP load generator for the service's benchmarks (soak, service latency).

Request i is due at ``start + i / rate`` whatever the answers do (open loop), and goes out on the
first free of ``conns`` keep-alive connections through a minimal HTTP/1.1 client: at 1,000
requests/s a general client (httpx) spends more CPU than the service it measures on a small
machine. Bounded in count (``rate × duration``) and time.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import numpy as np


class Connection:
    """One keep-alive HTTP/1.1 connection with a minimal client: write a prepared request, read
    the status line, the headers and a Content-Length body. At 1,000 requests/s a general client
    (httpx) spends more CPU than the service it measures on a small machine; this one does not."""

    def __init__(self, host: str, port: int) -> None:
        self.host, self.port = host, port
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def request(self, raw: bytes, timeout_s: float) -> int:
        if self.writer is None:
            self.reader, self.writer = await asyncio.wait_for(
                asyncio.open_connection(self.host, self.port), timeout_s
            )
        assert self.reader is not None
        self.writer.write(raw)
        return await asyncio.wait_for(self._response(self.reader), timeout_s)

    async def _response(self, reader: asyncio.StreamReader) -> int:
        parts = (await reader.readline()).split()
        if len(parts) < 2 or not parts[1].isdigit():
            raise ValueError(f"not an HTTP status line: {parts!r}")
        status = int(parts[1])
        length = 0
        close = False
        while (line := await reader.readline()) not in (b"\r\n", b""):
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"content-length":
                length = int(value)
            elif name.strip().lower() == b"connection" and b"close" in value.lower():
                close = True
        await reader.readexactly(length)
        if close:
            self.close()
        return status

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None


async def load_phase(
    host: str, port: int, token: str, rate: float, duration_s: float, body: bytes, conns: int = 32
) -> dict[str, Any]:
    """Open loop: request i is due at start + i / rate and goes out on the first free
    connection (``conns`` keep-alive connections). Latency is measured from the send and, to
    count any queueing in the generator too, from the time the request was due."""
    n = int(rate * duration_s)
    raw = (
        f"POST /v1/reports HTTP/1.1\r\nHost: {host}:{port}\r\n"
        f"Authorization: Bearer {token}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    ).encode() + body
    records: list[tuple[float, float | None, float]] = []  # (sent, latency or None, from due)
    lateness: list[float] = []
    errors: dict[str, int] = {}
    queue: asyncio.Queue[float | None] = asyncio.Queue()

    async def worker() -> None:
        connection = Connection(host, port)
        try:
            while (due := await queue.get()) is not None:
                sent = time.monotonic()
                lateness.append(sent - due)
                try:
                    status = await connection.request(raw, 5.0)
                except (TimeoutError, OSError, asyncio.IncompleteReadError, ValueError) as exc:
                    connection.close()
                    errors[type(exc).__name__] = errors.get(type(exc).__name__, 0) + 1
                    records.append((sent, None, time.monotonic() - due))
                    continue
                done = time.monotonic()
                if status != 200:
                    errors[str(status)] = errors.get(str(status), 0) + 1
                    records.append((sent, None, done - due))
                else:
                    records.append((sent, done - sent, done - due))
        finally:
            connection.close()

    workers = [asyncio.create_task(worker()) for _ in range(conns)]
    start = time.monotonic() + 0.05
    for i in range(n):
        due = start + i / rate
        delay = due - time.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        queue.put_nowait(due)
    for _ in workers:
        queue.put_nowait(None)
    await asyncio.wait_for(asyncio.gather(*workers), timeout=60)
    end = time.monotonic()
    ok = [r[1] for r in records if r[1] is not None]
    lat = np.array(ok) * 1e3 if ok else np.array([np.nan])
    from_due = np.array([r[2] for r in records]) * 1e3
    late = np.array(lateness) * 1e3
    return {
        "rate_rps": rate,
        "duration_s": duration_s,
        "requests": n,
        "ok": len(ok),
        "errors": errors,
        "error_count": sum(errors.values()),
        "achieved_rps": round(len(ok) / (end - start), 1),
        "latency_ms": {
            "p50": round(float(np.percentile(lat, 50)), 2),
            "p99": round(float(np.percentile(lat, 99)), 2),
            "max": round(float(np.max(lat)), 2),
        },
        "latency_from_due_ms": {
            "p50": round(float(np.percentile(from_due, 50)), 2),
            "p99": round(float(np.percentile(from_due, 99)), 2),
        },
        "generator_lateness_p99_ms": round(float(np.percentile(late, 99)), 2),
        "_records": [(r[0], r[1]) for r in records],
        "_t0": start,
        "_t1": end,
    }
