"""Alembic environment: the only way trustlab's schema changes.

Run through ``trustlab db upgrade|downgrade|current`` (app/schema.py), which hands over an open
connection; plain ``alembic`` on the command line works too and reads TRUSTLAB_DATABASE_URL via the
settings object. SQLite gets batch mode (it cannot ALTER most things in place); PostgreSQL takes an
advisory lock so that several workers starting at once migrate one after another.
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import Connection, text

from app.db import create_db_engine
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
    )
    if connection.dialect.name == "postgresql":
        connection.execute(text("SELECT pg_advisory_xact_lock(:id)"), {"id": MIGRATION_LOCK_ID})
    with context.begin_transaction():
        context.run_migrations()


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
