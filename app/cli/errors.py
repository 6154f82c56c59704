"""Turning exceptions into one-line messages and exit codes."""

from __future__ import annotations

import sys
from typing import Any, NoReturn

import typer
from sqlalchemy.exc import OperationalError
from typer.core import TyperGroup

from app.errors import DatabaseUnavailable, InvalidInput, TrustlabError


def fail(message: str, code: int = 1) -> NoReturn:
    """Print ``error: message`` to stderr and exit with ``code``."""
    first, *rest = message.splitlines() or [""]
    typer.echo(f"error: {first}", err=True)
    for line in rest:
        typer.echo(f"  {line}", err=True)
    raise typer.Exit(code)


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
        except OperationalError as exc:
            reason = str(exc.orig).strip().splitlines()[0] if exc.orig else str(exc)
            fail(DatabaseUnavailable(f"the database failed: {reason}").message, 1)
        except KeyboardInterrupt:
            print(file=sys.stderr)
            raise typer.Exit(130) from None
