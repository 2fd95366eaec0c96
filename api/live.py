"""The operator view's data over HTTP: ``GET /v1/live`` (one frame) and ``GET /v1/live/events``
(frames as they are published, as Server-Sent Events).

Both are ``/v1`` routes: they need the bearer token like every other (:class:`api.auth.
BearerGuard`), and the page sends it in the ``Authorization`` header of a ``fetch()`` (the
browser's ``EventSource`` cannot send headers, and a token in a URL would end up in logs and
histories). The stream is plain HTTP/1.1 (``text/event-stream``) through the same middlewares as
any request: the rate limit counts one request per stream, not per frame.

A stream sends ``retry:``, then the current frame at once, then each frame the placement loop
publishes (one per decision period), each as ``id: SEQ`` / ``event: frame`` / ``data: JSON``
(:mod:`service.live_view` describes the JSON), and a ``: keep-alive`` comment after
``KEEPALIVE_S`` without one. What keeps it from hurting the service:

* the placement loop never waits for a stream: it appends to each stream's bounded queue
  (:mod:`service.pubsub`: a reader that falls behind loses its oldest frames);
* at most ``live_max_streams`` streams at once (503 with ``Retry-After`` beyond), each holding
  one of the server's ``http_max_connections``;
* a client that stops reading is cut off once one write has waited ``live_stall_s`` (its
  connection's buffers are full by then), which frees its place;
* at shutdown the server ends every stream first (:class:`api.server.Server`), so that it does
  not wait for them (uvicorn waits for every response to complete).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from typing import Any

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse
from starlette.types import Message, Receive, Scope, Send

from api.auth import require_token
from api.live_schemas import LiveFrameOut
from api.schemas import ErrorOut
from service.live_view import LiveFrame
from service.placement import PlacementService
from service.pubsub import SubscriberLimitError, Subscription

log = logging.getLogger(__name__)

KEEPALIVE_S = 15.0
"""A comment line after this long without a frame: proxies keep the connection, and a client
that vanished without a word is found out by the write."""
RETRY_AFTER_S = 5
"""What a client over the stream limit is told to wait."""
RECONNECT_MS = 2000
"""The SSE ``retry:`` hint (the page keeps its own backoff)."""

live = APIRouter(
    prefix="/v1",
    dependencies=[Depends(require_token)],
    responses={401: {"model": ErrorOut, "description": "Missing or wrong bearer token"}},
)


def sse_event(frame: LiveFrame) -> bytes:
    """One Server-Sent Event carrying ``frame`` (its JSON is one line: no newline inside)."""
    return b"id: %d\nevent: frame\ndata: %s\n\n" % (frame.seq, frame.data)


@live.get(
    "/live",
    response_model=LiveFrameOut,
    summary="What the operator view shows now",
    responses={200: {"content": {"application/json": {}}}},
)
def get_live(request: Request) -> Response:
    """The operator view's current frame: the area and its geofence, the vehicles (position,
    heading, target, track, link, mode, last decision), the users of the latest report and
    how well each is served, the utility and its three parts, and their recent history.
    ``GET /v1/live/events`` streams the same frames (Server-Sent Events, one per decision
    period; not listed here because it never ends)."""
    frame = request.app.state.service.live_frame()
    return Response(
        frame.data, media_type="application/json", headers={"Cache-Control": "no-store"}
    )


@live.get("/live/events", include_in_schema=False)
async def live_events(request: Request) -> Response:
    """The frames as they are published (see the module docstring); 503 over the limit."""
    service: PlacementService = request.app.state.service
    loop = asyncio.get_running_loop()
    wake = asyncio.Event()

    def notify() -> None:  # from the placement loop's thread: must not block
        loop.call_soon_threadsafe(wake.set)

    try:
        subscription = service.live.hub.subscribe(notify)
    except SubscriberLimitError as exc:
        raise HTTPException(
            status.HTTP_503_SERVICE_UNAVAILABLE,
            detail=str(exc),
            headers={"Retry-After": str(RETRY_AFTER_S)},
        ) from None
    try:
        first = await run_in_threadpool(service.live_frame)
    except BaseException:
        subscription.close()
        raise
    return EventStream(
        _events(subscription, wake, first),
        subscription,
        stall_s=service.settings.live_stall_s,
        media_type="text/event-stream",
        headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"},
    )


async def _events(
    subscription: Subscription[LiveFrame], wake: asyncio.Event, first: LiveFrame
) -> AsyncIterator[bytes]:
    try:
        yield b"retry: %d\n" % RECONNECT_MS + sse_event(first)  # one event: hint and frame
        last_seq = first.seq
        while True:
            try:
                await asyncio.wait_for(wake.wait(), KEEPALIVE_S)
            except TimeoutError:
                yield b": keep-alive\n\n"
                continue
            wake.clear()
            if subscription.closed:  # the service is stopping
                return
            for frame in subscription.take():
                if frame.seq > last_seq:  # not older than one already sent
                    last_seq = frame.seq
                    yield sse_event(frame)
    finally:
        subscription.close()


class EventStream(StreamingResponse):
    """A streaming response that closes ``subscription`` however it ends, and gives up on a
    client once one write has waited ``stall_s`` (it stopped reading)."""

    def __init__(
        self,
        content: AsyncIterator[bytes],
        subscription: Subscription[Any],
        stall_s: float,
        **kwargs: Any,
    ) -> None:
        super().__init__(content, **kwargs)
        self.subscription = subscription
        self.stall_s = stall_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.subscription.close()

    async def stream_response(self, send: Send) -> None:
        async def bounded_send(message: Message) -> None:
            await asyncio.wait_for(send(message), self.stall_s)

        try:
            await super().stream_response(bounded_send)
        except TimeoutError:
            # Returning without completing the response makes the server close the connection
            # (uvicorn logs that it was left incomplete).
            log.warning(
                "live stream: the client read nothing for %g s (%d frames dropped); closing it",
                self.stall_s,
                self.subscription.dropped,
            )


def end_streams(app: FastAPI) -> None:
    """End every live stream (the server calls it as it starts shutting down)."""
    service = getattr(app.state, "service", None)
    if service is not None:
        service.live.hub.close_all()
