"""Request dependencies as ``Annotated`` aliases: the database session and who is asking.

One transaction per request: ``SessionDep`` is a read session for safe methods (GET, HEAD,
OPTIONS) and a write session otherwise, so a handler never has to choose. Every unsafe request
authenticated by the login cookie must carry the login's CSRF token (form field ``csrf_token`` or
header ``X-CSRF-Token``); that check lives in :func:`current_login`, which every signed-in route
depends on, so no route can forget it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from datetime import timedelta
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from app.db import Database
from app.errors import NotAuthenticated, PermissionDenied
from app.security import same
from app.services import users
from app.settings import Settings
from app.tables import LoginSession, Role, User

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
SESSION_COOKIE = "tl_session"
CSRF_HEADER = "X-CSRF-Token"
CSRF_FIELD = "csrf_token"


def get_settings(request: Request) -> Settings:
    """The application's settings."""
    settings: Settings = request.app.state.settings
    return settings


def get_database(request: Request) -> Database:
    """The application's database."""
    database: Database = request.app.state.database
    return database


SettingsDep = Annotated[Settings, Depends(get_settings)]
DatabaseDep = Annotated[Database, Depends(get_database)]


def request_session(request: Request, database: DatabaseDep) -> Iterator[Session]:
    """The request's session: it reads for safe methods and may write otherwise."""
    writes = request.method not in SAFE_METHODS
    with database.write_session() if writes else database.read_session() as session:
        yield session


SessionDep = Annotated[Session, Depends(request_session)]


async def submitted_csrf_token(request: Request) -> str | None:
    """The CSRF token an unsafe request carries, from its header or its form."""
    if request.method in SAFE_METHODS:
        return None
    header = request.headers.get(CSRF_HEADER)
    if header:
        return header
    content_type = request.headers.get("content-type", "")
    if content_type.startswith(("application/x-www-form-urlencoded", "multipart/form-data")):
        value = (await request.form()).get(CSRF_FIELD)
        return value if isinstance(value, str) else None
    return None


def current_login(
    request: Request,
    db: SessionDep,
    database: DatabaseDep,
    settings: SettingsDep,
    csrf_token: Annotated[str | None, Depends(submitted_csrf_token)],
) -> LoginSession:
    """The signed-in browser's login session; 401 without one, 403 on a missing CSRF token."""
    token = request.cookies.get(SESSION_COOKIE)
    login = (
        users.resolve_login(db, token=token, idle_timeout=timedelta(minutes=settings.idle_minutes))
        if token
        else None
    )
    if login is None:
        raise NotAuthenticated("sign in first")
    if request.method not in SAFE_METHODS and (
        csrf_token is None or not same(csrf_token, login.csrf_token)
    ):
        raise PermissionDenied(
            "missing or wrong CSRF token: reload the page and try again "
            f"(API clients send the {CSRF_HEADER} header)"
        )
    if users.login_needs_touch(login):
        with database.write_session() as writer:
            users.touch_login(writer, login_id=login.id)
    request.state.login = login
    return login


CurrentLogin = Annotated[LoginSession, Depends(current_login)]


def current_user(login: CurrentLogin) -> User:
    """The signed-in user."""
    return login.user


CurrentUser = Annotated[User, Depends(current_user)]


def require(*roles: Role) -> Callable[[User], User]:
    """A dependency admitting the given roles (admins are always admitted)."""
    allowed = frozenset((*roles, Role.ADMIN))

    def dependency(user: CurrentUser) -> User:
        if Role(user.role) not in allowed:
            names = " or ".join(sorted(r.value for r in allowed))
            raise PermissionDenied(f"this needs the {names} role; you are {user.role}")
        return user

    return dependency


AdminUser = Annotated[User, Depends(require(Role.ADMIN))]
ExperimenterUser = Annotated[User, Depends(require(Role.EXPERIMENTER))]
AnalystUser = Annotated[User, Depends(require(Role.ANALYST))]


async def form_fields(request: Request) -> dict[str, str]:
    """A posted form's text fields (for forms whose field names depend on the protocol)."""
    form = await request.form()
    return {key: value for key, value in form.multi_items() if isinstance(value, str)}


FormFields = Annotated[dict[str, str], Depends(form_fields)]
