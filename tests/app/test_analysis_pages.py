"""The PI's side in the app: analysis page, downloads, ``trustlab export``, and the mapping of the
protocol onto the analysis package's specifications."""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import stat
from collections.abc import Iterator
from pathlib import Path

import pyreadstat
import pytest
from sqlalchemy import select
from typer.testing import CliRunner, Result

from analysis.exports import EXPORT_FORMATS
from analysis.scoring import TIPI_SCALES, nars_scales
from app.cli import cli
from app.db import Database
from app.protocol import default_protocol
from app.services.analysis_views import study_data
from app.tables import AuditEvent, Role, Study
from bench.seed import seed_study
from tests.conftest import Lab, UserClientFactory, create_blinded_study


@pytest.fixture
def seeded(database: Database) -> str:
    """A study of 24 complete participants (bulk-generated)."""
    seed_study(database, name="seeded", participants=24, seed=3)
    return "seeded"


def test_protocol_scales_match_the_published_keys() -> None:
    scales = {s.name: s for s in study_data.scales_of(default_protocol().protocol)}
    for published in TIPI_SCALES:
        ours = scales[published.name]
        assert (set(ours.items), ours.reverse) == (set(published.items), published.reverse)
        assert (ours.scale_min, ours.scale_max, ours.method) == (1, 7, "mean")
    nars = {s.name: s for s in nars_scales("sum")}
    for name in ("nars_s1", "nars_s2", "nars_s3", "nars_total"):
        assert set(scales[name].items) == set(nars[f"{name}_sum"].items)
        assert scales[name].reverse == nars[f"{name}_sum"].reverse
    assert scales["nars_s3"].reverse == frozenset({"nars_3", "nars_5", "nars_6"})


def test_instruments_cover_every_stored_item() -> None:
    instruments = {i.name: i for i in study_data.instruments_of(default_protocol().protocol)}
    assert set(instruments) == {
        "consent",
        "demographics",
        "background",
        "tipi",
        "nars",
        "trust",
        "overall",
    }
    assert instruments["trust"].per_session and not instruments["tipi"].per_session
    demographics = {item.key: item for item in instruments["demographics"].items}
    assert demographics["gender"].kind == "categorical"
    assert demographics["gender_description"].kind == "text"
    assert {item.key for item in instruments["trust"].items if item.reverse} == {"trust_5"}


def test_analysis_page_shows_each_measure(seeded: str, user_client: UserClientFactory) -> None:
    analyst = user_client(Role.ANALYST)
    page = analyst.get(f"/studies/{seeded}/analysis")
    assert page.status_code == 200
    assert "24 participants analysed · type 3 sums of squares" in page.text
    assert page.text.count('class="card outcome"') == 5
    assert "condition: F(1, 22) = " in page.text
    assert 'type="application/json" id="figure-trust_1"' in page.text
    assert "<script>" not in page.text  # figures are data blocks, drawn by a static script
    type2 = analyst.get(f"/studies/{seeded}/analysis?ss=2")
    assert "type 2 sums of squares" in type2.text
    assert analyst.get(f"/studies/{seeded}/analysis?ss=1").status_code == 422
    experimenter = user_client(Role.EXPERIMENTER)
    assert experimenter.get(f"/studies/{seeded}/analysis").status_code == 403


def test_a_young_study_says_what_cannot_be_computed(
    database: Database, exp3_study: str, user_client: UserClientFactory
) -> None:
    analyst = user_client(Role.ANALYST)
    page = analyst.get(f"/studies/{exp3_study}/analysis")
    assert page.status_code == 200
    assert "Nothing to analyse yet" in page.text


_READ_ON_BOTH = ("long-csv", "steps-csv")
"""Every format reads the study through the same loader; PostgreSQL is checked on these two
(the answers and the step log), the costly formats (report, mixed models) on SQLite only."""


