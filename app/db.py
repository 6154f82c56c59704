"""Database engines and sessions for SQLite and PostgreSQL.

Two kinds of session exist because SQLite has one writer at a time: a transaction that starts as a
reader and later writes fails at once (``SQLITE_BUSY``) when another writer committed in between,
whatever the busy timeout. Requests and commands that write therefore open a *write session*,
whose transactions start with ``BEGIN IMMEDIATE`` on SQLite and so queue politely for the write
lock. On PostgreSQL both kinds are ordinary READ COMMITTED transactions; rows that must not change
under a transaction are locked explicitly (``SELECT … FOR UPDATE``).
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import sqlite3
import threading
import time
import weakref
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import anyio
import anyio.from_thread
from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import DBAPIError, DisconnectionError, OperationalError
from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool

from app.errors import DatabaseUnavailable
from app.events import EventHub, attach_publishing
from app.private_files import create_private
from app.services.sessions import learner_cache

log = logging.getLogger(__name__)

T = TypeVar("T")

WRITE_OPTION = "trustlab_write"
"""Execution option that marks connections of write sessions (``BEGIN IMMEDIATE`` on SQLite)."""
WRITER_WAIT_SECONDS = 30.0

WAL_CHECKPOINT_SECONDS = 0.5
"""How often a server's thread checkpoints SQLite's WAL (see :class:`WalCheckpointer`)."""
WAL_AUTOCHECKPOINT_PAGES = 10_000
"""SQLite's own checkpoint threshold while the background thread runs (the default is 1000): only
a safety net, should the thread fall behind, so the WAL stays bounded (about 40 MB)."""

POOL_SIZE, POOL_OVERFLOW = 20, 20
ADMITTED_REQUESTS = 30
"""Requests doing database work at once per process: below the connection pool (40) and the
thread pool (40), so an admitted request always finds both; the rest wait as coroutines."""


def describe_url(url: str | URL) -> str:
    """The URL as it may be shown to a person: the password masked."""
    return make_url(url).render_as_string(hide_password=True)


class _GatedConnection(sqlite3.Connection):
    """A sqlite3 connection that hands the writer queue on only after COMMIT or ROLLBACK returned.

    SQLAlchemy's "commit" event fires *before* the driver commits; releasing the queue there let
    the next writer's ``BEGIN IMMEDIATE`` meet a still-held lock, and SQLite's busy handler then
    sleeps (1, 2, 5, 10… ms): a tail latency of its own making. Here the release follows the
    driver's own commit or rollback (the pool's reset rolls back too, so nothing leaks).
    """

    writers: threading.Lock | None = None
    """The engine's writer queue, set when the connection opens."""
    holds_writer = False

    def commit(self) -> None:
        try:
            super().commit()
        finally:
            self.release_writer()

    def rollback(self) -> None:
        try:
            super().rollback()
        finally:
            self.release_writer()

    def close(self) -> None:
        try:
            super().close()
        finally:
            self.release_writer()

    def release_writer(self) -> None:
        """Let the next writer in (idempotent)."""
        if self.holds_writer:
            self.holds_writer = False
            assert self.writers is not None
            self.writers.release()


def _configure_sqlite(engine: Engine, synchronous: str, autocheckpoint_pages: int) -> None:
    """WAL, foreign keys, a generous busy timeout, explicit BEGINs, and a fair writer queue.

    SQLite has one writer at a time and its busy handler polls with growing sleeps, so under
    contention an unlucky writer can starve for seconds. SQLite serves from one process by
    design, so writers first queue on an in-process lock and only then ``BEGIN IMMEDIATE``: the
    lock is handed over the moment a write transaction's COMMIT or ROLLBACK has returned
    (:class:`_GatedConnection`).

    Durability: in WAL mode a committed transaction survives a crash of the process (SIGKILL)
    whatever ``synchronous`` says, because the WAL is written before COMMIT returns; FULL also
    fsyncs the WAL at every commit, so it survives power loss and OS crashes too, at the price of
    one fsync (milliseconds on ordinary disks) per write request. NORMAL fsyncs only at
    checkpoints. The default (app.settings) is FULL.

    ``secure_delete`` zeroes what a DELETE removes instead of leaving it in free pages, so an
    erased participant's answers (app.services.privacy.erasure) cannot be read back out of the file
    with a hex editor; trustlab deletes rarely, so its cost does not show.
    """
    writers = threading.Lock()

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: _GatedConnection, _record: Any) -> None:
        dbapi_connection.writers = writers
        # Let SQLAlchemy's "begin" event (below) issue BEGIN instead of the sqlite3 module.
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute("PRAGMA secure_delete=ON")
        cursor.execute("PRAGMA busy_timeout=30000")
        cursor.execute(f"PRAGMA synchronous={synchronous}")
        cursor.execute(f"PRAGMA wal_autocheckpoint={autocheckpoint_pages}")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(connection: Any) -> None:
        # BEGIN goes straight to the driver: through SQLAlchemy's execution machinery it cost
        # as much as a small query, on every request.
        dbapi_connection: _GatedConnection = connection.connection.driver_connection
        if not connection.get_execution_options().get(WRITE_OPTION, False):
            _begin(connection, dbapi_connection, "BEGIN")
            return
        if not writers.acquire(timeout=_writer_wait_left()):
            raise OperationalError("BEGIN IMMEDIATE", {}, TimeoutError("writer queue full"))
        dbapi_connection.holds_writer = True
        try:
            _begin(connection, dbapi_connection, "BEGIN IMMEDIATE")
        except BaseException:
            dbapi_connection.release_writer()
            raise

    def _begin(connection: Any, dbapi_connection: _GatedConnection, statement: str) -> None:
        for observer in connection.dispatch.before_cursor_execute:  # statement counters
            observer(connection, None, statement, (), None, False)
        try:
            dbapi_connection.execute(statement)
        except sqlite3.Error as exc:
            raise OperationalError(statement, (), exc) from exc


