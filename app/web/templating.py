"""Rendering pages and htmx fragments from one set of templates.

A page template names its swappable regions as Jinja blocks. A normal request gets the whole page;
an htmx request (``HX-Request`` header) for a route that names a block gets just that block, and
every such response carries ``Vary: HX-Request`` so caches keep the two apart.
"""

from __future__ import annotations

import base64
import binascii
from datetime import datetime
from typing import Any
from urllib.parse import quote

from fastapi import Request
from fastapi.responses import HTMLResponse, RedirectResponse
from jinja2 import Environment, FileSystemLoader, StrictUndefined, select_autoescape

from app.deps import CSRF_FIELD, CSRF_HEADER, set_private_cookie
from app.inputs import STATION_NAME
from app.security import sign, unsign
from app.settings import REPO_ROOT
from app.web.assets import asset

NOTICE_COOKIE = "tl_notice"

REFUSAL_HEADER = "X-Trustlab-Refusal"
"""A refused request's message, percent-encoded UTF-8. htmx does not swap a 4xx/5xx response, so
static/js/refusals.js reads this header and shows the words next to the control that sent the
request: the same words the page shows with JavaScript off."""

REFUSAL_KEYS = ("error", "form_error", "message")
"""The context keys pages put their refusal text under (the first one set is sent)."""

environment = Environment(
    loader=FileSystemLoader(REPO_ROOT / "templates"),
    autoescape=select_autoescape(["html"]),
    undefined=StrictUndefined,
    trim_blocks=True,
    lstrip_blocks=True,
)


def _when(value: datetime | None) -> str:
    return value.strftime("%Y-%m-%d %H:%M UTC") if value else "—"


environment.filters["when"] = _when
environment.globals["asset"] = asset
environment.globals["station_name_rule"] = STATION_NAME.sentence


def is_htmx(request: Request) -> bool:
    """Whether htmx sent this request (and so wants a fragment)."""
    return request.headers.get("HX-Request") == "true"


def _base_context(request: Request) -> dict[str, Any]:
    viewer = getattr(request.state, "viewer", None)
    return {
        "request": request,
        "user": viewer,
        "csrf_token": viewer.csrf_token if viewer else "",
        "csrf_field": CSRF_FIELD,
        "csrf_header": CSRF_HEADER,
        "notice": _read_notice(request),
    }


def _cookie_safe(text: str) -> str:
    """``text`` as URL-safe base64 of its UTF-8: a cookie header carries Latin-1 only, and a
    notice can name a device label or a study title in any script. The padding is left off:
    "=" would make the cookie a quoted string."""
    return base64.urlsafe_b64encode(text.encode()).decode("ascii").rstrip("=")


def _from_cookie_safe(value: str) -> str:
    """The text :func:`_cookie_safe` encoded ("" for anything else)."""
    try:
        padded = value + "=" * (-len(value) % 4)
        return base64.urlsafe_b64decode(padded.encode("ascii")).decode()
    except (binascii.Error, UnicodeError):
        return ""


def _read_notice(request: Request) -> str:
    signed = request.cookies.get(NOTICE_COOKIE)
    if not signed:
        return ""
    value = unsign(request.app.state.settings.secret, signed)
    return _from_cookie_safe(value) if value else ""


def redirect_with_notice(request: Request, url: str, notice: str) -> RedirectResponse:
    """A See-Other redirect that shows ``notice`` once on the next page (a signed cookie)."""
    response = RedirectResponse(url, status_code=303)
    signed = sign(request.app.state.settings.secret, _cookie_safe(notice[:300]))
    set_private_cookie(response, request, NOTICE_COOKIE, signed, max_age=60)
    return response


def render(
    request: Request,
    template: str,
    context: dict[str, Any] | None = None,
    *,
    block: str | None = None,
    status_code: int = 200,
) -> HTMLResponse:
    """The page, or only ``block`` of it when htmx asks."""
    page = environment.get_template(template)
    values = {**_base_context(request), **(context or {})}
    if block is not None and is_htmx(request):
        render_block = page.blocks[block]
        html = "".join(render_block(page.new_context(values)))
    else:
        html = page.render(values)
    response = HTMLResponse(html, status_code=status_code)
    response.headers["Vary"] = "HX-Request"
    if status_code >= 400:
        refusal = next((v for k in REFUSAL_KEYS if isinstance(v := values.get(k), str) and v), "")
        if refusal:
            response.headers[REFUSAL_HEADER] = quote(refusal, safe=" ")
    if NOTICE_COOKIE in request.cookies:
        response.delete_cookie(NOTICE_COOKIE)
    return response
