"""Hand-written SQL on the driver cursor of a session's transaction.

For the few statements that run on every robot request (app.services.sessions.step_store) and every
PostgreSQL commit with live events (app.events): through SQLAlchemy's execution machinery each
cost several times what the database spends on it. A :class:`Cursor` belongs to the session's
current transaction, so its statements commit or roll back with the session's other work; it
converts values as the ORM's column types (app.tables) store them, reports its statements to
SQLAlchemy's ``before_cursor_execute`` listeners (the tests' and benchmarks' statement counters),
and hands driver errors to SQLAlchemy's own handler. Like the ORM's autoflush, a statement first
flushes the session's pending ORM changes; a write then expires the session's ORM objects, so
nothing loaded before it is served stale afterwards.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from typing import Any

from sqlalchemy.orm import Session

from app.tables import utcnow

_NAMED = re.compile(r"(?<![:\w]):([a-z_]+)")


class Statement:
    """One SQL statement, written with ``:name`` parameters, in both drivers' styles.

    ``{lock}`` in the text becomes ``FOR UPDATE OF …`` on PostgreSQL when the statement is run
    with ``lock=True`` (SQLite's write transactions are exclusive already).
    """

    def __init__(self, sql: str, *, lock_of: str = "") -> None:
        text = " ".join(sql.split())
        lock = f" FOR UPDATE OF {lock_of}" if lock_of else ""
        self._sqlite = text.replace(" {lock}", "")
        postgres = _NAMED.sub(r"%(\1)s", text)
        self._postgres = postgres.replace(" {lock}", "")
        self._postgres_locked = postgres.replace(" {lock}", lock)

    def text(self, postgres: bool, lock: bool = False) -> str:
        """The statement for one driver."""
        if not postgres:
            return self._sqlite
        return self._postgres_locked if lock else self._postgres


_CURSOR_KEY = "trustlab_driver_cursor"
WROTE_KEY = "trustlab.wrote"
"""Set in a request session's ``info`` once its write transaction has ended (app.deps): from then
on the session only reads, through the ORM and through a :class:`Cursor` alike."""


class SecondWrite(RuntimeError):
    """A request tried to write after its write transaction had ended (a programming error: one
    request, one write transaction)."""


class Cursor:
    """The driver cursor of a session's transaction, with the ORM column types' conversions.

    Take it with :meth:`of`: one per transaction, shared by everything the request does in it.
    Driver errors come out as SQLAlchemy's (``IntegrityError``, ``OperationalError``…), as they
    would from ORM work, so the application's handlers (a lost database is a 503) apply; a lost
    connection is invalidated so the pool never hands it out again.
    """

    def __init__(self, db: Session) -> None:
        self.db = db
        self._connection = db.connection()  # begins the transaction (BEGIN IMMEDIATE for writers)
        self.transaction = db.get_transaction()
        dialect = self._connection.dialect
        self._dbapi_error: type[Exception] = dialect.loaded_dbapi.Error
        self.postgres = dialect.name == "postgresql"
        raw = self._connection.connection.driver_connection
        assert raw is not None
        self._raw_connection = raw
        self._raw = raw.cursor()
        # Statement counters (tests, bench/answer_cost.py) listen on SQLAlchemy's own event.
        self._observers = list(self._connection.dispatch.before_cursor_execute)
        self._now: datetime | None = None
        self._batching = False

    @classmethod
    def of(cls, db: Session) -> Cursor:
        """The cursor of ``db``'s current transaction (begun if need be)."""
        cached: Cursor | None = db.info.get(_CURSOR_KEY)
        if cached is not None and cached.transaction is db.get_transaction():
            return cached
        cursor = db.info[_CURSOR_KEY] = cls(db)
        return cursor

    @property
    def now(self) -> datetime:
        """The transaction's clock: every row it writes carries the same UTC time."""
        if self._now is None:
            self._now = utcnow()
        return self._now

    def _execute(
        self, statement: Statement, params: dict[str, Any], lock: bool = False, cursor: Any = None
    ) -> None:
        db = self.db
        if db.new or db.dirty or db.deleted:  # the ORM's autoflush: its changes go first
            db.flush()
        sql = statement.text(self.postgres, lock)
        target = self._raw if cursor is None else cursor
        for observer in self._observers:
            observer(self._connection, target, sql, params, None, False)
        try:
            target.execute(sql, params)
        except self._dbapi_error as error:
            self._failed(error, sql, params, target)

    def _failed(self, error: Exception, sql: str, params: dict[str, Any], cursor: Any) -> None:
        # SQLAlchemy's own handler, as its execute() would call it: wraps the error, runs
        # handle_error events, and on a lost connection invalidates it and the whole pool. It
        # also closes the driver cursor, so this Cursor is not handed out again.
        if self.db.info.get(_CURSOR_KEY) is self:
            del self.db.info[_CURSOR_KEY]
        self._connection._handle_dbapi_exception(error, sql, params, cursor, None)

    @contextmanager
    def batch(self) -> Iterator[None]:
        """Send the statements run inside together: PostgreSQL's pipeline mode, one round trip
        for several writes (each a wait for the server, which costs most when the machine is
        busy); SQLite runs in-process, so there nothing changes. Inside, :meth:`write` returns a
        :class:`Written` whose count is known once the batch has ended, and an error of any
        statement surfaces when it ends. A read inside waits for everything before it."""
        if not self.postgres or self._batching:
            yield
            return
        self._batching = True
        try:
            with self._raw_connection.pipeline():
                yield
        except self._dbapi_error as error:
            self._failed(error, "-- a batch of statements", {}, self._raw)
        finally:
            self._batching = False

    def rows(
        self, statement: Statement, params: dict[str, Any], *, lock: bool = False
    ) -> list[Any]:
        """Every row of a query."""
        self._execute(statement, params, lock)
        return list(self._raw.fetchall())

    def row(self, statement: Statement, params: dict[str, Any], *, lock: bool = False) -> Any:
        """The first row of a query, or None."""
        self._execute(statement, params, lock)
        return self._raw.fetchone()

    def write(self, statement: Statement, params: dict[str, Any]) -> Written:
        """Run an INSERT/UPDATE; how many rows it changed. Objects the session loaded earlier
        are expired, so later ORM reads in this transaction see the change."""
        self._refuse_after_the_write()
        cursor = self._send(statement, params)
        self.db.expire_all()
        # In a batch the count is known once the batch has ended (the write has a cursor of its
        # own); otherwise the shared cursor's count is read now, before another statement runs.
        return Written(cursor) if self._batching else Written(None, int(cursor.rowcount))

    def _refuse_after_the_write(self) -> None:
        if self.db.info.get(WROTE_KEY):
            raise SecondWrite("this request's write transaction has ended")

    def send(self, statement: Statement, params: dict[str, Any]) -> None:
        """Run a statement that changes no table and whose rows nobody reads (``pg_notify``):
        it may travel in a batch, and the session's ORM objects stay as they are."""
        self._send(statement, params)

    def _send(self, statement: Statement, params: dict[str, Any]) -> Any:
        # In a batch each write gets its own driver cursor, so its row count survives the next.
        cursor = self._raw_connection.cursor() if self._batching else self._raw
        self._execute(statement, params, cursor=cursor)
        return cursor

    def insert(self, statement: Statement, params: dict[str, Any]) -> int:
        """Run an ``INSERT … RETURNING id``; returns the new id (in a batch: waits for it)."""
        self._refuse_after_the_write()
        self._execute(statement, params)
        new_id = self._raw.fetchone()[0]
        self.db.expire_all()
        return int(new_id)

    # Conversions, as app.tables' column types do them.

    def json(self, value: Any) -> Any:
        """A JSON document parameter (JSON text on SQLite, JSONB on PostgreSQL)."""
        if not self.postgres:
            return json.dumps(value)
        # Imported here: on SQLite (every command's default) the PostgreSQL driver is not loaded.
        from psycopg.types.json import Jsonb

        return Jsonb(value)

    def parsed(self, value: Any) -> Any:
        """A JSON document as read (PostgreSQL's driver parses JSONB itself)."""
        return value if self.postgres or value is None else json.loads(value)

    def timestamp(self, value: datetime | None = None) -> Any:
        """A UTC timestamp parameter, by default the transaction's :attr:`now` (naive UTC text
        on SQLite, in SQLAlchemy's format; an aware datetime for PostgreSQL's driver)."""
        value = self.now if value is None else value
        if self.postgres:
            return value
        return value.astimezone(UTC).replace(tzinfo=None).isoformat(" ", "microseconds")


class Written:
    """What a write changed: its row count, read when asked (after a batch has ended)."""

    def __init__(self, cursor: Any, count: int | None = None) -> None:
        self._cursor = cursor
        self._count = count

    @property
    def count(self) -> int:
        """How many rows the statement changed."""
        if self._count is None:
            self._count = int(self._cursor.rowcount)
        return self._count
