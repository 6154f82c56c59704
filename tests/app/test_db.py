"""SQLite's WAL is checkpointed by a server's background thread, not inside requests' commits."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

from sqlalchemy import event, text

from app.db import WAL_AUTOCHECKPOINT_PAGES, Database
from app.services.sessions import learner_cache
from models.learners.exp3 import Exp3


def _autocheckpoint(database: Database) -> int:
    with database.engine.connect() as connection:
        return int(connection.exec_driver_sql("PRAGMA wal_autocheckpoint").scalar_one())


def _write(database: Database, rows: int) -> None:
    for n in range(rows):
        with database.writing() as db:
            db.execute(text("INSERT INTO t (v) VALUES (:v)"), {"v": "x" * 500 + str(n)})
            db.commit()


def test_a_server_database_checkpoints_in_the_background(tmp_path: Path) -> None:
    database = Database(
        f"sqlite:///{tmp_path}/c.sqlite3", sqlite_synchronous="NORMAL", background_checkpoints=True
    )
    try:
        assert _autocheckpoint(database) == WAL_AUTOCHECKPOINT_PAGES
        with database.writing() as db:
            db.execute(text("CREATE TABLE t (id INTEGER PRIMARY KEY, v TEXT)"))
            db.commit()
        _write(database, 50)
        checkpointer = database.checkpointer
        assert checkpointer is not None
        busy, frames, copied = checkpointer.checkpoint()
        assert busy == 0 and frames > 0 and copied == frames
        checkpointer.interval = 0.02
        database.start_background_work()
        runs = checkpointer.runs
        _write(database, 50)
        deadline = time.monotonic() + 60
        while checkpointer.runs < runs + 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        database.stop_background_work()
        busy, frames, copied = checkpointer.checkpoint()
        assert checkpointer.runs >= runs + 2 and busy == 0 and copied == frames
        with database.writing() as db:
            assert db.execute(text("SELECT count(*) FROM t")).scalar_one() == 100
    finally:
        database.dispose()


def test_other_databases_keep_sqlites_own_checkpoints(tmp_path: Path) -> None:
    database = Database(f"sqlite:///{tmp_path}/c.sqlite3")
    try:
        assert database.checkpointer is None and _autocheckpoint(database) == 1000
        database.start_background_work()  # nothing to start
        database.stop_background_work()
    finally:
        database.dispose()


def test_writers_queue_until_the_previous_commit_has_returned(tmp_path: Path) -> None:
    """With SQLite's busy handler off, a writer let in before the previous COMMIT finished would
    fail at once with 'database is locked': the in-process queue must be the only wait."""
    database = Database(f"sqlite:///{tmp_path}/q.sqlite3", sqlite_synchronous="FULL")

    @event.listens_for(database.engine, "connect")
    def _no_busy_wait(dbapi_connection: Any, _record: Any) -> None:
        dbapi_connection.execute("PRAGMA busy_timeout=0")

    try:
        with database.writing() as db:
            db.execute(text("CREATE TABLE t (id INTEGER PRIMARY KEY, v TEXT)"))
            db.commit()
        failures: list[BaseException] = []

        def writer() -> None:
            try:
                _write(database, 60)
            except BaseException as exc:  # reported below
                failures.append(exc)

        threads = [threading.Thread(target=writer) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert failures == []
        with database.writing() as db:
            assert db.execute(text("SELECT count(*) FROM t")).scalar_one() == 240
    finally:
        database.dispose()


def test_the_writer_queue_is_held_through_commit_and_freed_by_rollback(tmp_path: Path) -> None:
    database = Database(f"sqlite:///{tmp_path}/g.sqlite3")
    held_at_commit: list[bool] = []

    @event.listens_for(database.engine, "commit")
    def _before_driver_commit(connection: Any) -> None:
        held_at_commit.append(connection.connection.driver_connection.writers.locked())

    try:
        with database.writing() as db:
            db.execute(text("CREATE TABLE t (id INTEGER PRIMARY KEY)"))
            gate = db.connection().connection.driver_connection.writers
            assert gate.locked()
            db.commit()
        assert held_at_commit == [True] and not gate.locked()
        with database.writing() as db:
            db.execute(text("INSERT INTO t DEFAULT VALUES"))
            assert gate.locked()
        assert not gate.locked()  # closed without commit: the pool's rollback frees it
        with database.read_session() as db:
            assert db.execute(text("SELECT count(*) FROM t")).scalar_one() == 0
            assert not gate.locked()  # readers never take it
    finally:
        database.dispose()


def test_each_database_keeps_its_own_live_learners(tmp_path: Path) -> None:
    """Row ids repeat between databases: a learner cached for one must never serve the other."""
    first = Database(f"sqlite:///{tmp_path}/first.sqlite3")
    second = Database(f"sqlite:///{tmp_path}/second.sqlite3")
    try:
        with first.read_session() as reading, first.write_session() as writing:
            shared = learner_cache.of(reading)
            assert learner_cache.of(writing) is shared  # one cache across a database's sessions
            shared.put(1, 3, Exp3(3, gamma=0.1))
        with second.write_session() as other:
            rebuilt = Exp3(3, gamma=0.2)
            assert learner_cache.of(other).take(1, 3, lambda: rebuilt) is rebuilt
    finally:
        first.dispose()
        second.dispose()
