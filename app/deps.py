"""Request dependencies as ``Annotated`` aliases: the database session and who is asking.

One transaction per request: ``SessionDep`` is a read session for safe methods (GET, HEAD,
OPTIONS) and a write session otherwise, so a handler never has to choose. Every unsafe request
authenticated by the login cookie must carry the login's CSRF token (form field ``csrf_token`` or
header ``X-CSRF-Token``); that check lives in :func:`current_login`, which every signed-in route
depends on, so no route can forget it.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from datetime import timedelta
from typing import Annotated

from fastapi import Depends, Request, Response
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

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


def set_session_cookie(
    response: Response, request: Request, settings: Settings, token: str
) -> None:
    """Give the browser its login cookie: HttpOnly, SameSite=Lax, Secure over HTTPS."""
    secure = settings.cookie_secure
    if secure is None:
        secure = request.url.scheme == "https"
    response.set_cookie(
        SESSION_COOKIE,
        token,
        httponly=True,
        samesite="lax",
        secure=secure,
        max_age=int(settings.session_hours * 3600),
    )


async def get_settings(request: Request) -> Settings:
    """The application's settings."""
    settings: Settings = request.app.state.settings
    return settings


async def get_database(request: Request) -> Database:
    """The application's database."""
    database: Database = request.app.state.database
    return database


SettingsDep = Annotated[Settings, Depends(get_settings)]
DatabaseDep = Annotated[Database, Depends(get_database)]


async def request_session(request: Request, database: DatabaseDep) -> AsyncIterator[Session]:
    """The request's session: it reads for safe methods and may write otherwise.

    FastAPI runs each sync dependency and the handler in separate thread-pool hops, and a request
    keeps its connection (and on SQLite, once it writes, the write lock) between hops. Unbounded,
    requests holding connections or the lock would wait for threads that all wait for connections
    or the lock. So requests first queue, as coroutines outside the thread pool, for admission:
    fewer requests than the pool has connections and threads, so an admitted request always finds
    both, and SQLite's writers queue fairly on the writer lock (app.db).
    """
    writes = request.method not in SAFE_METHODS
    async with database.admission():
        session = database.write_session() if writes else database.read_session()
        try:
            yield session
        finally:
            await run_in_threadpool(session.close)


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


@dataclass(frozen=True)
class Viewer:
    """Who is looking at a page, as plain values: pages (and error pages rendered after a
    rollback, when ORM objects can no longer load) show these, never a live ORM object."""

    username: str
    role: str
    csrf_token: str


def current_login(
    request: Request,
    db: SessionDep,
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
    request.app.state.activity.note_login(login.id)
    request.state.viewer = Viewer(login.user.username, login.user.role, login.csrf_token)
    return login


CurrentLogin = Annotated[LoginSession, Depends(current_login)]


async def streaming_user(request: Request) -> User:
    """The signed-in user, for long-lived streams: checked in a short session of its own.

    A stream must not hold a request session (and its admission slot) for hours, so it cannot
    depend on :data:`SessionDep`; it needs no CSRF check because streams are GETs.
    """
    database: Database = request.app.state.database
    settings: Settings = request.app.state.settings
    token = request.cookies.get(SESSION_COOKIE)

    def resolve() -> User | None:
        if not token:
            return None
        with database.read_session() as db:
            login = users.resolve_login(
                db, token=token, idle_timeout=timedelta(minutes=settings.idle_minutes)
            )
            return login.user if login else None

    async with database.admission():
        user = await run_in_threadpool(resolve)
    if user is None:
        raise NotAuthenticated("sign in first")
    return user


StreamingUser = Annotated[User, Depends(streaming_user)]


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


def bearer_key(request: Request) -> str:
    """The key of an ``Authorization: Bearer …`` header ('' when absent)."""
    scheme, _, key = request.headers.get("authorization", "").partition(" ")
    return key.strip() if scheme.lower() == "bearer" else ""


AdminUser = Annotated[User, Depends(require(Role.ADMIN))]
ExperimenterUser = Annotated[User, Depends(require(Role.EXPERIMENTER))]
AnalystUser = Annotated[User, Depends(require(Role.ANALYST))]


async def form_fields(request: Request) -> dict[str, str]:
    """A posted form's text fields (for forms whose field names depend on the protocol)."""
    form = await request.form()
    return {key: value for key, value in form.multi_items() if isinstance(value, str)}


FormFields = Annotated[dict[str, str], Depends(form_fields)]
