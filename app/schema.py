"""Schema migrations, driven programmatically (``trustlab db …``, first start, tests).

Every command that opens the database first compares its revision with the code's
(:func:`current_revision`, :func:`head_revision`); both are read without Alembic, whose import
and script directory (which imports every migration) cost a command more than its own work.
Alembic is imported only to migrate.
"""

from __future__ import annotations

import ast
from typing import TYPE_CHECKING

from sqlalchemy import text

from app.db import Database
from app.settings import REPO_ROOT

if TYPE_CHECKING:
    from alembic.config import Config

MIGRATIONS_DIR = REPO_ROOT / "migrations"
VERSION_TABLE = "alembic_version"
"""Where Alembic keeps the database's revision (its default name; migrations/env.py keeps it)."""


def alembic_config() -> Config:
    """An Alembic configuration pointing at trustlab's migrations."""
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    return config


def head_revision() -> str:
    """The newest revision the code knows: the one that no migration names as its parent.

    Read from the ``revision`` and ``down_revision`` assignments of migrations/versions/*.py,
    as Alembic's script directory reads them (tests/app/test_schema.py checks the two agree).
    """
    parents: dict[str, str | None] = {}
    for path in sorted((MIGRATIONS_DIR / "versions").glob("*.py")):
        assigned: dict[str, ast.expr] = {}
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.value:
                assigned[node.target.id] = node.value
            elif isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name):
                assigned[node.targets[0].id] = node.value
        if "revision" in assigned:
            parent = ast.literal_eval(assigned["down_revision"])
            parents[ast.literal_eval(assigned["revision"])] = parent
    heads = set(parents) - set(parents.values())
    if len(heads) != 1:
        raise RuntimeError(f"expected one head under {MIGRATIONS_DIR}, found {sorted(heads)}")
    return heads.pop()


def current_revision(database: Database) -> str | None:
    """The revision the database is at (None when it was never migrated)."""
    with database.engine.connect() as connection:
        if not database.engine.dialect.has_table(connection, VERSION_TABLE):
            return None
        rows = connection.execute(text(f"SELECT version_num FROM {VERSION_TABLE}")).all()
    if len(rows) > 1:
        raise RuntimeError(f"the database is at several revisions: {[row[0] for row in rows]}")
    return str(rows[0][0]) if rows else None


def upgrade(database: Database, revision: str = "head") -> None:
    """Apply migrations up to ``revision``."""
    from alembic import command

    _run(database, command.upgrade, revision)


def downgrade(database: Database, revision: str) -> None:
    """Revert migrations down to ``revision`` ('base' empties the database)."""
    from alembic import command

    _run(database, command.downgrade, revision)


def _run(database: Database, action: object, revision: str) -> None:
    config = alembic_config()
    with database.engine.connect() as connection:
        config.attributes["connection"] = connection
        action(config, revision)  # type: ignore[operator]
        connection.commit()


def create_append_only_guard(table: str) -> None:
    """Inside a migration: make ``table`` refuse UPDATE, DELETE (and TRUNCATE on PostgreSQL).

    Since revision 0016 ``prompt``, ``answer`` and ``audit_event`` carry the guard of
    :func:`create_erasable_guard` instead; a migration that rebuilds one of them re-adds that."""
    from alembic import op

    if op.get_bind().dialect.name == "postgresql":
        op.execute(
            "CREATE OR REPLACE FUNCTION trustlab_append_only() RETURNS trigger "
            "LANGUAGE plpgsql AS $$ BEGIN "
            "RAISE EXCEPTION '% is append-only', TG_TABLE_NAME; END $$"
        )
        op.execute(
            f"CREATE TRIGGER {table}_append_only BEFORE UPDATE OR DELETE ON {table} "
            "FOR EACH ROW EXECUTE FUNCTION trustlab_append_only()"
        )
        op.execute(
            f"CREATE TRIGGER {table}_no_truncate BEFORE TRUNCATE ON {table} "
            "FOR EACH STATEMENT EXECUTE FUNCTION trustlab_append_only()"
        )
    else:
        for verb in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER {table}_no_{verb.lower()} BEFORE {verb} ON {table} "
                f"BEGIN SELECT RAISE(ABORT, '{table} is append-only'); END"
            )