@pytest.mark.parametrize(
    ("engine_name", "export"),
    [("sqlite", export) for export in EXPORT_FORMATS]
    + [pytest.param("postgresql", export, marks=pytest.mark.postgres) for export in _READ_ON_BOTH],
    indirect=["engine_name"],
)
def test_every_download(
    seeded: str, user_client: UserClientFactory, database: Database, export: str
) -> None:
    admin = user_client(Role.ADMIN)
    response = admin.get(f"/studies/{seeded}/exports/{export}")
    assert response.status_code == 200
    spec = EXPORT_FORMATS[export]
    assert response.headers["content-disposition"] == (
        f'attachment; filename="{seeded}-{spec.filename}"'
    )
    assert response.headers["x-content-sha256"] == hashlib.sha256(response.content).hexdigest()
    if export == "wide-csv":
        rows = list(csv.DictReader(io.StringIO(response.text)))
        assert len(rows) == 24
        assert {"trust_1_s1", "trust_2_s4", "tipi_extraversion"} <= set(rows[0])
        # The consent text's own version by the name that says which version it is.
        assert {"protocol_version", "consent_version"} <= set(rows[0])
        assert "version" not in rows[0]
    with database.read_session() as db:
        event = db.scalars(select(AuditEvent).where(AuditEvent.action == "export.downloaded")).one()
    assert event.subject == export and event.actor.startswith("admin")


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # no database question here
def test_exports_and_pages_name_the_study_by_its_own_title(
    database: Database, user_client: UserClientFactory, tmp_path: Path
) -> None:
    """Issue 35 item 4: a pilot and the main study share a protocol (and its title); the report,
    the exports' metadata and the study's pages name each study by the title the lab gave it."""
    title = "Pilot 2 — corridor layout"
    seed_study(database, name="pilot", participants=4, seed=3, title=title)
    protocol_title = default_protocol().protocol.study.title
    analyst = user_client(Role.ANALYST)
    report = analyst.get("/studies/pilot/exports/html").text
    assert f"<h1>Study report: {title}</h1>" in report
    assert f"<title>Study report: {title}</title>" in report
    assert protocol_title not in report
    assert analyst.get("/studies/pilot/exports/codebook-json").json()["study"] == title
    assert analyst.get("/studies/pilot/exports/mixed-json").json()["manifest"]["title"] == title
    sav = tmp_path / "pilot.sav"
    sav.write_bytes(analyst.get("/studies/pilot/exports/sav").content)
    assert pyreadstat.read_sav(str(sav), metadataonly=True)[1].file_label == f"{title} (trustlab)"
    for page in ("/studies/pilot", "/studies/pilot/analysis", "/studies/pilot/analysis/mixed"):
        assert f"{title} · trustlab</title>" in analyst.get(page).text, page


def test_unknown_download_and_roles(seeded: str, user_client: UserClientFactory) -> None:
    analyst = user_client(Role.ANALYST)
    missing = analyst.get(f"/studies/{seeded}/exports/xlsx")
    assert missing.status_code == 404
    assert "choose one of long-csv" in missing.text
    assert (
        user_client(Role.EXPERIMENTER).get(f"/studies/{seeded}/exports/long-csv").status_code == 403
    )


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # files: test_every_download
def test_export_command(seeded: str, database: Database, database_url: str, tmp_path: Path) -> None:
    runner = CliRunner()
    env = {"TRUSTLAB_DATABASE_URL": database_url}
    one = runner.invoke(
        cli,
        [
            "export",
            "--study",
            seeded,
            "--format",
            "steps-csv",
            "--out",
            str(tmp_path / "steps.csv"),
            "--json",
        ],
        env=env,
    )
    assert one.exit_code == 0, one.output
    result = json.loads(one.stdout)
    written = Path(result["files"]["steps-csv"]["path"])
    assert (
        hashlib.sha256(written.read_bytes()).hexdigest() == result["files"]["steps-csv"]["sha256"]
    )
    assert written.read_text().count("\n") == 1 + 24 * 3 * 12  # header + adapting steps
    # The bundle's files, modes and sums: a small study fits its models in a fraction of the time.
    seed_study(database, name="small", participants=3, seed=5)
    bundle = runner.invoke(
        cli,
        ["export", "--study", "small", "--format", "all", "--out", str(tmp_path / "bundle")],
        env=env,
    )
    assert bundle.exit_code == 0, bundle.output
    sums = (tmp_path / "bundle" / "SHA256SUMS").read_text()
    assert "report.html" in sums and "participants_wide.sav" in sums
    # Issue 35 item 13: every file of the bundle is its owner's only, whatever the umask, and
    # no temporary file is left beside them.
    assert _mode(tmp_path / "bundle") == 0o700
    bundled = sorted(f.name for f in (tmp_path / "bundle").iterdir())
    assert bundled == sorted([*(e.filename for e in EXPORT_FORMATS.values()), "SHA256SUMS"])
    assert {_mode(tmp_path / "bundle" / name) for name in bundled} == {0o600}
    wrong = runner.invoke(
        cli,
        ["export", "--study", seeded, "--format", "xlsx", "--out", str(tmp_path / "x")],
        env=env,
    )
    assert wrong.exit_code == 2
    assert wrong.stderr.startswith("error: --format 'xlsx': choose one of long-csv")


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture
def umask_022() -> Iterator[None]:
    """The usual umask, under which a plain write is readable by everyone."""
    previous = os.umask(0o022)
    yield
    os.umask(previous)


