"""Turning exceptions into one-line messages and exit codes."""

from __future__ import annotations

import sys
from typing import Any, NoReturn

import typer
from typer.core import TyperGroup

from app.errors import DatabaseUnavailable, InvalidInput, TrustlabError


def fail(message: str, code: int = 1) -> NoReturn:
    """Print ``error: message`` to stderr and exit with ``code``."""
    first, *rest = message.splitlines() or [""]
    typer.echo(f"error: {first}", err=True)
    for line in rest:
        typer.echo(f"  {line}", err=True)
    raise typer.Exit(code)


def _database_failure(exc: Exception) -> Any | None:
    """``exc`` if it is SQLAlchemy's OperationalError (the database failed), else None.

    Looked up rather than imported: only a command that opened the database can meet one, and
    the commands that need no database should not load SQLAlchemy to find out."""
    errors = sys.modules.get("sqlalchemy.exc")
    return exc if errors is not None and isinstance(exc, errors.OperationalError) else None


class ErrorsAsMessages(TyperGroup):
    """A command group that reports expected errors as messages (exit 1 refused, 2 bad input)."""

    def invoke(self, ctx: Any) -> Any:  # typer's vendored click.Context
        try:
            return super().invoke(ctx)
        except InvalidInput as exc:
            fail(exc.message, 2)
        except TrustlabError as exc:
            fail(exc.message, 1)
        except ValueError as exc:
            fail(str(exc), 2)
        except Exception as exc:
            failed = _database_failure(exc)
            if failed is None:
                raise
            reason = str(failed.orig).strip().splitlines()[0] if failed.orig else str(failed)
            fail(DatabaseUnavailable(f"the database failed: {reason}").message, 1)
        except KeyboardInterrupt:
            print(file=sys.stderr)
            raise typer.Exit(130) from None
