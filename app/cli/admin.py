"""Set-up and administration commands: init, serve, db, study, participant (accounts:
app.cli.accounts)."""

from __future__ import annotations

import logging
import secrets
import sys
import threading
from pathlib import Path
from typing import Annotated

import typer

from app.cli.common import JsonFlag, emit_json, open_database, read_settings, require_current_schema
from app.errors import InvalidInput

db_cli = typer.Typer(help="Database schema migrations.", no_args_is_help=True)
study_cli = typer.Typer(help="Studies.", no_args_is_help=True)
participant_cli = typer.Typer(help="Enrolment and withdrawal.", no_args_is_help=True)


def register(cli: typer.Typer) -> None:
    """Attach these commands to the top-level ``trustlab`` command."""
    cli.command("init")(init)
    cli.command("serve")(serve)
    cli.add_typer(db_cli, name="db")
    cli.add_typer(study_cli, name="study")
    cli.add_typer(participant_cli, name="participant")


def init(
    demo: Annotated[
        bool,
        typer.Option(
            "--demo/--no-demo",
            help="On an empty database, also create a demo study that the first "
            "`trustlab serve` fills with simulated participants.",
        ),
    ] = True,
) -> None:
    """Migrate the database, create the default study and, on first start, the admin account."""
    from app import schema
    from app.db import describe_url
    from app.demo import plan_demo
    from app.protocol import default_protocol
    from app.services import studies
    from app.services.audit import Actor
    from app.services.staff import users
    from app.tables import Role

    settings = read_settings()
    database = open_database(settings)
    before = schema.current_revision(database)
    schema.upgrade(database)
    after = schema.current_revision(database)
    typer.echo(
        f"database {describe_url(settings.database_url)}: schema at {after}"
        + ("" if before == after else f" (was {before or 'empty'})")
    )
    actor = Actor.system("trustlab init")
    once: list[str] = []
    with database.writing() as db:
        empty = studies.count_studies(db) == 0
        if empty:
            study = studies.create_study(
                db, name=studies.DEFAULT_STUDY_NAME, loaded=default_protocol(), actor=actor
            )
            typer.echo(f"created the default study {study.name!r}: {study.title}")
        if users.count_users(db) == 0:
            given = settings.admin_password
            password = given.get_secret_value() if given else secrets.token_urlsafe(12)
            users.create_user(
                db,
                username=settings.admin_username,
                role=Role.ADMIN,
                password=password,
                actor=actor,
            )
            typer.echo(f"created the admin account {settings.admin_username!r}")
            if given is None:
                once = [
                    f"the admin account {settings.admin_username!r}'s password: {password}",
                    "  (shown only this once: write it down, then add personal accounts)",
                ]
        if empty and demo:
            plan = plan_demo(db, settings, actor)
            typer.echo(
                f"created the demo study {plan.study!r}: the first `trustlab serve` fills it "
                f"with {plan.participants} simulated participants"
            )
    database.dispose()
    # Last, so that nothing init prints scrolls it away (and `serve` keeps its log quiet while
    # the demo fills, app.demo).
    for line in once:
        typer.echo(line)


DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8000
"""The settings' defaults, named in ``serve --help``: repeated here because showing help
imports no settings (tests/app/test_cli.py checks that they agree)."""


