"""Sign-in and sign-out pages.

The sign-in form is protected against cross-site posts by a signed double-submit token: the page
sets a random nonce cookie and embeds the nonce's HMAC in the form; a post is accepted only when
the two match. After sign-in, forms use the login's own CSRF token (see app.deps). A sign-in first
counts the attempt and reads the account in a short write transaction of its own
(app.services.staff.login_throttle: so that no more attempts than the limit are ever checked),
checks the password (Argon2id, slow by design) with no transaction open, and then records the
outcome and the new login in the request's write transaction, so it never holds SQLite's write lock
while hashing.
"""

from __future__ import annotations

from datetime import timedelta
from typing import Annotated

from fastapi import Form, Request
from fastapi.responses import RedirectResponse, Response

from app.deps import (
    SESSION_COOKIE,
    CurrentLogin,
    DatabaseDep,
    OneHopRouter,
    SessionDep,
    SettingsDep,
    set_private_cookie,
    set_session_cookie,
)
from app.errors import TooManyAttempts
from app.security import new_token, same, sign, unsign
from app.services.staff import users
from app.web.templating import render

router = OneHopRouter(tags=["pages"], include_in_schema=False)

LOGIN_NONCE_COOKIE = "tl_login_nonce"
INVALID_CREDENTIALS = "Invalid username or password."
ACCOUNT_DISABLED = "This account is disabled; an admin can enable it again."
"""Shown only to whoever gave the right password: nobody else learns that the account exists."""


def _safe_next(target: str | None) -> str:
    """Only same-site paths may follow sign-in (no open redirects)."""
    if target and target.startswith("/") and not target.startswith("//") and "\\" not in target:
        return target
    return "/"


def _login_page(
    request: Request, *, next_url: str, error: str = "", username: str = "", status_code: int = 200
) -> Response:
    nonce = new_token(16)
    response = render(
        request,
        "login.html",
        {
            "login_token": sign(request.app.state.settings.secret, nonce),
            "next_url": next_url,
            "error": error,
            "username": username,
        },
        status_code=status_code,
    )
    set_private_cookie(
        response, request, LOGIN_NONCE_COOKIE, nonce, max_age=3600, samesite="strict"
    )
    return response


@router.get("/login")
def login_form(request: Request, next: str = "/") -> Response:
    """The sign-in page."""
    return _login_page(request, next_url=_safe_next(next))


@router.post("/login")
def login(
    request: Request,
    db: SessionDep,
    database: DatabaseDep,
    settings: SettingsDep,
    username: Annotated[str, Form(max_length=200)] = "",
    password: Annotated[str, Form(max_length=1024)] = "",
    csrf_token: Annotated[str, Form(max_length=200)] = "",
    next: Annotated[str, Form(max_length=2000)] = "/",
) -> Response:
    """Check the credentials and start a login session."""
    next_url = _safe_next(next)
    nonce = request.cookies.get(LOGIN_NONCE_COOKIE, "")
    signed_nonce = unsign(settings.secret, csrf_token) if csrf_token else None
    if not nonce or signed_nonce is None or not same(signed_nonce, nonce):
        return _login_page(
            request,
            next_url=next_url,
            username=username,
            error="The form expired or did not come from this site; please sign in again.",
            status_code=403,
        )
    address = request.client.host if request.client else ""
    try:
        with database.writing() as counting:
            check = users.begin_password_check(counting, username=username, client_address=address)
    except TooManyAttempts as exc:
        return _login_page(
            request, next_url=next_url, username=username, error=exc.message, status_code=429
        )
    new_login = users.finish_sign_in(
        db,
        check=check,
        password=password,
        lifetime=timedelta(hours=settings.session_hours),
        user_agent=request.headers.get("user-agent", ""),
        client_address=address,
    )
    if isinstance(new_login, users.Refusal):
        return _login_page(
            request,
            next_url=next_url,
            username=username,
            error=ACCOUNT_DISABLED if new_login is users.Refusal.DISABLED else INVALID_CREDENTIALS,
            status_code=403 if new_login is users.Refusal.DISABLED else 401,
        )
    response = RedirectResponse(next_url, status_code=303)
    set_session_cookie(response, request, settings, new_login.token)
    response.delete_cookie(LOGIN_NONCE_COOKIE)
    return response


@router.post("/logout")
def logout(login: CurrentLogin, db: SessionDep) -> Response:
    """End the login session."""
    users.sign_out(db, login=login)
    response = RedirectResponse("/login", status_code=303)
    response.delete_cookie(SESSION_COOKIE)
    return response
