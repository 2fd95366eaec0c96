"""Per-client rate limit: a token bucket per client address, as a pure ASGI middleware.

Each client (the peer address of the connection) has a bucket of ``burst`` tokens that refills
at ``rate_per_s`` tokens per second; a request takes one token. Requests that carry the API
token and requests that do not (no token, a wrong one: whoever sends them) have separate
buckets per address, so a flood of unauthenticated requests from the controller's own address
is limited without spending any of the controller's budget. A request that finds the bucket
empty is answered ``429 Too Many Requests`` with ``Retry-After`` (whole seconds, at least 1)
before any route runs. The probes (``GET`` or ``HEAD`` ``/healthz`` and ``/readyz``) are never
limited, so that a client flooding the service cannot make an orchestrator restart it; any
other method on those paths is limited like any request.

The middleware runs on the event loop (one thread), so the buckets need no lock. At most
``max_clients`` buckets are kept (least recently seen dropped first): memory stays bounded
whatever the number of addresses. Behind a reverse proxy every request has the proxy's address:
name it in ``trusted_proxies`` (its ``X-Forwarded-For`` then names the client), limit there
instead, or disable this one (``rate_limit_rps = 0``). ``X-Forwarded-For`` from anyone else is
ignored: a client must not choose the address it is limited by.
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable

from starlette.types import ASGIApp, Receive, Scope, Send

from api.auth import is_authenticated
from api.responses import send_error

log = logging.getLogger(__name__)
UNLIMITED_PATHS = frozenset({"/healthz", "/readyz"})
UNLIMITED_METHODS = frozenset({"GET", "HEAD"})


class TokenBuckets:
    """Token buckets keyed by client; ``take(key)`` is 0.0 when allowed, else the seconds until
    a token is available."""

    def __init__(
        self,
        rate_per_s: float,
        burst: int,
        max_clients: int = 10_000,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not rate_per_s > 0 or not math.isfinite(rate_per_s):
            raise ValueError(f"rate_per_s: must be a finite number > 0, got {rate_per_s}")
        if burst < 1:
            raise ValueError(f"burst: must be at least 1, got {burst}")
        self.rate_per_s = float(rate_per_s)
        self.burst = float(burst)
        self.max_clients = max_clients
        self._clock = clock
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # tokens, at

    def take(self, key: str) -> float:
        now = self._clock()
        tokens, at = self._buckets.pop(key, (self.burst, now))
        tokens = min(self.burst, tokens + (now - at) * self.rate_per_s)
        wait_s = 0.0
        if tokens >= 1.0 - 1e-9:  # a token earned exactly now counts, whatever the rounding
            tokens = max(0.0, tokens - 1.0)
        else:
            wait_s = (1.0 - tokens) / self.rate_per_s
        self._buckets[key] = (tokens, now)  # most recently seen last
        while len(self._buckets) > self.max_clients:
            self._buckets.popitem(last=False)
        return wait_s

    def __len__(self) -> int:
        return len(self._buckets)


class RateLimit:
    """Pure ASGI middleware: 429 with ``Retry-After`` for a client over its rate.

    ``token``: the API token; requests with and without it are counted apart (``None``: no
    token is configured, every request counts as authenticated).
    """

    def __init__(
        self,
        app: ASGIApp,
        rate_per_s: float,
        burst: int,
        on_reject: Callable[[], None] | None = None,
        max_clients: int = 10_000,
        token: str | None = None,
    ) -> None:
        self.app = app
        self.buckets = TokenBuckets(rate_per_s, burst, max_clients)
        self.on_reject = on_reject
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or (
            scope.get("path") in UNLIMITED_PATHS and scope.get("method") in UNLIMITED_METHODS
        ):
            await self.app(scope, receive, send)
            return
        client = scope.get("client")
        address = str(client[0]) if client else "unknown"
        authenticated = self.token is None or is_authenticated(scope, self.token)
        key = address if authenticated else f"unauthenticated {address}"
        wait_s = self.buckets.take(key)
        if wait_s <= 0.0:
            await self.app(scope, receive, send)
            return
        if self.on_reject is not None:
            self.on_reject()
        log.debug("429 for %s %s from %s", scope.get("method"), scope.get("path"), key)
        retry_after = max(1, math.ceil(wait_s))
        rate = self.buckets.rate_per_s
        await send_error(
            send,
            429,
            f"rate limit: over {rate:g} requests/s from this client; retry after {retry_after} s",
            [(b"retry-after", str(retry_after).encode())],
        )
