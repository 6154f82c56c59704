"""Request dependencies as ``Annotated`` aliases, and how a request uses the database.

One transaction per request: ``SessionDep`` is a read session for safe methods (GET, HEAD,
OPTIONS) and a write session otherwise, so a handler never has to choose. Every unsafe request
authenticated by the login cookie must carry the login's CSRF token (form field ``csrf_token`` or
header ``X-CSRF-Token``); that check lives in :func:`current_login`, which every signed-in route
depends on, so no route can forget it.

How a request meets the database, the same way for every route (the robots' routes do the same in
one step, app/api/device_work.py):

1. **Admission** (:func:`request_session`): requests queue as coroutines for one of a bounded
   number of slots, so an admitted request always finds a connection and a thread (app.db).
2. **Who is asking is read first**, in one thread-pool hop, through :func:`identify`: the login
   cookie (:func:`current_login`) or a tablet's token (app.tablet). (A sign-in instead counts its
   attempt in a short write transaction of its own: app.services.staff.login_throttle.) The
   dependencies that check it (CSRF, idle timeout, roles) are coroutines around that one hop, so
   refusals still come before the request body is validated. For a write request that read is a
   transaction of its own, ended before the handler runs: a write session's transaction is, on
   SQLite, the single write lock (``BEGIN IMMEDIATE``), which must not wait through the hop from
   dependencies to handler (on PostgreSQL the same rule keeps no transaction open across it; a
   read request's one read transaction simply continues into its handler). When a login was
   used, its ``last_seen_at`` is written later by the activity recorder (app.activity), so
   reading it writes nothing.
3. **The handler's work is the request's one write transaction**: it begins with the handler's
   first statement and ends with the service's commit (or a rollback). After that the session only
   reads (on SQLite a plain ``BEGIN``, not another turn in the writers' queue), so a response built
   from the committed state, or a page showing a refusal, costs no second write transaction; a
   second write in the same request is a bug and raises :class:`SecondWrite`.
4. **The handler runs in one hop that also ends its transaction** (:class:`OneHopRouter`, the
   router of every page and API module with synchronous handlers): whatever is still open when
   the handler returns or raises — a read, or a write that failed — is rolled back in that same
   hop, so no transaction outlives it, and the response is validated on the event loop without a
   further hop.

A login revoked, or a participant's tablet link reissued, between step 2 and step 3 does not stop
the request already admitted; the next one is refused. Whatever the handler *decides on* is read
inside its own transaction (a questionnaire submission re-reads whether the participant's answers
are locked: app.services.participants.questionnaires).
"""

from __future__ import annotations

import functools
import inspect
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from datetime import timedelta
from typing import Annotated, Any, Literal, TypeVar

from fastapi import APIRouter, Depends, Query, Request, Response
from sqlalchemy import event, select
from sqlalchemy.engine import Connection
from sqlalchemy.orm import ORMExecuteState, Session, SessionTransaction
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import FormData

from app.db import WRITE_OPTION, Database
from app.errors import NotAuthenticated, NotFound, PermissionDenied
from app.security import same
from app.services.audit import Actor
from app.services.privacy import sites
from app.services.staff import users
from app.settings import Settings
from app.sql import WROTE_KEY, SecondWrite
from app.tables import LoginSession, Role, Station, User

T = TypeVar("T")

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
SESSION_COOKIE = "tl_session"
CSRF_HEADER = "X-CSRF-Token"
CSRF_FIELD = "csrf_token"
FORM_MAX_FIELDS = 5000
"""Fields a form may have (Starlette's default is 1000): a protocol's questionnaires section
draws an input per item setting (app.protocol_forms); the body limit (app.main) bounds the rest."""


def set_private_cookie(
    response: Response,
    request: Request,
    name: str,
    value: str,
    *,
    max_age: int,
    samesite: Literal["lax", "strict"] = "lax",
) -> None:
    """Set a cookie scripts cannot read (HttpOnly), Secure as configured, else when the request
    came over HTTPS (the connection's scheme, or X-Forwarded-Proto from a trusted proxy: the
    proxy-headers middleware has already put it into the URL). Every cookie trustlab sets goes
    through here, so none travels in clear where the login cookie would not."""
    settings: Settings = request.app.state.settings
    secure = settings.cookie_secure
    if secure is None:
        secure = request.url.scheme == "https"
    response.set_cookie(
        name, value, httponly=True, samesite=samesite, secure=secure, max_age=max_age
    )