def serve(
    host: Annotated[
        str | None,
        typer.Option(help=f"Interface to listen on (default: TRUSTLAB_HOST, else {DEFAULT_HOST})."),
    ] = None,
    port: Annotated[
        int | None,
        typer.Option(help=f"Port to listen on (default: TRUSTLAB_PORT, else {DEFAULT_PORT})."),
    ] = None,
    workers: Annotated[int, typer.Option(min=1, help="Worker processes (PostgreSQL for >1).")] = 1,
) -> None:
    """Serve the dashboard, the tablet pages and the API."""
    import uvicorn

    from app import access_log
    from app.demo import QuietWhileFilling, pending_demo, run_demo
    from app.settings import KEEP_ALIVE_SECONDS

    settings = read_settings()
    database = open_database(settings)
    require_current_schema(database)
    database.dispose()
    if workers > 1 and settings.is_sqlite:
        raise InvalidInput("several workers need PostgreSQL; SQLite serves from one process")
    host = host or settings.host
    port = port or settings.port
    typer.echo(f"trustlab serving on http://{host}:{port} (Ctrl-C stops)")
    plan = pending_demo(settings)
    if plan is not None:
        local = "127.0.0.1" if host in ("0.0.0.0", "::") else host
        quiet = QuietWhileFilling()
        logging.getLogger("uvicorn.access").addFilter(quiet)  # uvicorn's set-up keeps filters
        threading.Thread(
            target=run_demo,
            args=(plan, f"http://{local}:{port}", settings, typer.echo, quiet),
            name="demo-bots",
            daemon=True,
        ).start()
    uvicorn.run(
        "app.main:create_app",
        factory=True,
        host=host,
        port=port,
        workers=workers,
        proxy_headers=False,  # the app trusts only TRUSTLAB_TRUSTED_PROXIES (app.main)
        log_level="info",
        # No participant codes or tablet tokens in the access log unless asked (app.access_log).
        log_config=access_log.log_config(settings.access_log),
        access_log=settings.access_log != access_log.AccessLog.OFF,
        timeout_graceful_shutdown=settings.shutdown_grace_seconds,
        timeout_keep_alive=KEEP_ALIVE_SECONDS,
    )


@db_cli.command("upgrade")
def db_upgrade(revision: Annotated[str, typer.Argument(help="Target revision.")] = "head") -> None:
    """Apply migrations (to the newest by default)."""
    from app import schema

    database = open_database(read_settings())
    schema.upgrade(database, revision)
    typer.echo(f"schema at {schema.current_revision(database)}")


@db_cli.command("downgrade")
def db_downgrade(
    revision: Annotated[str, typer.Argument(help="Target revision ('base' removes everything).")],
) -> None:
    """Revert migrations down to a revision."""
    from app import schema

    database = open_database(read_settings())
    schema.downgrade(database, revision)
    typer.echo(f"schema at {schema.current_revision(database) or 'base (empty)'}")


@db_cli.command("current")
def db_current() -> None:
    """Show the database's schema revision and the code's."""
    from app import schema

    database = open_database(read_settings())
    current, head = schema.current_revision(database), schema.head_revision()
    state = (
        "up to date" if current == head else f"behind: run `trustlab db upgrade` to reach {head}"
    )
    typer.echo(f"{current or 'base (empty)'} ({state})")


@db_cli.command("backup")
def db_backup(
    out: Annotated[Path, typer.Option(help="The backup file to create.")],
) -> None:
    """Back up the whole database (SQLite online backup; pg_dump for PostgreSQL)."""
    from app import backup
    from app.db import describe_url
    from app.services import audit
    from app.services.audit import Actor

    settings = read_settings()
    database = open_database(settings)
    database.dispose()
    written = backup.backup(settings.database_url, out)
    with open_database(settings).writing() as db:
        audit.record(
            db,
            actor=Actor.command_line(),
            action="db.backed_up",
            # Absolute: an erasure run from another folder lists it (app.services.privacy.erasure).
            details={"file": str(written.resolve())},
        )
        db.commit()
    typer.echo(
        f"backed up {describe_url(settings.database_url)} to {written} "
        f"({written.stat().st_size // 1024} KiB)"
    )


