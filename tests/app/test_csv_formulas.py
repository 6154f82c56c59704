"""Tablet free text that a spreadsheet would run as a formula, through every CSV the app writes:
the download routes, ``trustlab export`` and the audit log's CSV."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import pyreadstat
from typer.testing import CliRunner

from analysis.exports import EXPORT_FORMATS
from app.cli import cli
from app.tables import Role
from tests.conftest import PRE_STUDY_ANSWERS, Lab, UserClientFactory, tablet_client

FORMULAS = ['=HYPERLINK("http://x","y")', "+1", "-2+3", "@SUM(A1)"]
"""Self-descriptions a participant types on the tablet (leading tabs and CRs are stripped there;
the analysis tests cover them)."""

CSV_EXPORTS = [name for name, spec in EXPORT_FORMATS.items() if spec.media_type == "text/csv"]


def _answer_on_tablets(lab: Lab) -> list[str]:
    """One participant per formula, each describing their gender with it on the tablet."""
    codes = []
    for formula in FORMULAS:
        code = lab.enrol_and_assign(questionnaires=False)
        tablet = tablet_client(lab.app, lab, code)
        assert tablet.post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
        answers = {
            **PRE_STUDY_ANSWERS,
            "demographics": {
                "age": "27",
                "gender": "self_described",
                "gender_description": formula,
            },
        }
        for instrument, given in answers.items():
            response = tablet.post(
                f"/api/v1/tablet/questionnaires/{instrument}", json={"answers": given}
            )
            assert response.status_code == 200, response.text
        codes.append(code)
    return codes


def _cells(text: str) -> list[list[str]]:
    return list(csv.reader(io.StringIO(text, newline="")))


def _assert_neutralised(name: str, text: str, codes: list[str]) -> None:
    """The answers are prefixed with ', numbers are not, and no other cell starts a formula."""
    rows = _cells(text)
    for row in rows:
        for cell in row:
            if cell.startswith(("=", "+", "-", "@", "\t", "\r")):
                float(cell)  # only a number may
    table = [dict(zip(rows[0], row, strict=True)) for row in rows[1:]]
    if name == "long-csv":
        described = {
            r["participant"]: r["value"] for r in table if r["item"] == "gender_description"
        }
        ages = {r["value"] for r in table if r["item"] == "age"}
    elif name == "wide-csv":
        described = {r["participant"]: r["gender_description"] for r in table}
        ages = {r["age"] for r in table}
    else:
        return
    assert described == {code: "'" + formula for code, formula in zip(codes, FORMULAS, strict=True)}
    assert ages == {"27.0"}


def test_every_download_neutralises_tablet_formulas(
    lab: Lab, user_client: UserClientFactory, tmp_path: Path
) -> None:
    codes = _answer_on_tablets(lab)
    analyst = user_client(Role.ANALYST)
    assert set(CSV_EXPORTS) == {
        "long-csv", "wide-csv", "steps-csv", "codebook-csv", "adaptation-csv",
    }  # fmt: skip
    for name in CSV_EXPORTS:
        response = analyst.get(f"/studies/{lab.study}/exports/{name}")
        assert response.status_code == 200
        _assert_neutralised(name, response.text, codes)
    sav = tmp_path / "wide.sav"
    sav.write_bytes(analyst.get(f"/studies/{lab.study}/exports/sav").content)
    frame, _ = pyreadstat.read_sav(str(sav))
    assert frame["gender_description"].tolist() == FORMULAS  # the .sav keeps the raw answers


def test_export_command_and_audit_csv_neutralise_formulas(
    lab: Lab, user_client: UserClientFactory, database_url: str, tmp_path: Path
) -> None:
    codes = _answer_on_tablets(lab)
    # Whoever runs the command is named in the audit log, and a login name is anyone's choice.
    login = '=HYPERLINK("http://x","me")'
    env = {"TRUSTLAB_DATABASE_URL": database_url, "LOGNAME": login, "USER": login}
    out = tmp_path / "bundle"
    result = CliRunner().invoke(
        cli, ["export", "--study", lab.study, "--format", "all", "--out", str(out)], env=env
    )
    assert result.exit_code == 0, result.output
    for name in CSV_EXPORTS:
        path = out / EXPORT_FORMATS[name].filename
        _assert_neutralised(name, path.read_text(encoding="utf-8"), codes)
    frame, _ = pyreadstat.read_sav(str(out / EXPORT_FORMATS["sav"].filename))
    assert frame["gender_description"].tolist() == FORMULAS

    exported = user_client(Role.ADMIN).get("/admin/audit.csv?action=export.")
    assert exported.status_code == 200
    rows = list(csv.DictReader(io.StringIO(exported.text, newline="")))
    assert [row["actor"] for row in rows if row["action"] == "export.written"] == ["'" + login]
    _assert_neutralised("audit", exported.text, codes)