def set_session_cookie(
    response: Response, request: Request, settings: Settings, token: str
) -> None:
    """Give the browser its login cookie: HttpOnly, SameSite=Lax, Secure over HTTPS."""
    max_age = int(settings.session_hours * 3600)
    set_private_cookie(response, request, SESSION_COOKIE, token, max_age=max_age)


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


REQUEST_SESSION = "request_session"
"""Where :func:`request_session` leaves the request's session on ``request.state`` (for
:class:`OneHopRouter`)."""
READS_SINCE = "reads_since"
"""When the request's session was opened, before it read anything (wall clock, as the event
hub's: app.events.EventHub.since): a page renders it as its streams' ``since``."""
_REQUEST_WRITES = "trustlab.request_writes"
_READS_WITH = "trustlab.reads_with"
_TRANSACTION_WRITES = "trustlab.transaction_writes"


async def request_session(request: Request, database: DatabaseDep) -> AsyncIterator[Session]:
    """The request's session: it reads for safe methods and may write, once, otherwise.

    FastAPI runs each sync dependency and the handler in separate thread-pool hops. Unbounded,
    requests holding connections would wait for threads that all wait for connections. So
    requests first queue, as coroutines outside the thread pool, for admission: fewer requests
    than the pool has connections and threads, so an admitted request always finds both, and
    SQLite's writers queue fairly on the writer lock (app.db). Closing needs a hop only when a
    transaction is still open (routes outside :class:`OneHopRouter`).
    """
    writes = request.method not in SAFE_METHODS
    async with database.admission():
        # Before the first read: a live page asks its stream for what changed since then.
        setattr(request.state, READS_SINCE, time.time())
        session = database.write_session() if writes else database.read_session()
        if writes:
            session.info[_REQUEST_WRITES] = True
            session.info[_READS_WITH] = database.engine
            event.listen(session, "do_orm_execute", _refuse_a_second_statement)
        setattr(request.state, REQUEST_SESSION, session)
        try:
            yield session
        finally:
            if session.in_transaction():
                await run_in_threadpool(session.close)
            else:
                session.close()


@event.listens_for(Session, "after_begin")
def _note_transaction_kind(
    session: Session, _transaction: SessionTransaction, connection: Connection
) -> None:
    if _REQUEST_WRITES in session.info:
        writes = bool(connection.get_execution_options().get(WRITE_OPTION, False))
        session.info[_TRANSACTION_WRITES] = writes


@event.listens_for(Session, "after_commit")
@event.listens_for(Session, "after_rollback")
def _read_after_the_write(session: Session) -> None:
    """A request session's write transaction ended: from now on the session reads (a page that
    shows a refusal after rolling back, or a response built after the commit)."""
    info = session.info
    if info.get(_TRANSACTION_WRITES):
        info[_TRANSACTION_WRITES] = False
        info[WROTE_KEY] = True
        session.bind = info[_READS_WITH]


@event.listens_for(Session, "before_flush")
def _refuse_a_second_flush(session: Session, *_: Any) -> None:
    if session.info.get(WROTE_KEY) and (session.new or session.dirty or session.deleted):
        raise SecondWrite("this request's write transaction has ended")


def _refuse_a_second_statement(state: ORMExecuteState) -> None:
    """Listens to write requests' sessions only: a listener per statement costs every session."""
    if state.session.info.get(WROTE_KEY) and (
        state.is_insert or state.is_update or state.is_delete
    ):
        raise SecondWrite("this request's write transaction has ended")


