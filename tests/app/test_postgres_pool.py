"""PostgreSQL connections: pinged only after sitting idle, and a lost one never handed out again.

app.db pings a pooled connection before reuse only when it was idle for IDLE_PING_SECONDS (a ping
on every checkout cost each request a round trip); a connection lost while in use fails its
request once, and the pool is invalidated so the next request connects afresh — also when the
loss surfaces in the robot's hot path (app.services.sessions.step_store's driver cursor).
"""

from __future__ import annotations

from collections.abc import Iterator

import psycopg
import pytest
from sqlalchemy import text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import OperationalError

import app.db
from app.db import Database
from app.services.sessions import step_store
from app.sql import Cursor
from tests.conftest import POSTGRES_SKIP_REASON, POSTGRES_URL


@pytest.fixture(params=[pytest.param("postgresql", marks=pytest.mark.postgres)])
def engine_name(request: pytest.FixtureRequest) -> str:
    """Only PostgreSQL has connections that can die under the pool."""
    if not POSTGRES_URL:
        pytest.skip(POSTGRES_SKIP_REASON)
    return str(request.param)


@pytest.fixture
def pool(database_url: str) -> Iterator[Database]:
    database = Database(database_url)
    yield database
    database.dispose()


def _backend(database: Database) -> int:
    with database.read_session() as db:
        return int(db.execute(text("SELECT pg_backend_pid()")).scalar_one())


def _terminate(database_url: str, pid: int) -> None:
    conninfo = make_url(database_url).set(drivername="postgresql")
    with psycopg.connect(conninfo.render_as_string(hide_password=False), autocommit=True) as conn:
        conn.execute("SELECT pg_terminate_backend(%s)", (pid,))


def _count_pings(pool: Database, monkeypatch: pytest.MonkeyPatch) -> list[object]:
    pings: list[object] = []
    dialect = pool.engine.dialect
    original = dialect.do_ping

    def counted(dbapi_connection: object) -> bool:
        pings.append(dbapi_connection)
        return bool(original(dbapi_connection))

    monkeypatch.setattr(dialect, "do_ping", counted)
    return pings


def test_a_connection_in_steady_use_is_not_pinged(
    pool: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    pings = _count_pings(pool, monkeypatch)
    first = _backend(pool)
    assert [_backend(pool) for _ in range(5)] == [first] * 5  # the same pooled connection
    assert pings == []


def test_an_idle_connection_is_pinged_and_a_dead_one_replaced(
    pool: Database, database_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    pings = _count_pings(pool, monkeypatch)
    dead = _backend(pool)
    _terminate(database_url, dead)
    monkeypatch.setattr(app.db, "IDLE_PING_SECONDS", 0.0)  # every checkin now counts as idle
    replacement = _backend(pool)  # no error: the ping found the dead one first
    assert replacement != dead and len(pings) >= 1


def test_a_connection_lost_in_use_fails_once_then_the_pool_connects_afresh(
    pool: Database, database_url: str
) -> None:
    """The hot path's own statements hand a lost connection to SQLAlchemy's handler: the error
    is SQLAlchemy's OperationalError (a 503 in the app), and every pooled connection is
    replaced, the idle ones too (after a server restart they are all dead)."""
    with pool.read_session() as one, pool.read_session() as two:
        pooled = {
            int(db.execute(text("SELECT pg_backend_pid()")).scalar_one()) for db in (one, two)
        }
    with pool.read_session() as db:
        cursor = Cursor.of(db)
        lost = int(db.execute(text("SELECT pg_backend_pid()")).scalar_one())
        _terminate(database_url, lost)
        with pytest.raises(OperationalError) as raised:
            step_store.station_seat(cursor, name="nowhere")
        assert raised.value.connection_invalidated
    with pool.read_session() as one, pool.read_session() as two:
        fresh = {int(db.execute(text("SELECT pg_backend_pid()")).scalar_one()) for db in (one, two)}
        assert step_store.station_seat(Cursor.of(one), name="nowhere") is None
    assert lost in pooled and not fresh & pooled
