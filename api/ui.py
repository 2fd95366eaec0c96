"""The operator view's page: ``GET /`` and ``GET /ui`` (HTML), ``/ui/app.js``, ``/ui/style.css``.

Plain files shipped as package data (``api/static/``): no build step, no CDN, no library. The
page needs no token to load; it asks for one once, keeps it in the tab's ``sessionStorage`` and
sends it in the ``Authorization`` header of the stream it opens (:mod:`api.live`), never in a
URL. Every answer carries a Content-Security-Policy that lets the page load only its own script
and style and talk only to its own origin (an injected script could not send the token
elsewhere), and may not be framed.
"""

from __future__ import annotations

from functools import cache
from importlib import resources

from fastapi import APIRouter, HTTPException, Response, status

SECURITY_HEADERS = {
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; "
        "img-src 'self' data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    ),
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}
ASSETS = {
    "index.html": "text/html; charset=utf-8",
    "app.js": "text/javascript; charset=utf-8",
    "style.css": "text/css; charset=utf-8",
}

ui = APIRouter(include_in_schema=False)


@cache
def asset(name: str) -> bytes:
    """The bytes of ``api/static/NAME`` (read once)."""
    return (resources.files("api") / "static" / name).read_bytes()


def _answer(name: str) -> Response:
    return Response(asset(name), media_type=ASSETS[name], headers=SECURITY_HEADERS)


@ui.get("/")
@ui.get("/ui")
def page() -> Response:
    """The operator view."""
    return _answer("index.html")


@ui.get("/ui/{name}")
def static_file(name: str) -> Response:
    """The page's script and style sheet (nothing else is served from here)."""
    if name not in ASSETS or name == "index.html":
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail="Not Found")
    return _answer(name)