IDLE_PING_SECONDS = 1.0
"""A pooled PostgreSQL connection idle for longer is pinged before it is handed out: when the
server is quiet enough for connections to idle, the ping costs nobody anything; under load they
never idle this long, so requests skip it."""


def _ping_idle_connections(engine: Engine) -> None:
    """Ping a PostgreSQL connection before reuse only if it sat idle (:data:`IDLE_PING_SECONDS`).

    SQLAlchemy's ``pool_pre_ping`` pings on every checkout: a round trip and ~0.3 ms of CPU on
    every request (bench/answer_cost.py), to catch connections that died while idle — a server
    restart, an idle timeout, a dropped network. Connections in steady use need no ping: if the
    server goes away under them the request fails with a 503 (app.http), and SQLAlchemy then
    invalidates the whole pool (app.sql hands the hot path's driver errors to the same handler), so
    the next requests connect afresh. A dead idle connection found here is replaced at once.
    """

    @event.listens_for(engine.pool, "checkin")
    def _note_idle(_dbapi_connection: Any, record: Any) -> None:
        record.info["idle_since"] = time.monotonic()

    @event.listens_for(engine.pool, "checkout")
    def _ping_if_idle(dbapi_connection: Any, record: Any, _proxy: Any) -> None:
        idle_since = record.info.get("idle_since")
        if idle_since is None or time.monotonic() - idle_since < IDLE_PING_SECONDS:
            return
        try:
            alive = engine.dialect.do_ping(dbapi_connection)
        except engine.dialect.loaded_dbapi.Error as exc:
            raise DisconnectionError(f"idle connection is gone: {exc}") from exc
        if not alive:  # pragma: no cover - psycopg's ping raises rather than returning False
            raise DisconnectionError("idle connection is gone")


def create_db_engine(
    database_url: str, *, sqlite_synchronous: str = "FULL", background_checkpoints: bool = False
) -> Engine:
    """An engine for ``database_url`` with trustlab's connection settings applied.

    ``background_checkpoints``: a :class:`WalCheckpointer` will checkpoint SQLite's WAL, so
    requests' commits need not (SQLite's own threshold is raised to a safety net).
    """
    url = make_url(database_url)
    if url.get_backend_name() == "sqlite":
        if url.database and url.database != ":memory:":
            Path(url.database).parent.mkdir(parents=True, exist_ok=True)
            # It holds seeds and password hashes: a new file is the owner's only (SQLite gives
            # its -wal and -shm files the database file's mode).
            create_private(Path(url.database))
        engine = create_engine(
            url,
            connect_args={"check_same_thread": False, "timeout": 30, "factory": _GatedConnection},
            pool_size=POOL_SIZE,
            max_overflow=POOL_OVERFLOW,
            # The connection returned last is handed out next: SQLite keeps a page cache per
            # connection, valid until another connection writes, so the writer thread
            # (:class:`WriterThread`) keeps working on a warm one.
            pool_use_lifo=True,
        )
        pages = WAL_AUTOCHECKPOINT_PAGES if background_checkpoints else 1000
        _configure_sqlite(engine, sqlite_synchronous, pages)
        return engine
    if url.get_backend_name() == "postgresql":
        engine = create_engine(
            url,
            pool_size=POOL_SIZE,
            max_overflow=POOL_OVERFLOW,
            connect_args={"connect_timeout": 5, "application_name": "trustlab"},
        )
        _ping_idle_connections(engine)
        return engine
    raise ValueError(
        f"unsupported database {describe_url(url)!r}: use sqlite:///FILE or postgresql+psycopg://…"
    )


