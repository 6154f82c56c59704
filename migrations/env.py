"""Alembic environment: the only way trustlab's schema changes.

Run through ``trustlab db upgrade|downgrade|current`` (app/schema.py), which hands over an open
connection; plain ``alembic`` on the command line works too and reads TRUSTLAB_DATABASE_URL via the
settings object. SQLite gets batch mode (it cannot ALTER most things in place); PostgreSQL takes an
advisory lock so that several workers starting at once migrate one after another.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Any

from alembic import context
from alembic.runtime.migration import MigrationContext, MigrationInfo
from sqlalchemy import Connection, text

from app.db import create_db_engine
from app.errors import Conflict
from app.settings import Settings
from app.tables import Base

MIGRATION_LOCK_ID = 0x7472757374  # "trust": one advisory lock id for every trustlab database


def _run(connection: Connection) -> None:
    is_sqlite = connection.dialect.name == "sqlite"
    context.configure(
        connection=connection,
        target_metadata=Base.metadata,
        render_as_batch=is_sqlite,
        compare_type=True,
        on_version_apply=_check_foreign_keys if is_sqlite else None,
    )
    if not is_sqlite:
        connection.execute(text("SELECT pg_advisory_xact_lock(:id)"), {"id": MIGRATION_LOCK_ID})
        with context.begin_transaction():
            context.run_migrations()
        return
    # SQLite's batch mode copies a table into a new one, drops the old and renames the copy:
    # with foreign keys enforced, dropping a table other tables' keys point at fails (0021).
    # As SQLite's own procedure for such changes says: keys off (only outside a transaction, so
    # on the driver's connection before any BEGIN), every key checked before each migration's
    # commit (Alembic commits each one on its own on SQLite), and on again for whoever uses the
    # connection next.
    _sqlite_foreign_keys(connection, on=False)
    try:
        with context.begin_transaction():
            context.run_migrations()
    finally:
        if connection.in_transaction():
            connection.rollback()
        _sqlite_foreign_keys(connection, on=True)


def _check_foreign_keys(
    ctx: MigrationContext, step: MigrationInfo, heads: Collection[Any], run_args: Mapping[str, Any]
) -> None:
    """After each SQLite migration, inside its transaction: refuse it if any key points nowhere."""
    assert ctx.connection is not None
    broken = ctx.connection.exec_driver_sql("PRAGMA foreign_key_check").all()
    if broken:
        raise Conflict(
            f"after this migration {len(broken)} rows' keys would point nowhere "
            f"(first: {tuple(broken[0])}); it was not applied"
        )


def _sqlite_foreign_keys(connection: Connection, *, on: bool) -> None:
    """Switch SQLite's key enforcement on the driver's connection (a no-op inside a transaction,
    so never through SQLAlchemy, whose first statement begins one)."""
    driver = connection.connection.driver_connection
    assert driver is not None
    driver.execute(f"PRAGMA foreign_keys={'ON' if on else 'OFF'}")


def run_migrations_online() -> None:
    """Migrate over the connection we were given, or one to the configured database."""
    connection = context.config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    url = context.config.get_main_option("sqlalchemy.url") or Settings().database_url
    engine = create_db_engine(url)
    try:
        with engine.connect() as new_connection:
            _run(new_connection)
            new_connection.commit()
    finally:
        engine.dispose()


if context.is_offline_mode():
    raise SystemExit("offline (SQL script) migrations are not supported; connect to a database")
run_migrations_online()
