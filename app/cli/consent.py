"""``trustlab study consent``: add a new version of a study's consent text."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from app.cli.admin import study_cli
from app.cli.common import JsonFlag, emit_json, open_database, require_current_schema
from app.errors import InvalidInput


def study_consent(
    study: Annotated[str, typer.Option(help="Study name.")],
    file: Annotated[
        Path,
        typer.Option(
            help="TOML file with the new wording: text in the study's first language, "
            "translations.<code>.text for each further one, and optionally version "
            '(its label, e.g. "2.0"; default the version\'s number).'
        ),
    ],
    reason: Annotated[str, typer.Option(help="Why it changed (kept in the audit log).")] = "",
    as_json: JsonFlag = False,
) -> None:
    """Add the next version of a study's consent text (e.g. after an amendment the ethics
    board approved). Participants who accepted an earlier version are flagged; with the
    protocol's reconsent_before_next_session they accept the new one on the tablet before
    their next session can start."""
    from app.services.audit import Actor
    from app.services.privacy import consent
    from app.settings import Settings

    try:
        source = file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidInput(f"cannot read {file}: {exc}") from exc
    label, texts = consent.texts_from_toml(source, name=str(file))
    database = open_database(Settings())
    require_current_schema(database)
    with database.writing() as db:
        added = consent.add_version(
            db,
            study_name=study,
            texts=texts,
            actor=Actor.command_line(),
            label=label,
            reason=reason,
        )
    if as_json:
        emit_json(
            {"study": study, "version": added.number, "label": added.label, "sha256": added.sha256}
        )
        return
    typer.echo(f"added version {added.number} ({added.label}) of {study!r}'s consent text")
    for code, digest in added.sha256.items():
        typer.echo(f"  {code}: sha256 {digest}")


def register(cli: typer.Typer) -> None:
    """Attach ``study consent`` to the ``study`` commands (app.cli.admin)."""
    study_cli.command("consent")(study_consent)
