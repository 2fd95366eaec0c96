"""Bearer-token authentication for every ``/v1`` route (constant-time comparison)."""

from __future__ import annotations

import hmac
import logging

from fastapi import HTTPException, Request, Security, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.types import ASGIApp, Receive, Scope, Send

from api.responses import send_error

log = logging.getLogger(__name__)
_bearer = HTTPBearer(auto_error=False, description="TUPA_API_TOKEN")
UNAUTHORIZED = "authorization: a valid 'Bearer <token>' header is required"


def token_matches(provided: str, expected: str) -> bool:
    """True when both tokens are equal; the time taken does not depend on where they differ."""
    return hmac.compare_digest(provided.encode(), expected.encode())


async def require_token(
    request: Request,
    credentials: HTTPAuthorizationCredentials | None = Security(_bearer),  # noqa: B008
) -> None:
    """FastAPI dependency: 401 unless ``Authorization: Bearer <token>`` matches the service's.

    A service started with ``--insecure`` and no token accepts every request. (``Security``
    declares the bearer scheme in the OpenAPI document.)
    """
    expected: str | None = request.app.state.api_token
    if expected is None:
        return
    if credentials is None or not token_matches(credentials.credentials, expected):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            detail=UNAUTHORIZED,
            headers={"WWW-Authenticate": "Bearer"},
        )


class BearerGuard:
    """Pure ASGI middleware: the same check for every path under ``prefix``, before routing and
    before the body is read, so that a request without the token learns nothing (not whether
    its body parses, nor which routes exist) and costs nothing but this comparison. The route
    dependency :func:`require_token` stays: it declares the scheme in the OpenAPI document."""

    def __init__(self, app: ASGIApp, token: str | None, prefix: str = "/v1") -> None:
        self.app = app
        self.token = token
        self.prefix = prefix

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if (
            scope["type"] != "http"
            or self.token is None
            or not (path == self.prefix or path.startswith(self.prefix + "/"))
            or is_authenticated(scope, self.token)
        ):
            await self.app(scope, receive, send)
            return
        client = scope.get("client")
        log.debug(  # what was sent is never logged: it may be the token with a typo
            "401 for %s %s from %s", scope.get("method"), path, client[0] if client else "?"
        )
        await send_error(send, 401, UNAUTHORIZED, [(b"www-authenticate", b"Bearer")])


_AUTHENTICATED = "tupa.authenticated"


def is_authenticated(scope: Scope, expected: str) -> bool:
    """:func:`bearer_token_matches`, computed once per request (the rate limit and the guard
    both ask; the answer is kept in the request's scope)."""
    known = scope.get(_AUTHENTICATED)
    if known is None:
        known = scope[_AUTHENTICATED] = bearer_token_matches(scope, expected)
    return bool(known)


def bearer_token_matches(scope: Scope, expected: str) -> bool:
    """True when the request's ``Authorization: Bearer <token>`` header carries ``expected``."""
    for name, value in scope.get("headers", []):
        if name == b"authorization":
            scheme, _, credentials = value.decode("latin-1").partition(" ")
            return scheme.lower() == "bearer" and token_matches(credentials.strip(), expected)
    return False
