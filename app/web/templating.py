"""Rendering pages and htmx fragments from one set of templates.

A page template names its swappable regions as Jinja blocks. A normal request gets the whole page;
an htmx request (``HX-Request`` header) for a route that names a block gets just that block, and
every such response carries ``Vary: HX-Request`` so caches keep the two apart.
"""

from __future__ import annotations

import base64
import binascii
import math
import time
from datetime import datetime
from typing import Any
from urllib.parse import quote

from fastapi import Request
from fastapi.responses import HTMLResponse, RedirectResponse
from jinja2 import Environment, FileSystemLoader, StrictUndefined, pass_context, select_autoescape
from jinja2.runtime import Context
from markupsafe import Markup

from app.deps import CSRF_FIELD, CSRF_HEADER, READS_SINCE, set_private_cookie
from app.i18n.catalogues import SOURCE_LANGUAGE, Catalogue, catalogue, ui_languages
from app.inputs import STATION_NAME
from app.security import sign, unsign
from app.settings import REPO_ROOT
from app.web.assets import asset

NOTICE_COOKIE = "tl_notice"
LANGUAGE_COOKIE = "tl_lang"
"""The language of the last participant page this browser showed, so that an error page (which
cannot know whose tablet it is on) speaks it too."""

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
    extensions=["jinja2.ext.i18n"],
)
# Staff pages are in English: their marked words pass through. Participant pages get their
# language's catalogue per request (:func:`_language_context`).
environment.install_null_translations(newstyle=True)  # type: ignore[attr-defined]


def _when(value: datetime | None) -> str:
    return value.strftime("%Y-%m-%d %H:%M UTC") if value else "—"


environment.filters["when"] = _when
environment.globals["asset"] = asset
environment.globals["station_name_rule"] = STATION_NAME.sentence


def _language_context(catalogue: Catalogue) -> dict[str, Any]:
    """What a page needs to speak the participant's language: ``gettext``/``ngettext`` (with
    Jinja's "newstyle" rules: values filled in with ``%``, escaped when the page autoescapes),
    the ``lang`` and ``dir`` of its ``<html>``, and the room scripts' message table."""

    @pass_context
    def gettext(context: Context, text: str, /, **values: Any) -> str:
        translated = catalogue.gettext(text)
        if context.eval_ctx.autoescape:
            translated = Markup(translated)
        return translated % values

    @pass_context
    def ngettext(
        context: Context, singular: str, plural: str, number: int, /, **values: Any
    ) -> str:
        values.setdefault("num", number)
        translated = catalogue.ngettext(singular, plural, number)
        if context.eval_ctx.autoescape:
            translated = Markup(translated)
        return translated % values

    return {
        "gettext": gettext,
        "_": gettext,
        "ngettext": ngettext,
        "lang": catalogue.language,
        "dir": catalogue.direction,
    }


def tablet_catalogue(request: Request) -> Catalogue:
    """The interface words of the language this browser last showed a participant page in."""
    code = request.cookies.get(LANGUAGE_COOKIE, "")
    return catalogue(code if code in ui_languages() else SOURCE_LANGUAGE)


def is_htmx(request: Request) -> bool:
    """Whether htmx sent this request (and so wants a fragment)."""
    return request.headers.get("HX-Request") == "true"


def _base_context(request: Request) -> dict[str, Any]:
    viewer = getattr(request.state, "viewer", None)
    # A live page's streams send at once what changed since the page began to read
    # (app.web.streams.event_stream); a page that read nothing: since now.
    reads_since = getattr(request.state, READS_SINCE, None) or time.time()
    return {
        "request": request,
        "live_since": f"{math.floor(reads_since * 1000) / 1000:.3f}",  # rounded down
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
    if isinstance(values.get("catalogue"), Catalogue):
        values.update(_language_context(values["catalogue"]))
    if block is not None and is_htmx(request):
        render_block = page.blocks[block]
        html = "".join(render_block(page.new_context(values)))
    else:
        html = page.render(values)
    response = HTMLResponse(html, status_code=status_code)
    response.headers["Vary"] = "HX-Request"
    language = values.get("lang")
    if isinstance(language, str) and request.cookies.get(LANGUAGE_COOKIE) != language:
        set_private_cookie(response, request, LANGUAGE_COOKIE, language, max_age=7 * 86400)
    if status_code >= 400:
        refusal = next((v for k in REFUSAL_KEYS if isinstance(v := values.get(k), str) and v), "")
        if refusal:
            response.headers[REFUSAL_HEADER] = quote(refusal, safe=" ")
    if NOTICE_COOKIE in request.cookies:
        response.delete_cookie(NOTICE_COOKIE)
    return response
