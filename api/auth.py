"""Bearer-token authentication for every ``/v1`` route (constant-time comparison)."""

from __future__ import annotations

import hmac

from fastapi import HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

_bearer = HTTPBearer(auto_error=False, description="TUPA_API_TOKEN")


def token_matches(provided: str, expected: str) -> bool:
    """True when both tokens are equal; the time taken does not depend on where they differ."""
    return hmac.compare_digest(provided.encode(), expected.encode())


async def require_token(request: Request) -> None:
    """FastAPI dependency: 401 unless ``Authorization: Bearer <token>`` matches the service's.

    A service started with ``--insecure`` and no token accepts every request.
    """
    expected: str | None = request.app.state.api_token
    if expected is None:
        return
    credentials: HTTPAuthorizationCredentials | None = await _bearer(request)
    if credentials is None or not token_matches(credentials.credentials, expected):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            detail="authorization: a valid 'Bearer <token>' header is required",
            headers={"WWW-Authenticate": "Bearer"},
        )