class WalCheckpointer:
    """Checkpoints a SQLite database's WAL from a background thread, off the request path.

    By default SQLite checkpoints inside the commit that grows the WAL past 1000 pages: about one
    write request in a hundred then copies the WAL into the database and fsyncs it, which takes
    milliseconds and is exactly what a p99 latency shows. A PASSIVE checkpoint here every
    ``interval`` seconds does the same work without taking the write lock (writers go on
    appending to the WAL meanwhile) and leaves SQLite's own checkpoint as a safety net only.
    Checkpoints change nothing about durability: they copy committed transactions.
    """

    def __init__(self, path: str, interval: float = WAL_CHECKPOINT_SECONDS) -> None:
        self._path = path
        self.interval = interval
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.runs = 0

    def checkpoint(self) -> tuple[int, int, int]:
        """One PASSIVE checkpoint: (busy, frames in the WAL, frames checkpointed)."""
        connection = sqlite3.connect(self._path, timeout=30, isolation_level=None)
        try:
            row = connection.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
        finally:
            connection.close()
        self.runs += 1
        return int(row[0]), int(row[1]), int(row[2])

    def truncate(self) -> bool:
        """Copy the whole WAL into the database file and empty it, so that no earlier version of
        a page (say, one an erasure has since zeroed) stays in the WAL; False when a reader
        still needs the WAL (it is then emptied by a later checkpoint)."""
        connection = sqlite3.connect(self._path, timeout=30, isolation_level=None)
        try:
            row = connection.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
        finally:
            connection.close()
        return int(row[0]) == 0

    def start(self) -> None:
        """Checkpoint every interval until :meth:`stop`."""
        self._thread = threading.Thread(target=self._run, name="trustlab-checkpoint", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread (a last checkpoint first)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30)

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self._checkpoint_logged()
        self._checkpoint_logged()

    def _checkpoint_logged(self) -> None:
        try:
            self.checkpoint()
        except sqlite3.Error as exc:  # SQLite's own checkpoint still bounds the WAL
            log.warning("WAL checkpoint failed: %s", exc)


_queued = threading.local()
"""On a writer thread: when the unit of work it runs was queued, and by which clock
(:class:`WriterThread`)."""


def _writer_wait_left() -> float:
    """How long a writer may still wait for the write lock: :data:`WRITER_WAIT_SECONDS` from when
    its unit of work was queued on a writer thread, or from now. Time spent waiting for its turn
    on that thread counts, so queued writes behind a stuck lock fail after 30 s together, not one
    30 s after another."""
    queued_at: float | None = getattr(_queued, "at", None)
    if queued_at is None:
        return WRITER_WAIT_SECONDS
    return max(0.0, queued_at + WRITER_WAIT_SECONDS - _queued.clock())


