"""The HTTP server ``tupa serve`` runs: uvicorn, with limits a hostile client cannot get past.

uvicorn's defaults suit a trusted network. Out of the box it picks the ``httptools`` parser when
installed, which puts no bound on a request head (a 100 MB header is buffered and parsed, slowly);
it never times out a connection that sends half a request and stalls (nor one that never sends
anything); and it trusts ``X-Forwarded-For`` from 127.0.0.1, so any local client chooses its own
address. :func:`server_config` builds the one configuration both ``tupa serve`` and
:func:`api.app.run` use:

* the ``h11`` parser, whose ``max_incomplete_event_size`` bounds the request head
  (``http_max_header_bytes``): a longer one gets 400 and the connection is closed, after reading
  at most one socket buffer of it; the number of header lines is bounded by the app
  (:class:`api.app.HeaderLimit`, 431);
* a read deadline (``http_request_timeout_s``) from a connection's first byte (or from when it
  opened) until the whole request, body included, is in: :func:`guarded_h11`;
* a write deadline (``http_write_timeout_s``): a connection whose unsent bytes have not
  shrunk for that long (its client reads nothing) is reset, whatever it was doing;
* keep-alive connections closed after ``http_keep_alive_s`` idle;
* connection caps, per client (peer address, ``http_max_connections_per_client``) and in all
  (``http_max_connections``), shared fairly: at the cap a newcomer takes the place of a
  connection of the client holding the most, so that one client's flood (or a few clients')
  cannot take every place, and the probes and the network controller find one
  (:class:`ConnectionTable`). Refused connections are closed at once; requests are never
  answered 503 for want of a place (each connection carries one request at a time);
* no WebSocket upgrades (the app has no WebSocket route);
* no proxy headers from uvicorn: the app honours ``X-Forwarded-For`` only from
  ``trusted_proxies`` (:func:`api.app.create_app`).

Long-lived responses (the operator view's streams, :mod:`api.live`) and these limits: the read
deadline ends once a request is in (a stream's ``GET`` has no body), and the keep-alive timeout
applies only between requests, so neither cuts an open stream. Each stream holds one of the
``http_max_connections`` for as long as it is open: the app caps streams at
``live_max_streams`` (503 beyond), well below it, so that the network controller always finds a
place; a stream whose client stops reading is cut off by the write deadline or by the stream's
own (``live_stall_s``), whichever comes first. uvicorn waits at shutdown until every response
is complete, which a stream never is: :class:`Server` ends the streams first.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import socket
import sys
from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.utils import get_remote_addr

from service.settings import ServiceSettings

log = logging.getLogger(__name__)

_TIMEOUT_RESPONSE = (
    b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
    b"connection: close\r\ncontent-length: 16\r\n\r\nrequest timeout\n"
)


class ConnectionTable:
    """The server's open connections, by client (peer address), and the caps on them.

    ``admit`` decides when a connection opens:

    * a client that already holds ``max_per_client`` connections is refused (``client_cap``),
      unless ``is_exempt(client)`` (a trusted proxy, which speaks for many clients);
    * with ``max_total`` connections open, the newcomer takes the place of one held by the
      client holding the most, if that client holds more than the newcomer does: its oldest
      idle connection is closed (else its oldest one; ``evicted``); otherwise the newcomer is
      refused (``full``). So a client's share shrinks to make room for one that holds less,
      and a client with no connection (a probe, the network controller) always gets one
      while another client holds several.

    A refused connection is closed at once, nothing answered. ``closed`` counts the
    connections the server closed itself, by reason (with ``read_timeout`` and
    ``write_timeout``, counted by the protocol). Everything runs on the event loop: no lock.
    """

    def __init__(
        self,
        max_total: int,
        max_per_client: int,
        is_exempt: Callable[[str], bool] = lambda client: False,
    ) -> None:
        if max_total < 1 or max_per_client < 1:
            raise ValueError("max_total and max_per_client: must be at least 1")
        self.max_total = max_total
        self.max_per_client = max_per_client
        self.is_exempt = is_exempt
        self._by_client: dict[str, dict[Any, None]] = {}  # oldest connection first
        self._by_size: dict[int, dict[str, None]] = {}  # clients by connections held
        self._biggest = 0  # the most any client holds
        self.total = 0
        self.closed: Counter[str] = Counter()

    @property
    def clients(self) -> int:
        """How many clients hold a connection."""
        return len(self._by_client)

    def held_by(self, client: str) -> int:
        """How many connections ``client`` holds."""
        return len(self._by_client.get(client, ()))

    def admit(self, connection: Any, client: str) -> bool:
        """Whether ``connection`` from ``client`` may stay open (see the class docstring); when
        it may, it is counted until :meth:`remove`. ``connection`` has ``is_idle()`` and
        ``evict()``. Constant time, but for finding an idle connection of the biggest client."""
        held = self.held_by(client)
        if held >= self.max_per_client and not self.is_exempt(client):
            self.closed["client_cap"] += 1
            return False
        if self.total >= self.max_total:
            if self._biggest <= held:
                self.closed["full"] += 1
                return False
            biggest = next(iter(self._by_size[self._biggest]))
            victims = self._by_client[biggest]
            victim = next((c for c in victims if c.is_idle()), next(iter(victims)))
            self._forget(victim, biggest)
            self.closed["evicted"] += 1
            victim.evict()
        self._by_client.setdefault(client, {})[connection] = None
        self._resize(client, held, held + 1)
        self.total += 1
        return True

    def remove(self, connection: Any, client: str) -> None:
        """Stop counting ``connection`` (it closed); nothing if it is not counted."""
        if connection in self._by_client.get(client, ()):
            self._forget(connection, client)

    def connections(self) -> list[Any]:
        """Every connection counted, oldest client first."""
        return [c for held in self._by_client.values() for c in held]

    def _forget(self, connection: Any, client: str) -> None:
        held = self._by_client[client]
        del held[connection]
        self.total -= 1
        self._resize(client, len(held) + 1, len(held))
        if not held:
            del self._by_client[client]

    def _resize(self, client: str, old: int, new: int) -> None:
        """Move ``client`` from the clients holding ``old`` to those holding ``new`` (one
        more or one fewer), keeping ``_biggest``."""
        if old:
            same = self._by_size[old]
            del same[client]
            if not same:
                del self._by_size[old]
        if new:
            self._by_size.setdefault(new, {})[client] = None
        if new > self._biggest:
            self._biggest = new
        elif old == self._biggest and old not in self._by_size:
            self._biggest = new  # it was the only one that big: now one fewer


def trusted(addresses: Iterable[str]) -> Callable[[str], bool]:
    """Whether a peer address is one of ``addresses`` (addresses, networks such as
    ``10.0.0.0/8``, or ``*`` for any), as ``trusted_proxies`` names them."""
    names = set(addresses)
    networks = []
    for name in names:
        with contextlib.suppress(ValueError):  # a name, not an address (a Unix socket's)
            networks.append(ipaddress.ip_network(name, strict=False))

    def is_trusted(client: str) -> bool:
        if "*" in names or client in names:
            return True
        if not networks:
            return False
        try:
            address = ipaddress.ip_address(client)
        except ValueError:
            return False
        return any(address in network for network in networks)

    return is_trusted


def guarded_h11(
    read_timeout_s: float,
    write_timeout_s: float | None = None,
    table: ConnectionTable | None = None,
) -> type[H11Protocol]:
    """uvicorn's h11 protocol, closing a connection that takes longer than ``read_timeout_s`` to
    send a whole request, or that has not taken any of what it is sent for ``write_timeout_s``
    (default: ``read_timeout_s``), and admitting connections through ``table`` (none: no caps).

    Reading: the deadline starts when the connection opens (a client that never sends
    anything), and again at the first byte of each later request (between requests uvicorn's
    keep-alive timeout applies); it ends once the request, body included, has been received:
    from then on the time is the application's. A client still sending at the deadline
    (slowly, stalled, or with a body shorter than its ``Content-Length``) gets ``408`` when
    nothing was answered yet, and the connection is closed.

    Writing: a connection with bytes waiting to be sent (the client's and the server's socket
    buffers are full: the client reads nothing) whose backlog has not shrunk for
    ``write_timeout_s`` is aborted (reset), whatever it is doing: a response being written, a
    pipelined request's answer, a close waiting to flush. Checked every quarter of
    ``write_timeout_s`` (at most every second) while connections are open.
    """
    write_s = read_timeout_s if write_timeout_s is None else write_timeout_s
    check_every_s = min(1.0, write_s / 4)
    connections = table if table is not None else ConnectionTable(sys.maxsize, sys.maxsize)
    sweeping: dict[asyncio.AbstractEventLoop, asyncio.TimerHandle] = {}  # the next write check

    def sweep(loop: asyncio.AbstractEventLoop) -> None:
        del sweeping[loop]
        now = loop.time()
        for connection in connections.connections():
            connection.check_writes(now)
        if connections.total:
            sweeping[loop] = loop.call_later(check_every_s, sweep, loop)

    class GuardedH11Protocol(H11Protocol):
        _read_deadline: asyncio.TimerHandle | None = None
        _key: str | None = None  # the client, once admitted
        _stalled_since: float | None = None
        _stalled_backlog = 0

        def __init__(self, *args: Any, **kwargs: Any) -> None:
            # Set up only once admitted: a refused connection (one of thousands a second, in
            # a flood) costs the event loop as little as it can.
            self._setup = (args, kwargs)

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            peer = get_remote_addr(transport)
            client = str(peer[0]) if peer else "unknown"
            if not connections.admit(self, client):
                log.debug("refusing a connection from %s: over its share", client)
                transport.abort()
                return
            args, kwargs = self._setup
            super().__init__(*args, **kwargs)
            super().connection_made(transport)
            self._key = client
            if self.loop not in sweeping:
                sweeping[self.loop] = self.loop.call_later(check_every_s, sweep, self.loop)
            self._arm_read_deadline()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if self.conn.their_state in (h11.IDLE, h11.SEND_BODY):  # a request is arriving
                self._arm_read_deadline()
            else:  # in whole (DONE), or the connection is ending
                self._cancel_read_deadline()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if self.conn.their_state is h11.SEND_BODY:  # a pipelined request is arriving
                self._arm_read_deadline()
            else:  # idle between requests: the keep-alive timeout applies
                self._cancel_read_deadline()

        def resume_writing(self) -> None:
            super().resume_writing()
            self._stalled_since = None  # the client took some

        def connection_lost(self, exc: Exception | None) -> None:
            if self._key is None:  # refused: never set up
                return
            self._cancel_read_deadline()
            connections.remove(self, self._key)
            super().connection_lost(exc)

        def is_idle(self) -> bool:
            """No request arriving or being answered (between requests, or none yet)."""
            return (
                self.cycle is None or self.cycle.response_complete
            ) and self.conn.their_state is h11.IDLE

        def evict(self) -> None:
            """Close to make room for another client's connection: an idle one gently, else
            at once (what was in flight is lost)."""
            log.debug("evicting a connection from %s to make room", self._key)
            if self.is_idle() and not self.transport.get_write_buffer_size():
                self.transport.close()
            else:
                self.transport.abort()

        def check_writes(self, now: float) -> None:
            """Abort the connection if its unsent backlog has not shrunk for ``write_s``."""
            backlog = self.transport.get_write_buffer_size()
            if not backlog:
                self._stalled_since = None
            elif self._stalled_since is None or backlog < self._stalled_backlog:
                self._stalled_since, self._stalled_backlog = now, backlog
            elif now - self._stalled_since >= write_s:
                log.debug(
                    "aborting a connection from %s: %d bytes unsent for %g s",
                    self._key,
                    backlog,
                    write_s,
                )
                connections.closed["write_timeout"] += 1
                self._stalled_since = None
                self.transport.abort()

        def _arm_read_deadline(self) -> None:
            if self._read_deadline is None:
                self._read_deadline = self.loop.call_later(read_timeout_s, self._read_too_slow)

        def _cancel_read_deadline(self) -> None:
            if self._read_deadline is not None:
                self._read_deadline.cancel()
                self._read_deadline = None

        def _read_too_slow(self) -> None:
            self._read_deadline = None
            if self.transport.is_closing():
                return
            log.debug(
                "closing a connection from %s: no whole request within %g s",
                self.client[0] if self.client else "?",
                read_timeout_s,
            )
            connections.closed["read_timeout"] += 1
            if self.conn.their_state is h11.IDLE and self.conn.our_state is h11.IDLE:
                self.transport.write(_TIMEOUT_RESPONSE)  # nothing was answered on it yet
            self.transport.close()

    return GuardedH11Protocol


def server_config(app: Any, settings: ServiceSettings, **options: Any) -> uvicorn.Config:
    """The uvicorn configuration for ``app`` with the limits of ``settings`` (see the module
    docstring); ``options`` (log level, access log, ...) are passed on. The connection table
    is left in ``app.state.http_connections`` (``/metrics`` reads it)."""
    table = ConnectionTable(
        settings.http_max_connections,
        settings.http_max_connections_per_client,
        is_exempt=trusted(settings.trusted_proxies),
    )
    state = getattr(app, "state", None)
    if state is not None:
        state.http_connections = table
    return uvicorn.Config(
        app,
        http=guarded_h11(settings.http_request_timeout_s, settings.http_write_timeout_s, table),
        ws="none",  # no WebSocket routes; an upgraded connection would leave the table
        h11_max_incomplete_event_size=settings.http_max_header_bytes,
        timeout_keep_alive=settings.http_keep_alive_s,
        limit_concurrency=None,  # the table caps connections (one request at a time each)
        proxy_headers=False,
        **options,
    )


class Server(uvicorn.Server):
    """uvicorn's server, calling ``before_shutdown`` (ending the live streams:
    :func:`api.live.end_streams`) as it starts shutting down, since it waits for every response
    to complete before it stops."""

    def __init__(
        self, config: uvicorn.Config, before_shutdown: Callable[[], None] | None = None
    ) -> None:
        super().__init__(config)
        self.before_shutdown = before_shutdown

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        if self.before_shutdown is not None:
            try:
                self.before_shutdown()
            except Exception:  # shutting down all the same
                log.exception("before shutdown")
        await super().shutdown(sockets=sockets)
