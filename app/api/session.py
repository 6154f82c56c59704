"""Sign-in for API clients (scripts, the bots): the same login session as the pages.

JSON only: a cross-site HTML form cannot send ``application/json``, so this route needs no CSRF
token of its own; the response hands the client the login's CSRF token for later requests. Like
the sign-in page (app.web.auth), it counts the attempt and reads the account in a short write
transaction of its own, checks the password with no transaction open, and records the outcome and
the login in the request's write transaction.
"""

from __future__ import annotations

from datetime import timedelta

from fastapi import Request, Response
from pydantic import BaseModel, Field

from app.api.schemas import RequestBody
from app.deps import (
    SESSION_COOKIE,
    CurrentLogin,
    DatabaseDep,
    OneHopRouter,
    SessionDep,
    SettingsDep,
    set_session_cookie,
)
from app.errors import InvalidInput, NotAuthenticated, PermissionDenied
from app.services.staff import users

router = OneHopRouter(prefix="/session", tags=["session"])


class Credentials(RequestBody):
    """A username and password."""

    username: str = Field(max_length=200)
    password: str = Field(max_length=1024)


class SignedIn(BaseModel):
    """Who is signed in, and the token to send as ``X-CSRF-Token`` with unsafe requests."""

    username: str
    role: str
    csrf_token: str


@router.post("")
def sign_in(
    body: Credentials,
    request: Request,
    response: Response,
    db: SessionDep,
    database: DatabaseDep,
    settings: SettingsDep,
) -> SignedIn:
    """Sign in; sets the session cookie."""
    if not request.headers.get("content-type", "").startswith("application/json"):
        raise InvalidInput("send the credentials as application/json")
    address = request.client.host if request.client else ""
    with database.writing() as counting:
        check = users.begin_password_check(counting, username=body.username, client_address=address)
    new_login = users.finish_sign_in(
        db,
        check=check,
        password=body.password,
        lifetime=timedelta(hours=settings.session_hours),
        user_agent=request.headers.get("user-agent", ""),
        client_address=address,
    )
    if new_login is users.Refusal.DISABLED:
        raise PermissionDenied("this account is disabled; an admin can enable it again")
    if isinstance(new_login, users.Refusal):
        raise NotAuthenticated("invalid username or password")
    set_session_cookie(response, request, settings, new_login.token)
    user = new_login.session.user
    return SignedIn(username=user.username, role=user.role, csrf_token=new_login.session.csrf_token)


@router.get("")
def whoami(login: CurrentLogin) -> SignedIn:
    """The signed-in user and the login's CSRF token."""
    return SignedIn(username=login.user.username, role=login.user.role, csrf_token=login.csrf_token)


@router.delete("", status_code=204)
def sign_out(login: CurrentLogin, db: SessionDep, response: Response) -> Response:
    """End the login session."""
    users.sign_out(db, login=login)
    response.delete_cookie(SESSION_COOKIE)
    response.status_code = 204
    return response