class WriterThread:
    """One thread that runs a SQLite database's robot write work, one unit after another.

    SQLite has one writer at a time (:func:`_configure_sqlite`). In the shared thread pool,
    concurrent robot requests each took a thread and a pooled connection and then queued on the
    writer lock inside them: every commit woke another thread, which competed for the GIL with
    the event loop and the thread just finishing, and began on a connection whose page cache the
    previous writer had invalidated. Queued here, the next unit of work starts on the same thread
    as soon as the last one ends, on the connection it just returned (the SQLite pool is LIFO).
    docs/performance.md ("One writer thread") has the measurements.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._executor: ThreadPoolExecutor | None = None
        self._guard = threading.Lock()
        self._clock = clock
        """Measures the time a unit waited for its turn (tests inject one they advance)."""

    async def run(self, func: Callable[..., T], *args: Any) -> T:
        """``func(*args)`` on the writer thread, in the caller's context variables.

        Cancelling the caller never drops the work, queued or running (asyncio.shield). As with
        ``run_in_threadpool``, a caller cancelled through anyio's cancel scopes (a task group)
        goes on waiting until the work has ended, so its admission slot is held exactly as long
        as the work runs; a native ``task.cancel()`` lets it go at once, as it did there."""
        queued_at = self._clock()

        def unit() -> T:
            _queued.at, _queued.clock = queued_at, self._clock
            try:
                return func(*args)
            finally:
                _queued.at = None

        context = contextvars.copy_context()
        with self._guard:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(1, thread_name_prefix="trustlab-writer")
            future = self._executor.submit(context.run, unit)
        with anyio.CancelScope(shield=True):
            result = await asyncio.shield(asyncio.wrap_future(future))
        return result

    def stop(self) -> None:
        """Let queued work finish, then end the thread (a later :meth:`run` starts a new one)."""
        with self._guard:
            executor, self._executor = self._executor, None
        if executor is not None:
            executor.shutdown(wait=True)


class Database:
    """An engine plus the two session factories every caller uses.

    ``background_checkpoints`` (servers: app.main): SQLite's WAL is checkpointed by a thread
    started with :meth:`start_background_work` rather than inside requests' commits.
    """

    def __init__(
        self,
        database_url: str,
        *,
        sqlite_synchronous: str = "FULL",
        background_checkpoints: bool = False,
    ) -> None:
        self.url = database_url
        self.engine = create_db_engine(
            database_url,
            sqlite_synchronous=sqlite_synchronous,
            background_checkpoints=background_checkpoints,
        )
        path = self.engine.url.database
        self._checkpointer = (
            WalCheckpointer(path)
            if background_checkpoints and self.is_sqlite and path and path != ":memory:"
            else None
        )
        # One learner cache per database, shared by its sessions (info is copied shallowly).
        shared = {learner_cache.SESSION_KEY: learner_cache.LearnerCache()}
        self._read = sessionmaker(self.engine, expire_on_commit=False, info=shared)
        self._write = sessionmaker(
            self.engine.execution_options(**{WRITE_OPTION: True}),
            expire_on_commit=False,
            info=shared,
        )
        self.hub = EventHub()
        self._admissions: weakref.WeakKeyDictionary[
            asyncio.AbstractEventLoop, asyncio.Semaphore
        ] = weakref.WeakKeyDictionary()
        for factory in (self._read, self._write):
            attach_publishing(factory, self.hub, postgres=not self.is_sqlite)
        self._writer = WriterThread() if self.is_sqlite else None

    @property
    def is_sqlite(self) -> bool:
        """Whether this is a SQLite database (one writer, one process)."""
        return self.engine.dialect.name == "sqlite"

    def admission(self) -> asyncio.Semaphore:
        """The running event loop's limit on requests doing database work at once (app.deps)."""
        loop = asyncio.get_running_loop()
        limit = self._admissions.get(loop)
        if limit is None:
            limit = self._admissions[loop] = asyncio.Semaphore(ADMITTED_REQUESTS)
        return limit

    @contextmanager
    def admitted_from_thread(self) -> Iterator[None]:
        """Hold an admission slot from a worker thread (one started by anyio, as FastAPI's
        thread pool is), for work a request does in a thread without holding a slot all along:
        it waits like any request, on the request's event loop."""
        admission = anyio.from_thread.run_sync(self.admission)
        anyio.from_thread.run(admission.acquire)
        try:
            yield
        finally:
            anyio.from_thread.run_sync(admission.release)

    async def run_unit_of_work(self, func: Callable[..., T], *args: Any, write: bool) -> T:
        """Run ``func(*args)``, a request's synchronous database work, off the event loop: a
        write on SQLite on the :class:`WriterThread`, anything else in the shared thread pool
        (PostgreSQL serves concurrent writers in parallel)."""
        if write and self._writer is not None:
            return await self._writer.run(func, *args)
        return await run_in_threadpool(func, *args)

    def read_session(self) -> Session:
        """A session for requests that only read."""
        return self._read()

    def write_session(self) -> Session:
        """A session whose transactions may write (BEGIN IMMEDIATE on SQLite)."""
        return self._write()

    @contextmanager
    def writing(self) -> Iterator[Session]:
        """A write session closed afterwards; the caller commits (uncommitted work rolls back)."""
        with self.write_session() as session:
            yield session

    def ping(self) -> None:
        """Raise :class:`DatabaseUnavailable` (one clear sentence) unless the database answers."""
        try:
            with self.engine.connect() as connection:
                connection.execute(text("SELECT 1"))
        except (OperationalError, DBAPIError) as exc:
            reason = str(exc.orig).strip().splitlines()[0] if exc.orig else str(exc)
            raise DatabaseUnavailable(
                f"cannot reach the database at {describe_url(self.url)}: {reason}"
            ) from exc

    def start_background_work(self) -> None:
        """Start the WAL checkpoints, if this database has them (server start)."""
        if self._checkpointer is not None:
            self._checkpointer.start()

    def finish_requests(self) -> None:
        """Let the writer thread finish the work queued on it, then end it (server shutdown,
        after the last request; before the last flushes of anything that work feeds)."""
        if self._writer is not None:
            self._writer.stop()

    def stop_background_work(self) -> None:
        """Stop what :meth:`start_background_work` started (server shutdown)."""
        if self._checkpointer is not None:
            self._checkpointer.stop()

    @property
    def checkpointer(self) -> WalCheckpointer | None:
        """The background WAL checkpointer (SQLite servers), for tests and the health page."""
        return self._checkpointer

    def dispose(self) -> None:
        """Close every pooled connection (tests, shutdown, before a restore)."""
        self.engine.dispose()