@db_cli.command("restore")
def db_restore(
    source: Annotated[Path, typer.Argument(help="A backup made by `trustlab db backup`.")],
    yes: Annotated[bool, typer.Option("--yes", help="Do not ask for confirmation.")] = False,
) -> None:
    """Replace the database's content with a backup (stop the server first)."""
    from app import backup, schema
    from app.db import describe_url
    from app.services import audit
    from app.services.audit import Actor

    settings = read_settings()
    where = describe_url(settings.database_url)
    if not yes:
        if not sys.stdin.isatty():
            raise InvalidInput(f"restoring replaces everything in {where}: add --yes to confirm")
        typer.confirm(f"Replace everything in {where} with {source}?", abort=True)
    open_database(settings).dispose()
    backup.restore(settings.database_url, source)
    database = open_database(settings)
    revision = schema.current_revision(database)
    if revision is None:
        raise InvalidInput(f"{source} holds no trustlab schema")
    with database.writing() as db:
        audit.record(
            db,
            actor=Actor.command_line(),
            action="db.restored",
            details={"file": str(source), "revision": revision},
        )
        db.commit()
    typer.echo(
        f"restored {where} from {source}: schema at {revision}; "
        "run `trustlab verify --study NAME` to check each study"
    )


@study_cli.command("create")
def study_create(
    name: Annotated[str, typer.Option(help="Short unique name, e.g. pilot-2026.")],
    protocol: Annotated[
        Path | None, typer.Option(help="Start from this protocol TOML file.")
    ] = None,
    shipped: Annotated[
        str,
        typer.Option(help="Start from a shipped protocol, by file name (`study protocols`)."),
    ] = "",
    copy_of: Annotated[
        str, typer.Option(help="Start from a copy of this study's protocol, comments and all.")
    ] = "",
    title: Annotated[
        str, typer.Option(help="Shown on every page (default: the protocol's title).")
    ] = "",
    phase: Annotated[
        str,
        typer.Option(
            help="live (enrols real participants now), pilot, or draft (edit and preview first)."
        ),
    ] = "live",
    as_json: JsonFlag = False,
) -> None:
    """Create a study from a protocol file, a shipped protocol or a copy of a study's."""
    from app.protocol import load_protocol_file
    from app.services import studies
    from app.services.audit import Actor
    from app.services.design import study_phases

    starts_in = study_phases.parse_phase(phase)

    chosen = [
        option
        for option, given in (
            ("--protocol", protocol),
            ("--shipped", shipped),
            ("--copy-of", copy_of),
        )
        if given
    ]
    if len(chosen) != 1:
        raise InvalidInput(
            "say what the study starts from: one of --protocol, --shipped, --copy-of"
        )
    # A file is read and checked before the database is opened: its problems come first.
    if protocol is not None:
        loaded, started_from = load_protocol_file(protocol), f"file {protocol}"
    database = open_database(read_settings())
    require_current_schema(database)
    with database.writing() as db:
        if protocol is None:
            loaded, started_from = studies.starting_protocol(
                db, shipped=shipped or None, copy_of=copy_of or None
            )
        study = studies.create_study(
            db,
            name=name,
            loaded=loaded,
            actor=Actor.command_line(),
            title=title,
            started_from=started_from,
            phase=starts_in,
        )
        if as_json:
            emit_json(
                {
                    "name": study.name,
                    "title": study.title,
                    "sha256": study.protocol_sha256,
                    "phase": study.phase,
                }
            )
        else:
            note = "" if starts_in == "live" else f" ({study.phase})"
            typer.echo(f"created study {study.name!r}{note}: {study.title}")


@study_cli.command("phase")
def study_phase(
    name: Annotated[str, typer.Argument(help="The study.")],
    phase: Annotated[str, typer.Argument(help="draft, pilot or live (live cannot be undone).")],
    yes: Annotated[bool, typer.Option("--yes", help="Do not ask before going live.")] = False,
) -> None:
    """Move a study between draft, pilot and live (audited). Going live freezes its protocol
    and starts its concealed sequence; pilot participants stay marked as pilot."""
    from app.services.audit import Actor
    from app.services.design import study_phases

    target = study_phases.parse_phase(phase)
    database = open_database(read_settings())
    require_current_schema(database)
    if target == "live" and not yes:
        if not sys.stdin.isatty():
            raise InvalidInput(f"taking {name!r} live cannot be undone: add --yes to confirm")
        typer.confirm(
            f"Take {name!r} live? Its protocol is frozen and real participants enrol from "
            "now on; this cannot be undone.",
            abort=True,
        )
    with database.writing() as db:
        study = study_phases.set_phase(db, name=name, phase=target, actor=Actor.command_line())
        typer.echo(f"study {study.name!r} is {study.phase}")


