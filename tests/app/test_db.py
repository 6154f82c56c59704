"""SQLite's WAL is checkpointed by a server's background thread, not inside requests' commits."""

from __future__ import annotations

import time
from pathlib import Path

from sqlalchemy import text

from app.db import WAL_AUTOCHECKPOINT_PAGES, Database


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
        deadline = time.monotonic() + 10
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
