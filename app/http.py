"""Cross-cutting HTTP behaviour: error responses and security headers.

Errors are answered in the caller's language: JSON ``{"detail": "…"}`` under /api and for
devices, an HTML page (or a redirect to sign-in) for browsers. Every response carries a strict
Content-Security-Policy (no inline scripts, no third-party origins), framing and sniffing
protection and a referrer policy; everything but the static files is ``Cache-Control: no-store``,
so a staff page (or a participant's) is never kept by the browser or a proxy, and Back after
signing out asks the server again instead of showing the signed-in page.
"""

from __future__ import annotations

import json
import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse, Response
from sqlalchemy.exc import DataError, OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.errors import DatabaseUnavailable, NotAuthenticated, TrustlabError
from app.i18n import catalogues
from app.tablet import ONLINE_COOKIE
from app.web.templating import is_htmx, render, tablet_catalogue

log = logging.getLogger(__name__)

SECURITY_HEADERS = {
    "content-security-policy": (
        "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; "
        "img-src 'self' data:; connect-src 'self'; font-src 'self'; object-src 'none'; "
        "base-uri 'self'; form-action 'self'; frame-ancestors 'none'"
    ),
    "x-content-type-options": "nosniff",
    "x-frame-options": "DENY",
    "referrer-policy": "same-origin",
    "permissions-policy": "camera=(), microphone=(), geolocation=()",
}


NO_STORE = (b"cache-control", b"no-store")
CACHEABLE_PREFIX = "/static/"
"""The only responses browsers may keep: the vendored libraries, scripts and styles (their caching
is app/web/assets.py's)."""


