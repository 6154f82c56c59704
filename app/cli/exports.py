"""``trustlab export``: the PI's files from the stored data, like the dashboard's buttons."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from analysis.exports import EXPORT_FORMATS, sha256_file, write_all_exports, write_export
from app.cli.admin import JsonFlag, emit_json, open_database, require_current_schema
from app.errors import InvalidInput
from app.services import audit, studies, study_data
from app.services.audit import Actor
from app.settings import Settings

ALL = "all"


def register(cli: typer.Typer) -> None:
    """Attach ``export`` to the top-level command."""
    cli.command("export")(export)


def export(
    study: Annotated[str, typer.Option(help="Study name.")],
    format: Annotated[
        str, typer.Option(help=f"One of {', '.join(EXPORT_FORMATS)}, or '{ALL}' (a folder).")
    ],
    out: Annotated[Path, typer.Option(help="File to write (a folder for 'all').")],
    as_json: JsonFlag = False,
) -> None:
    """Write an export of a study: CSV (long, wide, steps), codebook, SPSS .sav, the mixed
    models (JSON) or the report."""
    if format != ALL and format not in EXPORT_FORMATS:
        raise InvalidInput(f"--format {format!r}: choose one of {', '.join(EXPORT_FORMATS)}, {ALL}")
    database = open_database(Settings())
    require_current_schema(database)
    with database.read_session() as db:
        found = studies.get_study(db, study)
        dataset = study_data.load_dataset(db, study=found)
        study_id = found.id
    if format == ALL:
        out.mkdir(parents=True, exist_ok=True)
        written = write_all_exports(dataset, out)
        files = {
            name: {"path": str(path), "sha256": sha256_file(path)} for name, path in written.items()
        }
    else:
        if out.is_dir():
            out = out / EXPORT_FORMATS[format].filename
        out.parent.mkdir(parents=True, exist_ok=True)
        path = write_export(dataset, format, out)
        files = {format: {"path": str(path), "sha256": sha256_file(path)}}
    with database.writing() as db:
        audit.record(
            db,
            actor=Actor.command_line(),
            action="export.written",
            study_id=study_id,
            subject=format,
            details={"files": files, "data_sha256": dataset.manifest["data_sha256"]},
        )
        db.commit()
    if as_json:
        emit_json({"study": study, "data_sha256": dataset.manifest["data_sha256"], "files": files})
        return
    for name, info in files.items():
        typer.echo(f"{name:<13} {info['path']}  sha256 {info['sha256'][:16]}…")
