"""Pseudonymised exports: every participant code replaced by a keyed hash in every file, the
codebook and manifest say so, the same code gets the same pseudonym, and without a key the
export is refused in one line (nothing written)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from pydantic import SecretStr
from sqlalchemy import select
from typer.testing import CliRunner, Result

from analysis.exports import EXPORT_FORMATS
from app.cli import cli
from app.db import Database
from app.main import create_app
from app.services import studies
from app.services.analysis_views import study_data
from app.services.privacy import pseudonyms
from app.services.privacy.sites import Scope
from app.settings import Settings
from app.tables import AuditEvent, Role
from bench.seed import seed_study
from tests.conftest import UserClientFactory, make_user, sign_in_api, sqlite_only

KEY = "k3y-for-the-tests-only-0123456789"


def _export(
    database_url: str, out: Path, *extra: str, key: str | None = KEY, form: str = "all"
) -> Result:
    env = {"TRUSTLAB_DATABASE_URL": database_url}
    if key is not None:
        env["TRUSTLAB_PSEUDONYM_KEY"] = key
    return CliRunner().invoke(
        cli,
        ["export", "--study", "small", "--format", form, "--out", str(out), *extra],
        env=env,
    )


def _codes(database: Database) -> list[str]:
    with database.read_session() as db:
        dataset = study_data.load_dataset(
            db, scope=Scope.every_site(), study=studies.get_study(db, "small")
        )
    return list(dataset.participants["participant"])


@sqlite_only("files and hashing: the database only supplies the rows")
def test_a_pseudonymised_bundle_holds_no_participant_code(
    database: Database, database_url: str, tmp_path: Path
) -> None:
    seed_study(database, name="small", participants=3, seed=5)
    codes = _codes(database)
    written = _export(database_url, tmp_path / "bundle", "--pseudonymise")
    assert written.exit_code == 0, written.output
    expected = {pseudonyms.pseudonym(KEY.encode(), "small", code) for code in codes}
    files = [p for p in (tmp_path / "bundle").iterdir() if p.name in _filenames()]
    assert len(files) == len(EXPORT_FORMATS)
    for path in files:
        content = path.read_bytes()
        for code in codes:  # as a word: the report's embedded Plotly says "DEP0003"
            found_code = re.search(rb"(?<![A-Za-z0-9_])" + code.encode() + rb"(?![0-9])", content)
            assert found_code is None, f"{code} in {path.name}"
    wide = (tmp_path / "bundle" / EXPORT_FORMATS["wide-csv"].filename).read_text()
    found = {line.split(",")[0] for line in wide.splitlines()[1:]}
    assert found == expected
    book = json.loads((tmp_path / "bundle" / EXPORT_FORMATS["codebook-json"].filename).read_text())
    assert book["participants"] == "pseudonymised"
    # Stability and keying are the wide table's to show (the whole bundle is fitted once above).
    again = _export(database_url, tmp_path / "again.csv", "--pseudonymise", form="wide-csv")
    assert again.exit_code == 0
    stable = (tmp_path / "again.csv").read_text()
    assert stable.splitlines()[1:] == wide.splitlines()[1:]  # the same pseudonyms each time
    other = _export(
        database_url,
        tmp_path / "other.csv",
        "--pseudonymise",
        key="another-key-0123456789",
        form="wide-csv",
    )
    assert other.exit_code == 0
    keyed = (tmp_path / "other.csv").read_text()
    assert {line.split(",")[0] for line in keyed.splitlines()[1:]}.isdisjoint(found)


def _filenames() -> set[str]:
    return {spec.filename for spec in EXPORT_FORMATS.values()}


@pytest.mark.parametrize(
    ("key", "reason"),
    [(None, "no pseudonym key is configured"), ("short", "too short")],
    ids=["none", "short"],
)
@sqlite_only("refused before the database is read")
def test_without_a_key_a_pseudonymised_export_is_refused_and_nothing_written(
    database: Database, database_url: str, tmp_path: Path, key: str | None, reason: str
) -> None:
    seed_study(database, name="small", participants=2, seed=5)
    refused = _export(database_url, tmp_path / "bundle", "--pseudonymise", key=key)
    assert refused.exit_code == 2
    assert refused.stderr.startswith("error: ") and reason in refused.stderr
    assert refused.stderr.count("\n") == 1
    assert not (tmp_path / "bundle").exists()


def test_pseudonyms_are_per_study_and_keyed() -> None:
    key = KEY.encode()
    first = pseudonyms.pseudonym(key, "pilot", "P001")
    assert first == pseudonyms.pseudonym(key, "pilot", "P001")
    assert first.startswith("ps-") and len(first) == 19
    assert first != pseudonyms.pseudonym(key, "main", "P001")
    assert first != pseudonyms.pseudonym(b"another-key-0123456789", "pilot", "P001")


@sqlite_only("the download's wording; the data path is the command line's")
def test_an_analyst_downloads_with_pseudonyms(
    database: Database, user_client: UserClientFactory, tmp_path: Path
) -> None:
    seed_study(database, name="small", participants=2, seed=5)
    codes = _codes(database)
    analyst = user_client(Role.ANALYST)
    refused = analyst.get("/studies/small/exports/wide-csv?pseudonymise=1")
    assert refused.status_code == 422 and "no pseudonym key is configured" in refused.text
    plain = analyst.get("/studies/small/exports/wide-csv")
    assert plain.status_code == 200 and codes[0] in plain.text


@sqlite_only("the download's wording; the data path is the command line's")
def test_with_a_key_the_download_carries_pseudonyms_and_is_audited_so(
    database: Database, settings: Settings
) -> None:
    seed_study(database, name="small", participants=2, seed=5)
    codes = _codes(database)
    make_user(database, "pi", Role.ANALYST)
    keyed = settings.model_copy(update={"pseudonym_key": SecretStr(KEY)})
    with TestClient(create_app(keyed)) as analyst:
        sign_in_api(analyst, "pi")
        file = analyst.get("/studies/small/exports/long-csv?pseudonymise=1")
    assert file.status_code == 200
    assert not any(code in file.text for code in codes)
    assert pseudonyms.pseudonym(KEY.encode(), "small", codes[0]) in file.text
    with database.read_session() as db:
        entry = db.scalars(select(AuditEvent).where(AuditEvent.action == "export.downloaded")).one()
    assert entry.details["pseudonymised"] is True
