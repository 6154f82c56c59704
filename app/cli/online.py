"""``trustlab online``: an online study's participations, for admins at the server."""

from __future__ import annotations

from typing import Annotated

import typer

from app.cli.common import open_database, read_settings, require_current_schema

online_cli = typer.Typer(help="Online studies (docs/online.md).", no_args_is_help=True)


def register(cli: typer.Typer) -> None:
    """Attach these commands to the top-level ``trustlab`` command."""
    cli.add_typer(online_cli, name="online")


@online_cli.command("find")
def find(
    study: Annotated[str, typer.Option(help="Study name.")],
    recruitment_id: Annotated[
        str, typer.Option("--id", help="The participant's ID on the recruitment platform.")
    ],
) -> None:
    """Which participant a recruitment ID is (stored only as a keyed hash); audited. With the
    code, `trustlab participant export` or `withdraw --erase` answers their request."""
    from app.online import participation
    from app.services.audit import Actor
    from app.tables import Participant

    settings = read_settings()
    database = open_database(settings)
    require_current_schema(database)

    with database.writing() as db:
        found = participation.find_by_recruitment_id(
            db,
            study_name=study,
            recruitment_id=recruitment_id,
            secret=settings.secret,
            actor=Actor.command_line(),
        )
        participant = db.get(Participant, found.participant_id) if found.participant_id else None
        code = participant.code if participant is not None else "(not enrolled)"
        typer.echo(
            f"{code}: {found.status}, joined {found.joined_at:%Y-%m-%d %H:%M} UTC"
            + (f", screened out ({found.reason})" if found.reason else "")
        )