class SecurityHeaders:
    """Pure ASGI middleware adding :data:`SECURITY_HEADERS` to every HTTP response, and
    ``Cache-Control: no-store`` to every one outside /static/ that sets no caching of its own."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self._headers = [(k.encode(), v.encode()) for k, v in SECURITY_HEADERS.items()]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        cacheable = str(scope.get("path", "")).startswith(CACHEABLE_PREFIX)

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                present = {name.lower() for name, _ in message.get("headers", [])}
                extra = [(k, v) for k, v in self._headers if k not in present]
                if not cacheable and NO_STORE[0] not in present:
                    extra.append(NO_STORE)
                message["headers"] = list(message.get("headers", [])) + extra
            await send(message)

        await self.app(scope, receive, send_with_headers)


class BodyLimit:
    """Refuse request bodies over ``limit`` bytes with a JSON 413, declared length or not."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        message = f"the request body is larger than {self.limit // 1024} KiB"
        for name, value in scope.get("headers", []):
            if name == b"content-length" and value.isdigit() and int(value) > self.limit:
                body = json.dumps({"detail": message}).encode()
                await send(
                    {
                        "type": "http.response.start",
                        "status": 413,
                        "headers": [
                            (b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()),
                        ],
                    }
                )
                await send({"type": "http.response.body", "body": body})
                return
        received = 0

        async def counting_receive() -> Message:
            nonlocal received
            message_ = await receive()
            if message_["type"] == "http.request":
                received += len(message_.get("body", b""))
                if received > self.limit:
                    raise StarletteHTTPException(413, message)
            return message_

        await self.app(scope, counting_receive, send)


def wants_json(request: Request) -> bool:
    """API paths, and clients that ask for JSON rather than HTML, get JSON errors."""
    if request.url.path.startswith("/api/"):
        return True
    accept = request.headers.get("accept", "")
    return "application/json" in accept and "text/html" not in accept


ONLINE_PATHS = ("/join/", "/online")
"""An online participant's own pages (app.online.pages): no tablet, no experimenter."""
TABLET_PATHS = ("/tablet", "/t/", "/k/", *ONLINE_PATHS)
"""Participant pages: their errors are participant pages too (no staff styling or links)."""

TABLET_HEADINGS = {
    401: catalogues.Message("The questionnaire is not open on this tablet"),
    403: catalogues.Message("This page has expired"),
    404: catalogues.Message("This page does not exist"),
    409: catalogues.Message("This cannot be done right now"),
    503: catalogues.Message("Please wait a moment"),
}
TABLET_HEADING_OTHERWISE = catalogues.Message("Something went wrong")


def _error_response(
    request: Request, status: int, message: str, extra: dict[str, object] | None = None
) -> Response:
    if wants_json(request):
        return JSONResponse({"detail": message, **(extra or {})}, status_code=status)
    if request.url.path.startswith(TABLET_PATHS):
        words = tablet_catalogue(request)
        context = {
            "heading": words.say(
                TABLET_HEADINGS.get(status, catalogues.Message("Something went wrong"))
            ),
            # Only a sentence of the catalogue reaches a participant: any other refusal is the
            # server's English for staff (a path, a validation detail), so the heading says it.
            "message": words.say(message) if isinstance(message, catalogues.Message) else "",
            "catalogue": words,
            # no tablet to hand to anyone: the online pages, or an online participant's
            "online": request.url.path.startswith(ONLINE_PATHS) or ONLINE_COOKIE in request.cookies,
        }
        return render(request, "tablet_message.html", context, status_code=status)
    return render(request, "error.html", {"status": status, "message": message}, status_code=status)


def _describe_validation(errors: list[Any]) -> str:
    parts = []
    for error in errors[:5]:
        location = ".".join(str(p) for p in error.get("loc", ()) if p != "body")
        parts.append(f"{location}: {error.get('msg', 'invalid')}" if location else error["msg"])
    more = f" (and {len(errors) - 5} more)" if len(errors) > 5 else ""
    return "; ".join(parts) + more


def refused_value_message(exc: DataError) -> str:
    """One sentence for a value the database cannot store (PostgreSQL's text refuses NUL
    characters; a number can be out of range): the request is refused and nothing is written."""
    reason = str(exc.orig).strip().splitlines()[0] if exc.orig is not None else "invalid value"
    return f"a value in the request cannot be stored: {reason}; nothing was changed"


def install_error_handlers(app: FastAPI) -> None:
    """Map domain, validation, HTTP and database errors to clear responses."""

    @app.exception_handler(TrustlabError)
    async def domain_error(request: Request, exc: TrustlabError) -> Response:
        tablet = request.url.path.startswith(TABLET_PATHS)
        if isinstance(exc, NotAuthenticated) and not wants_json(request) and not tablet:
            target = f"/login?next={request.url.path}"
            if is_htmx(request):
                return Response(status_code=401, headers={"HX-Redirect": target})
            return RedirectResponse(target, status_code=303)
        return _error_response(request, exc.status_code, exc.message, exc.extra)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError) -> Response:
        errors = list(exc.errors())
        message = _describe_validation(errors)
        if wants_json(request):
            detail = [
                {"loc": list(e.get("loc", ())), "msg": e.get("msg", ""), "type": e.get("type", "")}
                for e in errors
            ]
            return JSONResponse({"detail": message, "errors": detail}, status_code=422)
        return _error_response(request, 422, message)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        message = exc.detail if isinstance(exc.detail, str) else "request refused"
        if exc.status_code == 404 and message == "Not Found":
            message = f"nothing at {request.url.path}"
        response = _error_response(request, exc.status_code, message)
        for name, value in (exc.headers or {}).items():
            response.headers[name] = value
        return response

    @app.exception_handler(DataError)
    async def unstorable_value(request: Request, exc: DataError) -> Response:
        return _error_response(request, 422, refused_value_message(exc))

    @app.exception_handler(OperationalError)
    async def database_error(request: Request, exc: OperationalError) -> Response:
        log.warning("database unavailable: %s", exc.orig)
        unavailable = DatabaseUnavailable(
            "the database is unavailable right now; nothing was changed, please retry"
        )
        response = _error_response(request, unavailable.status_code, unavailable.message)
        response.headers["Retry-After"] = "2"
        return response