def identify(db: Session, lookup: Callable[[Session], T]) -> T:
    """``lookup(db)``, the request's first read: who is asking (call it in a worker thread).

    For a write request's session the lookup reads in a transaction of its own (on SQLite a plain
    ``BEGIN``, which takes no lock), committed at once: what it loaded stays loaded, and the
    handler's write transaction begins only with the handler's first statement. Elsewhere (read
    requests, or once a transaction is open) it is simply part of the current transaction.
    """
    if not db.info.get(_REQUEST_WRITES) or db.in_transaction():
        return lookup(db)
    db.connection(execution_options={WRITE_OPTION: False})
    try:
        found = lookup(db)
    except BaseException:
        db.rollback()
        raise
    db.commit()
    return found


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
        value = (await request.form(max_fields=FORM_MAX_FIELDS)).get(CSRF_FIELD)
        return value if isinstance(value, str) else None
    return None


async def submitted_form(request: Request) -> FormData:
    """A posted form with up to :data:`FORM_MAX_FIELDS` fields, read before the (synchronous)
    endpoint runs: an async endpoint would hold the event loop through its database work."""
    return await request.form(max_fields=FORM_MAX_FIELDS)


SubmittedForm = Annotated[FormData, Depends(submitted_form)]


@dataclass(frozen=True)
class Viewer:
    """Who is looking at a page, as plain values: pages (and error pages rendered after a
    rollback, when ORM objects can no longer load) show these, never a live ORM object."""

    username: str
    role: str
    csrf_token: str


async def current_login(
    request: Request,
    db: SessionDep,
    settings: SettingsDep,
    csrf_token: Annotated[str | None, Depends(submitted_csrf_token)],
) -> LoginSession:
    """The signed-in browser's login session; 401 without one, 403 on a missing CSRF token."""
    token = request.cookies.get(SESSION_COOKIE)
    idle_timeout = timedelta(minutes=settings.idle_minutes)

    def lookup(read: Session) -> LoginSession | None:
        assert token
        return users.resolve_login(read, token=token, idle_timeout=idle_timeout)

    login = await run_in_threadpool(identify, db, lookup) if token else None
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


async def streaming_login(request: Request) -> LoginSession:
    """The signed-in browser's login, checked in a short session of its own: for requests that
    spend their time waiting rather than in the database — event streams, which stay open for
    hours (and end with their login: app.web.streams), and the dashboard's data, which waits for a
    computation shared with other dashboards.

    Such a request must not hold a request session (and its admission slot) while it waits, so it
    cannot depend on :data:`SessionDep`; it needs no CSRF check because these are GETs.
    """
    database: Database = request.app.state.database
    settings: Settings = request.app.state.settings
    token = request.cookies.get(SESSION_COOKIE)

    def resolve() -> LoginSession | None:
        if not token:
            return None
        with database.read_session() as db:
            return users.resolve_login(
                db, token=token, idle_timeout=timedelta(minutes=settings.idle_minutes)
            )

    async with database.admission():
        login = await run_in_threadpool(resolve)
    if login is None:
        raise NotAuthenticated("sign in first")
    request.app.state.activity.note_login(login.id)
    return login


StreamingLogin = Annotated[LoginSession, Depends(streaming_login)]


async def streaming_user(login: StreamingLogin) -> User:
    """The user of :func:`streaming_login`."""
    return login.user


StreamingUser = Annotated[User, Depends(streaming_user)]


async def current_user(login: CurrentLogin) -> User:
    """The signed-in user."""
    return login.user


CurrentUser = Annotated[User, Depends(current_user)]


def require(*roles: Role) -> Callable[[User], Awaitable[User]]:
    """A dependency admitting the given roles (admins are always admitted)."""
    allowed = frozenset((*roles, Role.ADMIN))

    async def dependency(user: CurrentUser) -> User:
        if Role(user.role) not in allowed:
            names = " or ".join(sorted(r.value for r in allowed))
            raise PermissionDenied(f"this needs the {names} role; you are {user.role}")
        return user

    return dependency


def bearer_key(request: Request) -> str:
    """The key of an ``Authorization: Bearer …`` header ('' when absent)."""
    scheme, _, key = request.headers.get("authorization", "").partition(" ")
    return key.strip() if scheme.lower() == "bearer" else ""