def drop_append_only_guard(table: str) -> None:
    """Inside a migration: remove what :func:`create_append_only_guard` added."""
    from alembic import op

    if op.get_bind().dialect.name == "postgresql":
        op.execute(f"DROP TRIGGER IF EXISTS {table}_append_only ON {table}")
        op.execute(f"DROP TRIGGER IF EXISTS {table}_no_truncate ON {table}")
    else:
        op.execute(f"DROP TRIGGER IF EXISTS {table}_no_update")
        op.execute(f"DROP TRIGGER IF EXISTS {table}_no_delete")


ERASURE_MARKER = "erasure_in_progress"
"""The table whose rows, present only inside an erasure's transaction, open the guards of
:func:`create_erasable_guard` for one participant (app.services.privacy.erasure)."""

ERASABLE_TABLES = {
    "prompt": "participant_id",
    "answer": "participant_id",
    "audit_event": "study_id",
}
"""Append-only tables an erasure may change, and the column naming the marked rows: a prompt or
answer of the participant being erased; an audit event of their study (only the events that name
the participant are rewritten)."""


def create_erasable_guard(table: str) -> None:
    """Inside a migration: make ``table`` append-only except for the rows an erasure in progress
    marks (its :data:`ERASURE_MARKER` row has the same value in :data:`ERASABLE_TABLES`' column).

    The marker rows are inserted and deleted inside the erasure's own transaction, so no other
    transaction ever sees one: for everyone else the table stays exactly as append-only as
    before. TRUNCATE (PostgreSQL) stays refused."""
    from alembic import op

    key = ERASABLE_TABLES[table]
    if op.get_bind().dialect.name == "postgresql":
        op.execute(
            "CREATE OR REPLACE FUNCTION trustlab_append_only() RETURNS trigger "
            "LANGUAGE plpgsql AS $$ BEGIN "
            "RAISE EXCEPTION '% is append-only', TG_TABLE_NAME; END $$"
        )
        op.execute(
            "CREATE OR REPLACE FUNCTION trustlab_append_only_unless_erasing() RETURNS trigger "
            "LANGUAGE plpgsql AS $$ BEGIN "
            f"IF EXISTS (SELECT 1 FROM {ERASURE_MARKER} e "
            "WHERE (to_jsonb(e) ->> TG_ARGV[0]) = (to_jsonb(OLD) ->> TG_ARGV[0])) THEN "
            "IF TG_OP = 'DELETE' THEN RETURN OLD; END IF; RETURN NEW; END IF; "
            "RAISE EXCEPTION '% is append-only', TG_TABLE_NAME; END $$"
        )
        op.execute(
            f"CREATE TRIGGER {table}_append_only BEFORE UPDATE OR DELETE ON {table} "
            f"FOR EACH ROW EXECUTE FUNCTION trustlab_append_only_unless_erasing('{key}')"
        )
        op.execute(
            f"CREATE TRIGGER {table}_no_truncate BEFORE TRUNCATE ON {table} "
            "FOR EACH STATEMENT EXECUTE FUNCTION trustlab_append_only()"
        )
    else:
        for verb in ("UPDATE", "DELETE"):
            op.execute(
                f"CREATE TRIGGER {table}_no_{verb.lower()} BEFORE {verb} ON {table} "
                f"WHEN NOT EXISTS (SELECT 1 FROM {ERASURE_MARKER} WHERE {key} = OLD.{key}) "
                f"BEGIN SELECT RAISE(ABORT, '{table} is append-only'); END"
            )
