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
* keep-alive connections closed after ``http_keep_alive_s`` idle, and at most
  ``http_max_connections`` connections or requests at once (503 beyond, at once);
* no proxy headers from uvicorn: the app honours ``X-Forwarded-For`` only from
  ``trusted_proxies`` (:func:`api.app.create_app`).

Long-lived responses (the operator view's streams, :mod:`api.live`) and these limits: the read
deadline ends once a request is in (a stream's ``GET`` has no body), and the keep-alive timeout
applies only between requests, so neither cuts an open stream. Each stream holds one of the
``http_max_connections`` for as long as it is open: the app caps streams at
``live_max_streams`` (503 beyond), well below it, so that the network controller always finds a
place. uvicorn waits at shutdown until every response is complete, which a stream never is:
:class:`Server` ends the streams first.
"""

from __future__ import annotations

import asyncio
import logging
import socket
from collections.abc import Callable
from typing import Any

import h11
import uvicorn
from uvicorn.protocols.http.h11_impl import H11Protocol

from service.settings import ServiceSettings

log = logging.getLogger(__name__)

_TIMEOUT_RESPONSE = (
    b"HTTP/1.1 408 Request Timeout\r\ncontent-type: text/plain; charset=utf-8\r\n"
    b"connection: close\r\ncontent-length: 16\r\n\r\nrequest timeout\n"
)


def guarded_h11(read_timeout_s: float) -> type[H11Protocol]:
    """uvicorn's h11 protocol, closing a connection that takes longer than ``read_timeout_s`` to
    send a whole request.

    The deadline starts when the connection opens (a client that never sends anything), and
    again at the first byte of each later request (between requests uvicorn's keep-alive timeout
    applies); it ends once the request, body included, has been received: from then on the
    time is the application's. A client still sending at the deadline (slowly, stalled, or with
    a body shorter than its ``Content-Length``) gets ``408`` when nothing was answered yet, and
    the connection is closed.
    """

    class GuardedH11Protocol(H11Protocol):
        _read_deadline: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
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

        def connection_lost(self, exc: Exception | None) -> None:
            self._cancel_read_deadline()
            super().connection_lost(exc)

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
            if self.conn.their_state is h11.IDLE and self.conn.our_state is h11.IDLE:
                self.transport.write(_TIMEOUT_RESPONSE)  # nothing was answered on it yet
            self.transport.close()

    return GuardedH11Protocol


def server_config(app: Any, settings: ServiceSettings, **options: Any) -> uvicorn.Config:
    """The uvicorn configuration for ``app`` with the limits of ``settings`` (see the module
    docstring); ``options`` (log level, access log, ...) are passed on."""
    return uvicorn.Config(
        app,
        http=guarded_h11(settings.http_request_timeout_s),
        h11_max_incomplete_event_size=settings.http_max_header_bytes,
        timeout_keep_alive=settings.http_keep_alive_s,
        limit_concurrency=settings.http_max_connections,
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
