"""A lossy, delaying UDP path for MAVLink tests: ``client <-> proxy <-> server`` on loopback.

The client (the service, ``--mavlink udpout:127.0.0.1:FRONT``) sends to the proxy's front port;
the proxy forwards each datagram to the server (the mock, ``--listen udp:127.0.0.1:PORT``) from
its back socket, and the server's answers back to the client's latest address. Every datagram, in
either direction, is dropped with probability ``loss`` and otherwise delayed by a uniform random
``0 .. jitter_s`` (so datagrams may also arrive out of order, as on a real radio link). One
thread, a ``selectors`` loop and a heap of datagrams due; seeded, so a run can be repeated::

    with UdpProxy(("127.0.0.1", mock_port), loss=0.1, jitter_s=0.03, seed=1) as proxy:
        url = f"udpout:127.0.0.1:{proxy.port}"
        ...
        print(proxy.counters)   # forwarded / dropped, per direction
"""

from __future__ import annotations

import contextlib
import heapq
import random
import selectors
import socket
import threading
import time
from collections import Counter


class UdpProxy:
    def __init__(
        self,
        server: tuple[str, int],
        loss: float = 0.0,
        jitter_s: float = 0.0,
        seed: int = 0,
        host: str = "127.0.0.1",
    ) -> None:
        if not 0.0 <= loss < 1.0:
            raise ValueError(f"loss: must be in [0, 1), got {loss}")
        if jitter_s < 0:
            raise ValueError(f"jitter_s: must be >= 0, got {jitter_s}")
        self.server = server
        self.loss = loss
        self.jitter_s = jitter_s
        self._rng = random.Random(seed)
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind((host, 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind((host, 0))
        for sock in (self.front, self.back):
            sock.setblocking(False)
        self.port = self.front.getsockname()[1]
        self.client: tuple[str, int] | None = None
        self.counters: Counter[str] = Counter()
        self._due: list[tuple[float, int, str, bytes]] = []
        self._seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="udp-proxy", daemon=True)

    def start(self) -> UdpProxy:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        for sock in (self.front, self.back):
            with contextlib.suppress(OSError):
                sock.close()

    def __enter__(self) -> UdpProxy:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _admit(self, direction: str, data: bytes, now: float) -> None:
        if self._rng.random() < self.loss:
            self.counters[f"dropped_{direction}"] += 1
            return
        self._seq += 1
        due = now + self._rng.uniform(0.0, self.jitter_s)
        heapq.heappush(self._due, (due, self._seq, direction, data))

    def _run(self) -> None:
        selector = selectors.DefaultSelector()
        selector.register(self.front, selectors.EVENT_READ, "up")
        selector.register(self.back, selectors.EVENT_READ, "down")
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                timeout = 0.05 if not self._due else max(0.0, min(0.05, self._due[0][0] - now))
                for key, _ in selector.select(timeout):
                    sock: socket.socket = key.fileobj  # type: ignore[assignment]
                    for _ in range(256):
                        try:
                            data, address = sock.recvfrom(65536)
                        except (BlockingIOError, InterruptedError):
                            break
                        except OSError:  # ICMP port unreachable from a peer that went away
                            self.counters["receive_errors"] += 1
                            continue
                        if key.data == "up":
                            self.client = address  # a reconnecting client has a new port
                        self._admit(key.data, data, time.monotonic())
                now = time.monotonic()
                while self._due and self._due[0][0] <= now:
                    _, _, direction, data = heapq.heappop(self._due)
                    try:
                        if direction == "up":
                            self.back.sendto(data, self.server)
                        elif self.client is not None:
                            self.front.sendto(data, self.client)
                        self.counters[f"forwarded_{direction}"] += 1
                    except OSError:
                        self.counters["send_errors"] += 1
        finally:
            selector.close()
