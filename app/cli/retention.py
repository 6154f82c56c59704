"""``trustlab retention``: each study's retention deadline, and anonymising or erasing what is due.

``status`` lists every study that declares ``[retention]``; ``run`` acts on what is due today
(``--dry-run`` only says so, and ``--as-of`` asks about another day). A lab schedules ``run``
daily (docs/data-protection.md, "Retention").
"""

from __future__ import annotations

import sys
from datetime import UTC, datetime
from typing import Annotated

import typer

from app.cli.common import JsonFlag, emit_json, open_database, require_current_schema
from app.errors import InvalidInput

retention_cli = typer.Typer(
    help="Retention deadlines: anonymise or erase identifiable data when it is due.",
    no_args_is_help=True,
)


def register(cli: typer.Typer) -> None:
    """Attach these commands to the top-level ``trustlab`` command."""
    cli.add_typer(retention_cli, name="retention")


def _day(text: str | None) -> datetime | None:
    if text is None:
        return None
    try:
        day = datetime.strptime(text, "%Y-%m-%d")
    except ValueError:
        raise InvalidInput(f"--as-of {text!r} is not a date: write YYYY-MM-DD") from None
    return day.replace(tzinfo=UTC)


@retention_cli.command("run")
def run(
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="Only say what is due; change nothing.")
    ] = False,
    as_of: Annotated[
        str | None,
        typer.Option(help="With --dry-run: what would be due on this day (YYYY-MM-DD)."),
    ] = None,
    study: Annotated[str | None, typer.Option(help="Only this study.")] = None,
    yes: Annotated[bool, typer.Option("--yes", help="Do not ask before changing data.")] = False,
    as_json: JsonFlag = False,
) -> None:
    """Anonymise or erase every participant whose study's retention period has run out."""
    from app.services.audit import Actor
    from app.services.privacy import retention
    from app.settings import Settings
    from app.tables import utcnow

    day = _day(as_of)
    if day is not None and not dry_run:
        raise InvalidInput("--as-of only with --dry-run: a run acts on today's date")
    settings = Settings()
    database = open_database(settings)
    require_current_schema(database)
    now = day or utcnow()
    if not dry_run:
        with database.read_session() as db:
            planned = retention.run(
                db,
                now=now,
                actor=Actor.command_line(),
                secret=settings.secret,
                dry_run=True,
                study_name=study,
            )
        due = [state for state in planned if state.due and state.participants]
        if due and not yes:
            if not sys.stdin.isatty():
                raise InvalidInput("this run changes data for good: add --yes to confirm")
            for state in due:
                typer.echo(state.describe())
            typer.confirm("Go ahead? This cannot be undone", abort=True)
    with database.writing() as db:
        report = retention.run(
            db,
            now=now,
            actor=Actor.command_line(),
            secret=settings.secret,
            dry_run=dry_run,
            study_name=study,
        )
    if as_json:
        emit_json(
            {"dry_run": dry_run, "as_of": now.isoformat(), "studies": [s.to_json() for s in report]}
        )
        return
    if not report:
        typer.echo("no study declares a retention period ([retention] in its protocol)")
    for state in report:
        line = state.describe()
        if state.done:
            participants = state.done.get("participants", 0)
            line = f"{state.study}: {state.then}d {participants} participant" + (
                "s" if participants != 1 else ""
            )
        typer.echo(line)
