"""``trustlab export``: the PI's files from the stored data, like the dashboard's buttons.

Exports hold participants' answers, so they are written as the backups are
(:mod:`app.private_files`): mode 0600 whatever the umask, never through a symbolic link, each
file complete or not at all, and never over an existing file unless ``--force`` says so.

The formats made of fitted analyses (``mixed-json``, ``html``, and so ``all``) take them from
the fits the web app keeps in the database (app.services.analysis_views.export_fits, the same
keys as the pages'), and store what they fit for the pages; the other formats import no
statistics at all (issue 49).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from app.cli.common import JsonFlag, emit_json, open_database, require_current_schema
from app.errors import InvalidInput

if TYPE_CHECKING:
    from pydantic import SecretStr
    from sqlalchemy.orm import Session

    from analysis.dataset import StudyDataset
    from analysis.exports import FittedAnalyses
    from app.db import Database

ALL = "all"

FORMATS = (
    *("long-csv", "wide-csv", "steps-csv", "codebook-csv", "codebook-json", "sav"),
    *("adaptation-csv", "mixed-json", "html"),
)
"""The names of analysis.exports.EXPORT_FORMATS, for ``--help``: repeated here because showing
help imports no exports (tests/app/test_cli.py checks that they agree)."""

FOLDER_MODE = 0o700
"""A new bundle folder: for its owner only, like its files."""


def register(cli: typer.Typer) -> None:
    """Attach ``export`` to the top-level command."""
    cli.command("export")(export)


def export(
    study: Annotated[str, typer.Option(help="Study name.")],
    format: Annotated[
        str, typer.Option(help=f"One of {', '.join(FORMATS)}, or '{ALL}' (a folder).")
    ],
    out: Annotated[Path, typer.Option(help="File to write (a folder for 'all').")],
    force: Annotated[
        bool, typer.Option("--force", help="Replace files that exist (never a symbolic link).")
    ] = False,
    pseudonymise: Annotated[
        bool,
        typer.Option(
            "--pseudonymise",
            help="Replace participant codes by keyed-hash pseudonyms (TRUSTLAB_PSEUDONYM_KEY), "
            "for data shared outside the lab.",
        ),
    ] = False,
    prereg: Annotated[
        Path | None,
        typer.Option(
            "--prereg",
            help="A prereg.json (from 'trustlab prereg'): the report says whether its analyses "
            "are the registered ones (default: the study's newest registration, if any).",
        ),
    ] = None,
    site: Annotated[
        str | None,
        typer.Option(help="Only this site's participants (a study with \\[sites]; default: all)."),
    ] = None,
    pilot: Annotated[
        bool,
        typer.Option(
            "--pilot",
            help="The pilot participants' data instead of the study's (every row marked pilot).",
        ),
    ] = False,
    as_json: JsonFlag = False,
) -> None:
    """Write an export of a study: CSV (long, wide, steps), codebook, SPSS .sav, the mixed
    models (JSON) or the report. Files are readable by their owner only; existing files are
    kept unless --force."""
    from analysis.exports import EXPORT_FORMATS, sha256_file, write_all_exports, write_export
    from app.private_files import new_private_file, refuse_existing, refuse_link
    from app.services import audit, studies
    from app.services.analysis_views import study_data
    from app.services.audit import Actor
    from app.services.blinding import is_sealed
    from app.services.privacy import pseudonyms, sites
    from app.settings import Settings

    if format != ALL and format not in EXPORT_FORMATS:
        raise InvalidInput(f"--format {format!r}: choose one of {', '.join(EXPORT_FORMATS)}, {ALL}")
    settings = Settings()
    key = pseudonyms.require_key(_secret(settings.pseudonym_key)) if pseudonymise else None
    targets = _targets(format, out)
    registration = read_registration(prereg) if prereg is not None else None
    for target in targets:  # refuse before the (slow) export, and before writing any file
        refuse_link(target)
        if target.exists() and not force:
            raise InvalidInput(f"{target} exists; choose a new file name, or --force to replace it")
        refuse_existing(target, replace=force)  # a folder is never replaced
    database = open_database(settings)
    require_current_schema(database)
    with database.read_session() as db:
        found = studies.get_study(db, study)
        scope = sites.Scope.every_site().narrowed(site or "", found)
        dataset = study_data.load_dataset(db, study=found, scope=scope, pilot=pilot)
        study_id, sealed = found.id, is_sealed(found)
        if key is not None:
            dataset = pseudonyms.pseudonymised(dataset, key=key, study=study)
        if registration is not None:
            dataset = replace(
                dataset, registration=registration[0], registration_source=registration[1]
            )
        fitted = None
        if format == ALL or EXPORT_FORMATS[format].write_fitted is not None:
            fitted = kept_fits(database, db, study_id=study_id, dataset=dataset)
    staging = partial(new_private_file, replace=force)
    if format == ALL:
        out.mkdir(mode=FOLDER_MODE, parents=True, exist_ok=True)
        written = write_all_exports(dataset, out, staging=staging, fitted=fitted)
    else:
        out = targets[0]
        out.parent.mkdir(parents=True, exist_ok=True)
        with staging(out) as draft:
            write_export(dataset, format, draft, fitted=fitted)
        written = {format: out}
    files = {
        # Absolute: an erasure run from another folder lists them (app.services.privacy.erasure).
        name: {"path": str(path.resolve()), "sha256": sha256_file(path)}
        for name, path in written.items()
    }
    with database.writing() as db:
        audit.record(
            db,
            actor=Actor.command_line(),
            action="export.written",
            study_id=study_id,
            subject=format,
            details={
                "files": files,
                "data_sha256": dataset.manifest["data_sha256"],
                "for_unblinded_use": sealed,
                "pseudonymised": key is not None,
                "sites": None if scope.sites is None else sorted(scope.sites),
            }
            | ({"pilot": True} if pilot else {}),
        )
        db.commit()
    if sealed:
        typer.echo(
            f"note: {study!r} is blinded: this export holds the real conditions and the learners' "
            "data, for unblinded use only (recorded in the audit log)",
            err=True,
        )
    if as_json:
        emit_json({"study": study, "data_sha256": dataset.manifest["data_sha256"], "files": files})
        return
    for name, info in files.items():
        typer.echo(f"{name:<13} {info['path']}  sha256 {info['sha256'][:16]}…")


def kept_fits(
    database: Database, db: Session, *, study_id: int, dataset: StudyDataset
) -> FittedAnalyses | None:
    """The fitted analyses of ``dataset`` as the web app keeps them: read from the database
    when a page (or an earlier export) fitted them, else fitted here, in this process, and
    stored for the pages. None when they cannot be computed (the export says why itself)."""
    from app.services.analysis_views.export_fits import fitted_analyses
    from app.services.analysis_views.fit_runner import FitRunner

    runner = FitRunner(database, processes=0, wait=0.0)
    try:
        return fitted_analyses(runner.for_study(db, study_id=study_id, dataset=dataset))
    finally:
        runner.close()


def read_registration(path: Path) -> tuple[dict[str, Any], str]:
    """A ``prereg.json`` and a note of where it came from (its path and SHA-256)."""
    from analysis.prereg import FORMAT

    try:
        content = path.read_bytes()
        value = json.loads(content)
    except OSError as error:
        raise InvalidInput(f"--prereg {path}: {error.strerror or error}") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise InvalidInput(f"--prereg {path}: not JSON") from None
    if not isinstance(value, dict) or value.get("format") != FORMAT:
        raise InvalidInput(f"--prereg {path}: not a prereg.json written by 'trustlab prereg'")
    digest = hashlib.sha256(content).hexdigest()
    return value, f"{path.name}, SHA-256 {digest[:16]}…"


def _secret(value: SecretStr | None) -> str | None:
    return value.get_secret_value() if value is not None else None


def _targets(format: str, out: Path) -> list[Path]:
    """The files an export writes: one file (into ``out`` if it is a folder), or the bundle's."""
    from analysis.exports import EXPORT_FORMATS, SUMS_FILE
    from app.private_files import refuse_link

    refuse_link(out)
    if format != ALL:
        return [out / EXPORT_FORMATS[format].filename if out.is_dir() else out]
    if out.exists() and not out.is_dir():
        raise InvalidInput(f"--out {out}: '{ALL}' writes a folder, and this is a file")
    return [out / export.filename for export in EXPORT_FORMATS.values()] + [out / SUMS_FILE]
