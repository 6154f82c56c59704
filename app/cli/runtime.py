"""Commands for the live experiment: stations, device keys and ``verify``."""

from __future__ import annotations

from typing import Annotated

import typer

from app.cli.common import JsonFlag, emit_json, open_database, require_current_schema
from app.errors import NotFound

station_cli = typer.Typer(help="Stations where robots meet participants.", no_args_is_help=True)
device_cli = typer.Typer(help="Robot clients' API keys.", no_args_is_help=True)


MAX_ROW_ID = 2**63 - 1
"""app.inputs.MAX_ROW_ID, for ``--help``: repeated here because app.inputs loads pydantic, which
showing help does not need (tests/app/test_cli.py checks that they agree)."""


def register(cli: typer.Typer) -> None:
    """Attach these commands to the top-level ``trustlab`` command."""
    cli.add_typer(station_cli, name="station")
    cli.add_typer(device_cli, name="device")
    cli.command("verify")(verify_command)


@station_cli.command("create")
def station_create(
    name: Annotated[str, typer.Argument(help="e.g. lab-1")],
    site: Annotated[
        str,
        typer.Option(
            help="The site it belongs to (one a study declares): only its participants are "
            "seated there, and accounts limited to other sites do not see it. Default: shared."
        ),
    ] = "",
) -> None:
    """Create a station, of a site or shared by every site."""
    from app.services.audit import Actor
    from app.services.sessions import stations
    from app.settings import Settings

    database = open_database(Settings())
    require_current_schema(database)
    with database.writing() as db:
        stations.create_station(db, name=name, site=site, actor=Actor.command_line())
    typer.echo(f"created station {name!r}" + (f" of site {site.strip()!r}" if site.strip() else ""))


@station_cli.command("list")
def station_list(as_json: JsonFlag = False) -> None:
    """List stations, their sites and who is assigned to them."""
    from app.services.sessions import stations
    from app.settings import Settings

    database = open_database(Settings())
    require_current_schema(database)
    with database.read_session() as db:
        rows = [
            {
                "name": s.name,
                "site": s.site,
                "participant": s.participant.code if s.participant else None,
            }
            for s in stations.list_stations(db)
        ]
    if as_json:
        emit_json({"stations": rows})
        return
    if not rows:
        typer.echo("no stations yet: `trustlab station create NAME`")
    for row in rows:
        site = row["site"] or "(shared)"
        typer.echo(f"{row['name']:<24} {site:<16} {row['participant'] or '(free)'}")


@device_cli.command("create")
def device_create(
    station: Annotated[str, typer.Option(help="Station name (created if it does not exist).")],
    label: Annotated[str, typer.Option(help="What the device is, e.g. pepper.")] = "robot",
    as_json: JsonFlag = False,
) -> None:
    """Issue an API key for a robot client at a station (printed once)."""
    from app.services.audit import Actor
    from app.services.sessions import stations
    from app.settings import Settings

    database = open_database(Settings())
    require_current_schema(database)
    actor = Actor.command_line()
    created_station = False
    with database.writing() as db:
        try:
            stations.get_station(db, station)
        except NotFound:
            db.rollback()
            stations.create_station(db, name=station, actor=actor)
            created_station = True
        issued = stations.issue_device_key(db, station_name=station, label=label, actor=actor)
        payload = {
            "device_id": issued.device.id,
            "station": station,
            "label": issued.device.label,
            "key": issued.key,
            "station_created": created_station,
        }
    if as_json:
        emit_json(payload)
        return
    if created_station:
        typer.echo(f"created station {station!r}")
    typer.echo(f"device {payload['device_id']} ({label}) at station {station!r}; its key:")
    typer.echo(f"  {issued.key}")
    typer.echo("  (shown only this once; give it to the robot client)")


@device_cli.command("revoke")
def device_revoke(
    device_id: Annotated[
        int, typer.Argument(min=1, max=MAX_ROW_ID, help="The id `device create` printed.")
    ],
) -> None:
    """Revoke a device key at once."""
    from app.services.audit import Actor
    from app.services.sessions import stations
    from app.settings import Settings

    database = open_database(Settings())
    require_current_schema(database)
    with database.writing() as db:
        stations.revoke_device(db, device_id=device_id, actor=Actor.command_line())
    typer.echo(f"revoked device {device_id}")


def verify_command(
    study: Annotated[str, typer.Option(help="Study name.")],
    as_json: JsonFlag = False,
) -> None:
    """Replay every learner from its step log and check the study's integrity (exit 1 if not)."""
    from app.services.sessions import verify
    from app.settings import Settings
    from app.wording import counted

    database = open_database(Settings())
    require_current_schema(database)
    with database.read_session() as db:
        report = verify.verify_study(db, study_name=study)
    if as_json:
        emit_json(report.to_json())
    else:
        counts = (
            counted(report.participants, "participant"),
            counted(report.learners, "learner"),
            counted(report.steps, "step"),
            counted(report.answers, "answer"),
        )
        typer.echo(f"study {report.study!r}: {', '.join(counts)} replayed")
        for finding in report.findings:
            who = f" {finding.participant}" if finding.participant else ""
            typer.echo(f"  [{finding.check}]{who}: {finding.detail}")
        typer.echo(
            "ok: every learner matches its replay"
            if report.ok
            else f"{counted(len(report.findings), 'problem')} found"
        )
    if not report.ok:
        raise typer.Exit(1)