def _export(database_url: str, study: str, format: str, out: Path, *extra: str) -> Result:
    return CliRunner().invoke(
        cli,
        ["export", "--study", study, "--format", format, "--out", str(out), *extra],
        env={"TRUSTLAB_DATABASE_URL": database_url},
    )


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # files, not the database
def test_export_command_writes_private_files_and_never_over_others(
    database: Database, database_url: str, tmp_path: Path, umask_022: None
) -> None:
    """Issue 35 item 13: 0600 whatever the umask, no symbolic link followed, no file replaced
    unless --force (and then in one step), and a bundle refused before any file is written."""
    seed_study(database, name="small", participants=2, seed=5)
    out = tmp_path / "steps.csv"
    assert _export(database_url, "small", "steps-csv", out).exit_code == 0
    assert _mode(out) == 0o600
    first = out.read_bytes()
    out.write_text("the PI's notes")
    again = _export(database_url, "small", "steps-csv", out)
    assert (again.exit_code, again.stderr) == (
        2,
        f"error: {out} exists; choose a new file name, or --force to replace it\n",
    )
    assert out.read_text() == "the PI's notes"
    forced = _export(database_url, "small", "steps-csv", out, "--force")
    assert forced.exit_code == 0, forced.output
    assert (out.read_bytes(), _mode(out)) == (first, 0o600)
    victim = tmp_path / "victim.txt"
    victim.write_text("not yours")
    for link, force in ((tmp_path / "link.csv", ()), (tmp_path / "link2.csv", ("--force",))):
        link.symlink_to(victim)
        followed = _export(database_url, "small", "long-csv", link, *force)
        assert followed.exit_code == 2
        assert followed.stderr.startswith(f"error: {link} is a symbolic link")
    dangling = tmp_path / "dangling.csv"
    dangling.symlink_to(tmp_path / "nowhere.csv")
    assert _export(database_url, "small", "long-csv", dangling).exit_code == 2
    assert victim.read_text() == "not yours" and not (tmp_path / "nowhere.csv").exists()
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "codebook.json").write_text("{}")
    refused = _export(database_url, "small", "all", bundle)
    assert refused.exit_code == 2
    assert refused.stderr.startswith(f"error: {bundle / 'codebook.json'} exists; choose a new")
    assert [f.name for f in bundle.iterdir()] == ["codebook.json"]
    leftovers = [f.name for f in tmp_path.iterdir() if f.name.endswith(".partial")]
    assert leftovers == []


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)
def test_a_sealed_studys_export_says_it_is_for_unblinded_use(
    database: Database, database_url: str, tmp_path: Path
) -> None:
    """Issue 35 item 13: the command line is not blinded, but it says so, and the audit log
    records that a blinded study's data left for unblinded use."""
    create_blinded_study(database, "sealed")
    seed_study(database, name="open", participants=2, seed=5)
    sealed = _export(database_url, "sealed", "long-csv", tmp_path / "sealed.csv", "--json")
    assert sealed.exit_code == 0, sealed.output
    assert sealed.stderr == (
        "note: 'sealed' is blinded: this export holds the real conditions and the learners' "
        "data, for unblinded use only (recorded in the audit log)\n"
    )
    assert json.loads(sealed.stdout)["study"] == "sealed"  # stdout stays one JSON object
    plain = _export(database_url, "open", "long-csv", tmp_path / "open.csv")
    assert plain.exit_code == 0 and plain.stderr == ""
    with database.read_session() as db:
        events = db.scalars(select(AuditEvent).where(AuditEvent.action == "export.written"))
        used = {e.study_id: e.details["for_unblinded_use"] for e in events}
        ids = {s.name: s.id for s in db.scalars(select(Study))}
    assert used == {ids["sealed"]: True, ids["open"]: False}


def test_degenerate_data_is_explained_not_crashed(
    database: Database, user_client: UserClientFactory
) -> None:
    seed_study(database, name="tiny", participants=2, seed=5)
    page = user_client(Role.ANALYST).get("/studies/tiny/analysis")
    assert page.status_code == 200
    assert "cannot be computed because" in page.text


def test_the_page_reads_right_for_one_participant(lab: Lab, user_client: UserClientFactory) -> None:
    """Issue 21, defect 7: count and noun agree, no ".:" in titles, reverse items marked."""
    lab.enrol_and_assign()
    for _ in ("familiarisation", "session 1"):
        lab.start_session()
        lab.run_session()
    lab.fill_pending_questionnaires()
    page = user_client(Role.ANALYST).get(f"/studies/{lab.study}/analysis").text
    assert "1 participant analysed" in page and "1 participants" not in page
    assert ".: mean" not in page
    assert "(reverse-scored)" in page