@study_cli.command("reset-pilot")
def study_reset_pilot(
    name: Annotated[str, typer.Argument(help="The study whose pilot participants go.")],
    yes: Annotated[bool, typer.Option("--yes", help="Do not ask for confirmation.")] = False,
) -> None:
    """Delete every pilot participant of a study and all their data (audited). Live
    participants and the live sequence are not touched."""
    from app.services.audit import Actor
    from app.services.design import study_phases

    database = open_database(read_settings())
    require_current_schema(database)
    if not yes:
        if not sys.stdin.isatty():
            raise InvalidInput(f"resetting the pilot of {name!r} deletes data: add --yes")
        typer.confirm(
            f"Delete every pilot participant of {name!r} and their data? This cannot be undone.",
            abort=True,
        )
    with database.writing() as db:
        reset = study_phases.reset_pilot(db, name=name, actor=Actor.command_line())
        typer.echo(reset.describe())


@study_cli.command("protocols")
def study_protocols(as_json: JsonFlag = False) -> None:
    """The protocols trustlab ships, to start a study from (`study create --shipped FILE`)."""
    from app.protocol import shipped_protocol, shipped_protocol_files

    rows = []
    for file in shipped_protocol_files():
        info = shipped_protocol(file).protocol.study
        rows.append({"file": file, "title": info.title, "languages": info.languages})
    if as_json:
        emit_json(rows)
        return
    for row in rows:
        typer.echo(f"{row['file']:<34} {', '.join(row['languages']):<8} {row['title']}")


@study_cli.command("list")
def study_list(as_json: JsonFlag = False) -> None:
    """List studies with their enrolment per condition."""
    from app.services import studies
    from app.services.audit import Actor

    database = open_database(read_settings())
    require_current_schema(database)
    with database.read_session() as db:
        rows = [
            {
                "name": s.name,
                "title": s.title,
                "status": s.status,
                "phase": s.phase,
                "created_at": s.created_at.isoformat(),
                "enrolment": studies.enrolment_counts(db, s, actor=Actor.command_line()),
            }
            for s in studies.list_studies(db)
        ]
    if as_json:
        emit_json({"studies": rows})
        return
    if not rows:
        typer.echo("no studies yet: `trustlab init` creates the default one")
    for row in rows:
        enrolled: dict[str, dict[str, int]] = row["enrolment"]  # type: ignore[assignment]
        counts = ", ".join(
            f"{condition} {by_status['active'] + by_status['completed']}"
            for condition, by_status in enrolled.items()
        )
        typer.echo(
            f"{row['name']:<24} {row['phase']:<5} {row['status']:<7} {counts:<20} {row['title']}"
        )


@study_cli.command("unblind")
def study_unblind(
    name: Annotated[str, typer.Argument(help="The blinded study, closed for enrolment.")],
    yes: Annotated[bool, typer.Option("--yes", help="Do not ask for confirmation.")] = False,
) -> None:
    """Lift a blinded study's blinding for good (audited): staff then see its conditions and
    the learners' probabilities, confidence levels and reply history."""
    from app.services import blinding
    from app.services.audit import Actor

    database = open_database(read_settings())
    require_current_schema(database)
    if not yes:
        if not sys.stdin.isatty():
            raise InvalidInput(f"unblinding {name!r} cannot be undone: add --yes to confirm")
        typer.confirm(
            f"Unblind {name!r}? Every signed-in person will see its conditions and learners; "
            "this cannot be undone.",
            abort=True,
        )
    with database.writing() as db:
        study = blinding.unblind(db, name=name, actor=Actor.command_line())
        typer.echo(f"unblinded study {study.name!r} at {study.unblinded_at:%Y-%m-%d %H:%M} UTC")
        labels = study.neutral_labels or {}
        if labels:
            pairs = ", ".join(f"{condition} was {label}" for condition, label in labels.items())
            typer.echo(f"while blinded: {pairs}")


