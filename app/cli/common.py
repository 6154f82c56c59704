"""What the command modules share: the ``--json`` flag, one-object output, opening the database.

Like every module under app/cli/, this one imports at its top only what ``trustlab --help``
needs (docs/development.md, "What a command may import"): the database layer is imported
when a command opens the database, not when the command line is built.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Annotated

import typer

from app.errors import InvalidInput

if TYPE_CHECKING:
    from app.db import Database
    from app.settings import Settings

JsonFlag = Annotated[bool, typer.Option("--json", help="Print one JSON object.")]


def read_settings() -> Settings:
    """The settings, read from the environment (and ``.env``) now."""
    from app.settings import Settings

    return Settings()


def open_database(settings: Settings) -> Database:
    """The configured database, after checking it answers (DatabaseUnavailable otherwise)."""
    from app.db import Database

    database = Database(settings.database_url, sqlite_synchronous=settings.sqlite_synchronous)
    database.ping()
    return database


def require_current_schema(database: Database) -> None:
    """Refuse to work on a database whose schema is behind (or ahead of) the code."""
    from app import schema

    current, head = schema.current_revision(database), schema.head_revision()
    if current != head:
        raise InvalidInput(
            f"the database schema is at {current or 'nothing'} but this trustlab needs {head}: "
            "run `trustlab db upgrade` (or `trustlab init`) first"
        )


def emit_json(value: object) -> None:
    """Print exactly one JSON object."""
    typer.echo(json.dumps(value, default=str, sort_keys=True))
