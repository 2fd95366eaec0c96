"""Open operator pages for the service's benchmarks: ``n`` streams of ``GET /v1/live/events``.

Each stream is what one open page costs the service: a connection holding the stream, read as
fast as frames come (counted per page). They run on an asyncio loop in a thread of their own,
through raw sockets (no HTTP client library: a benchmark's client must cost less than what it
measures). Bounded: they stop when told, or when the server ends them.

    pages = LivePages("127.0.0.1", port, token, n=10).start()   # each has its first frame
    ...
    pages.stop(); pages.frames                                   # frames per page
"""

from __future__ import annotations

import asyncio
import threading
import time


class LivePages:
    def __init__(self, host: str, port: int, token: str, n: int) -> None:
        self.host, self.port, self.token, self.n = host, port, token, n
        self.frames = [0] * n
        self.bytes = [0] * n
        self.statuses: list[int | None] = [None] * n
        self.errors: list[str] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="live-pages", daemon=True)

    def start(self, timeout_s: float = 15.0) -> LivePages:
        """Open the streams; returns once each has had its first frame (or raises)."""
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise TimeoutError(f"live pages: not all ready within {timeout_s} s")
        deadline = time.monotonic() + timeout_s
        while min(self.frames) < 1:
            if self.errors or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"live pages: {self.errors or 'no first frame'}")
            time.sleep(0.01)
        return self

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10.0)

    def _run(self) -> None:
        asyncio.run(self._main())

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._ready.set()
        tasks = [asyncio.create_task(self._page(i)) for i in range(self.n)]
        await self._stop.wait()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    async def _page(self, i: int) -> None:
        writer = None
        try:
            reader, writer = await asyncio.open_connection(self.host, self.port, limit=1 << 24)
            writer.write(
                f"GET /v1/live/events HTTP/1.1\r\nHost: {self.host}:{self.port}\r\n"
                f"Authorization: Bearer {self.token}\r\nAccept: text/event-stream\r\n\r\n".encode()
            )
            status_line = await reader.readline()
            self.statuses[i] = int(status_line.split()[1])
            if self.statuses[i] != 200:
                raise RuntimeError(f"page {i}: {status_line.decode().strip()}")
            while line := await reader.readline():  # chunk sizes and SSE lines alike
                self.bytes[i] += len(line)
                if line.startswith(b"event: frame"):
                    self.frames[i] += 1
        except asyncio.CancelledError:
            pass
        except Exception as exc:  # recorded, the others go on
            self.errors.append(f"page {i}: {type(exc).__name__}: {exc}")
        finally:
            if writer is not None:
                writer.close()