def _parse_strata(pairs: list[str]) -> dict[str, str]:
    strata = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise InvalidInput(f"--stratum {pair!r}: write it as key=value, e.g. gender=female")
        strata[key.strip()] = value.strip()
    return strata


@participant_cli.command("enroll")
def participant_enroll(
    study: Annotated[str, typer.Option(help="Study name.")],
    stratum: Annotated[
        list[str] | None, typer.Option(help="Stratification factor as key=value (repeatable).")
    ] = None,
    code: Annotated[
        str | None,
        typer.Option(help="Participant code (default P001, P002…; at a site SITE-001…)."),
    ] = None,
    language: Annotated[
        str | None,
        typer.Option(
            help="One of the study's languages (default: its first, or chosen on the tablet "
            "when the protocol lets participants choose)."
        ),
    ] = None,
    site: Annotated[
        str | None,
        typer.Option(help="The participant's site: one of the study's \\[sites] (required there)."),
    ] = None,
    as_json: JsonFlag = False,
) -> None:
    """Enrol a participant and reveal their allocation."""
    from app.services.audit import Actor
    from app.services.participants import enrolment

    database = open_database(read_settings())
    require_current_schema(database)
    with database.writing() as db:
        result = enrolment.enroll_participant(
            db,
            study_name=study,
            actor=Actor.command_line(),
            code=code,
            strata=_parse_strata(stratum or []),
            language=language,
            site=site,
        )
        # Not the entry's place in the allocation sequence: it is concealed while the study
        # enrols (app.services.blinding.allocation_disclosed).
        payload = {
            "code": result.participant.code,
            "condition": result.condition,
            "language": result.participant.language,
            "site": result.participant.site,
        }
    if as_json:
        emit_json(payload)
    else:
        spoken = payload["language"] or "chosen on the tablet"
        where = f" at {payload['site']}" if payload["site"] else ""
        typer.echo(
            f"enrolled {payload['code']} in {study!r}{where}: condition {payload['condition']}, "
            f"language {spoken}"
        )


@participant_cli.command("language")
def participant_language(
    study: Annotated[str, typer.Option(help="Study name.")],
    code: Annotated[str, typer.Option(help="Participant code.")],
    language: Annotated[str, typer.Option(help="One of the study's languages, e.g. sv.")],
    override_reason: Annotated[
        str,
        typer.Option(
            help="Why, when a session has already started (required then; kept in the audit "
            "log): their answers so far were given in the other language."
        ),
    ] = "",
) -> None:
    """Set a participant's language (before their first session; after it only with a reason)."""
    from app.services import studies
    from app.services.audit import Actor
    from app.services.participants import enrolment, languages
    from app.tables import Role

    database = open_database(read_settings())
    require_current_schema(database)
    with database.writing() as db:
        found = studies.get_study(db, study)
        languages.set_language(
            db,
            participant=enrolment.get_participant(
                db, found, code, actor=Actor.command_line(), for_update=True
            ),
            protocol=studies.protocol_of(found),
            study_name=study,
            language=language,
            actor=Actor.command_line(),
            actor_role=Role.ADMIN,  # whoever runs the server's command line administers it
            override_reason=override_reason,
        )
    typer.echo(f"{code} in {study!r} now takes part in {language}")


