"""The FastAPI application: routers, auth, header-count and body-size limits, rate limit,
proxy headers (from trusted proxies only), metrics, and the service's lifespan.

``create_app(settings)`` builds the app; its lifespan opens the placement service (policy loaded
and checked, MAVLink link started) before the first request and stops it cleanly afterwards.
Tests pass ``service_factory`` to start the service against a mock autopilot of their own.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from prometheus_client import CollectorRegistry
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from api.auth import BearerGuard
from api.live import end_streams, live
from api.metrics import ConnectionCollector, HttpMetrics, HttpMetricsMiddleware, ServiceCollector
from api.ratelimit import RateLimit
from api.responses import send_error
from api.routes import RATE_LIMITED, probes, v1
from api.ui import ui
from service.opening import open_service
from service.placement import PlacementService
from service.settings import ServiceSettings

DESCRIPTION = """\
Traffic-aware UAV placement. A network controller POSTs per-user traffic reports; the service's
policy decides where the flying access point should be and streams that target over MAVLink to
the autopilot. Every `/v1` route needs `Authorization: Bearer <TUPA_API_TOKEN>`.
"""


class BodySizeLimit:
    """Pure ASGI middleware: 413 for a request body over ``max_bytes``, declared
    (``Content-Length``: before the route reads any of it) or streamed (chunked: as soon as
    what was read passes the limit), with ``Connection: close`` (the rest is not read)."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    too_big = int(value) > self.max_bytes
                except ValueError:
                    too_big = True
                if too_big:
                    await send_error(send, 413, self._detail(), [(b"connection", b"close")])
                    return
        received = 0
        started = False

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    # An HTTPException, so that FastAPI's body parsing passes it on (it turns
                    # any other exception into 400) to the app's handler: 413.
                    raise _BodyTooLargeError(self._detail())
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _BodyTooLargeError as exc:  # raised where no handler caught it
            if started:
                raise
            await send_error(send, 413, exc.detail, [(b"connection", b"close")])

    def _detail(self) -> str:
        return f"body: over the {self.max_bytes}-byte limit"


class _BodyTooLargeError(StarletteHTTPException):
    def __init__(self, detail: str) -> None:
        super().__init__(413, detail, headers={"Connection": "close"})


class HeaderLimit:
    """Pure ASGI middleware: 431 for a request with more than ``max_headers`` header lines,
    before anything else looks at them. (Their total size is bounded by the server:
    :mod:`api.server`.)"""

    def __init__(self, app: ASGIApp, max_headers: int) -> None:
        self.app = app
        self.max_headers = max_headers

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and len(scope.get("headers", ())) > self.max_headers:
            await send_error(
                send,
                431,
                f"headers: more than {self.max_headers} header lines",
                [(b"connection", b"close")],
            )
            return
        await self.app(scope, receive, send)


async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """422 naming each bad field: ``loc``, ``msg`` and ``type`` only (the offending input is
    not echoed: it may be a NaN that JSON cannot carry, or something large)."""
    errors = [
        {"loc": list(err.get("loc", ())), "msg": str(err.get("msg", "")), "type": err.get("type")}
        for err in exc.errors()
    ]
    return JSONResponse({"detail": errors}, status_code=422)


_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
    """Starlette's own answer, except that a 405's ``Allow`` lists every method the path has
    (each method is its own route, and Starlette names only the first route's)."""
    if exc.status_code != 405:
        return await http_exception_handler(request, exc)
    methods = [
        method
        for method in _METHODS
        if any(
            route.matches({**request.scope, "method": method})[0] == Match.FULL
            for route in request.app.routes
        )
    ]
    return JSONResponse(
        {"detail": exc.detail},
        status_code=405,
        headers={**(exc.headers or {}), "Allow": ", ".join(methods)},
    )


def create_app(
    settings: ServiceSettings,
    service_factory: Callable[[ServiceSettings], PlacementService] | None = None,
) -> FastAPI:
    """The app for ``settings``; ``ValueError`` if it may not start (no token, not insecure)."""
    settings.check_startable()
    factory = service_factory or open_service

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service = factory(settings).start()
        app.state.service = service
        try:
            yield
        finally:
            app.state.service = None
            service.stop()

    app = FastAPI(
        title="TUPA placement service",
        version="1",
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    token = settings.api_token.get_secret_value() if settings.api_token else ""
    app.state.api_token = token or None
    app.add_exception_handler(RequestValidationError, validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, http_error)  # type: ignore[arg-type]
    app.state.service = None
    registry = CollectorRegistry()
    registry.register(ServiceCollector(lambda: app.state.service))
    app.state.http_connections = None  # the server's connection table (api.server), once served
    registry.register(ConnectionCollector(lambda: app.state.http_connections))
    app.state.registry = registry
    http_metrics = HttpMetrics(registry)
    # Middlewares, outermost last: header count, proxy headers (only from trusted proxies),
    # rate limit, body size, metrics, token, then the routes.
    app.add_middleware(BearerGuard, token=app.state.api_token)
    app.add_middleware(HttpMetricsMiddleware, metrics=http_metrics)
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_body_bytes)
    if settings.rate_limit_rps > 0:  # a flood is turned away before anything else runs
        app.add_middleware(
            RateLimit,
            rate_per_s=settings.rate_limit_rps,
            burst=settings.rate_limit_burst,
            on_reject=http_metrics.rate_limited.inc,
            token=app.state.api_token,
        )
    if settings.trusted_proxies:  # outside the limit: it counts the client the proxy names
        from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=list(settings.trusted_proxies))
    app.add_middleware(HeaderLimit, max_headers=settings.http_max_headers)
    app.include_router(v1, responses=RATE_LIMITED)
    app.include_router(live, responses=RATE_LIMITED)
    app.include_router(probes)
    app.include_router(ui)  # the operator view's page (no token: its data comes from /v1)
    return app


def run(settings: ServiceSettings, **uvicorn_options: Any) -> None:
    """Serve ``settings`` with uvicorn (and the limits of :mod:`api.server`) until interrupted."""
    from api.server import Server, server_config

    app = create_app(settings)
    config = server_config(app, settings, host=settings.host, port=settings.port, **uvicorn_options)
    Server(config, before_shutdown=lambda: end_streams(app)).run()