async def station_in_scope(request: Request, db: SessionDep, user: CurrentUser) -> None:
    """Every staff route of a station (``/stations/{name}…``) depends on this: for an account
    limited to some sites, a station whose seated participant is of another site does not exist
    (app.services.privacy.sites). Unlimited accounts pass without a read."""
    name = request.path_params.get("name")
    actor = Actor.of_user(user)
    # Only experimenters reach these routes limited (admins never are; an analyst meets the
    # route's own 403 first, as the access policy says).
    if not isinstance(name, str) or actor.sites is None or actor.role != Role.EXPERIMENTER:
        return

    def lookup(read: Session) -> bool:
        station = read.scalar(select(Station).where(Station.name == name))
        return station is not None and sites.station_hidden(read, station, actor)

    if await run_in_threadpool(identify, db, lookup):
        raise NotFound(f"no station named {name!r}")


async def reader_scope(user: CurrentUser) -> sites.Scope:
    """The participants the signed-in account may see (app.services.privacy.sites): its sites when
    it is limited, else every site. Pages reading participant data without an actor to record
    (the analysis, exports, the power planning) take this, and pass it to the query, which
    requires it."""
    return sites.Scope.of(Actor.of_user(user))


ReaderScope = Annotated[sites.Scope, Depends(reader_scope)]


SiteFilter = Annotated[
    str,
    Query(max_length=40, description="One of the study's sites: only its participants."),
]
"""A page's ``?site=`` filter (app.services.privacy.sites.narrowed checks it)."""


AdminUser = Annotated[User, Depends(require(Role.ADMIN))]
ExperimenterUser = Annotated[User, Depends(require(Role.EXPERIMENTER))]
AnalystUser = Annotated[User, Depends(require(Role.ANALYST))]


async def form_fields(request: Request) -> dict[str, str]:
    """A posted form's text fields (for forms whose field names depend on the protocol)."""
    form = await request.form()
    return {key: value for key, value in form.multi_items() if isinstance(value, str)}


FormFields = Annotated[dict[str, str], Depends(form_fields)]


# ------------------------------------------------------------------ handlers in one thread-pool hop

_REQUEST_PARAMETER = "_one_hop_request"


def _run_and_close(
    endpoint: Callable[..., Any], request: Request, arguments: dict[str, Any]
) -> Any:
    try:
        return endpoint(**arguments)
    finally:
        session: Session | None = getattr(request.state, REQUEST_SESSION, None)
        if session is not None:
            session.close()


def in_one_hop(endpoint: Callable[..., Any]) -> Callable[..., Any]:
    """``endpoint`` (a sync handler) as a coroutine running it in one thread-pool hop that ends
    the request's open transaction, if any, before the hop ends (see the module's docstring).

    Its parameters, and so what FastAPI resolves, validates and documents, stay the handler's
    own; the wrapper only asks for the request besides. Coroutines are returned unchanged.
    """
    if inspect.iscoroutinefunction(endpoint) or getattr(endpoint, "one_hop", False):
        return endpoint
    signature = inspect.signature(endpoint, eval_str=True)
    parameters = list(signature.parameters.values())
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        raise TypeError(f"{endpoint.__qualname__}: handlers take no **kwargs")
    # FastAPI hands the request to one parameter only: the handler's own if it has one.
    own = next((p.name for p in parameters if p.annotation is Request), None)
    if own is None:
        parameters.append(
            inspect.Parameter(
                _REQUEST_PARAMETER, inspect.Parameter.KEYWORD_ONLY, annotation=Request
            )
        )

    @functools.wraps(endpoint)
    async def run(**arguments: Any) -> Any:
        request = arguments[own] if own else arguments.pop(_REQUEST_PARAMETER)
        return await run_in_threadpool(_run_and_close, endpoint, request, arguments)

    run.__signature__ = signature.replace(parameters=parameters)  # type: ignore[attr-defined]
    run.one_hop = True  # type: ignore[attr-defined]
    return run


class OneHopRouter(APIRouter):
    """An APIRouter whose synchronous handlers each run as :func:`in_one_hop` does."""

    def add_api_route(self, path: str, endpoint: Callable[..., Any], **kwargs: Any) -> None:
        """Register ``endpoint`` (wrapped) like APIRouter does."""
        super().add_api_route(path, in_one_hop(endpoint), **kwargs)