@participant_cli.command("export")
def participant_export(
    study: Annotated[str, typer.Option(help="Study name.")],
    code: Annotated[str, typer.Option(help="Participant code.")],
    out: Annotated[
        Path, typer.Option(help="Folder to write CODE.json and CODE.html into (made if missing).")
    ],
    audio: Annotated[
        bool, typer.Option("--audio", help="Include recorded answers' audio (base64 WAV).")
    ] = False,
    force: Annotated[bool, typer.Option("--force", help="Replace files that exist.")] = False,
) -> None:
    """Everything stored about one participant, as JSON and a readable HTML page (for their
    subject-access request). Owner-only files; audited."""
    import json

    from app.private_files import new_private_file, refuse_existing, refuse_link
    from app.services import audit, studies
    from app.services.audit import Actor
    from app.services.privacy import subject_access
    from app.web.templating import environment

    targets = [out / f"{code}.json", out / f"{code}.html"]
    for target in targets:
        refuse_link(target)
        if target.exists() and not force:
            raise InvalidInput(f"{target} exists; choose another folder, or --force to replace it")
        refuse_existing(target, replace=force)
    database = open_database(read_settings())
    require_current_schema(database)
    with database.read_session() as db:
        record = subject_access.participant_record(
            db, study_name=study, code=code, with_audio=audio
        )
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    page = environment.get_template("subject_access.html").render(record=record)
    for target, content in zip(
        targets, (json.dumps(record, indent=2, ensure_ascii=False), page), strict=True
    ):
        with new_private_file(target, replace=force) as draft:
            draft.write_text(content + "\n", encoding="utf-8")
    with database.writing() as db:
        audit.record(
            db,
            actor=Actor.command_line(),
            action="participant.exported",
            study_id=studies.get_study(db, study).id,
            subject=code,
            details={"audio": audio},
        )
        db.commit()
    typer.echo(f"wrote {targets[0]} and {targets[1]}")


@participant_cli.command("withdraw")
def participant_withdraw(
    study: Annotated[str, typer.Option(help="Study name.")],
    code: Annotated[str, typer.Option(help="Participant code.")],
    reason: Annotated[str, typer.Option(help="Why (kept with a kept withdrawal).")] = "",
    erase: Annotated[
        bool,
        typer.Option(
            "--erase",
            help="Erase everything they gave the study (if the protocol allows it); the "
            "allocation slot stays. Also for someone already withdrawn.",
        ),
    ] = False,
    yes: Annotated[bool, typer.Option("--yes", help="Do not ask before erasing.")] = False,
) -> None:
    """Withdraw a participant: keep the data collected so far, or --erase it."""
    from app.services.audit import Actor
    from app.services.participants import enrolment
    from app.services.privacy import erasure

    settings = read_settings()
    database = open_database(settings)
    require_current_schema(database)
    if not erase:
        with database.writing() as db:
            enrolment.withdraw_participant(
                db, study_name=study, code=code, actor=Actor.command_line(), reason=reason
            )
        typer.echo(f"withdrew {code} from {study!r} (their data is kept)")
        return
    if not yes:
        if not sys.stdin.isatty():
            raise InvalidInput(f"erasing {code} cannot be undone: add --yes to confirm")
        typer.confirm(
            f"Erase every answer, questionnaire and transcript of {code} in {study!r}? "
            "This cannot be undone",
            abort=True,
        )
    with database.writing() as db:
        result = erasure.erase_participant(
            db,
            study_name=study,
            code=code,
            actor=Actor.command_line(),
            secret=settings.secret,
            reason=reason,
        )
    removed = ", ".join(f"{table} {n}" for table, n in result.removed.items()) or "none"
    typer.echo(
        f"erased {code} from {study!r} (rows removed: {removed}); their allocation slot stays"
    )
    if result.earlier_copies:
        typer.echo(
            f"made before the erasure, these may still hold {code} "
            "(docs/data-protection.md, 'Copies made before an erasure'):"
        )
        for copy in result.earlier_copies:
            typer.echo(f"  {copy.describe()}")
