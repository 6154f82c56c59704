"""A participant's own data (a subject-access request): everything stored about them, as JSON
and a readable page, nobody else's, owner-only files, audited; a sealed condition stays sealed."""

from __future__ import annotations

import json
import stat
from pathlib import Path

from sqlalchemy import select
from typer.testing import CliRunner, Result

from app.cli import cli
from app.services import studies
from app.services.audit import Actor
from app.services.participants import enrolment, questionnaires
from app.tables import AuditEvent
from tests.conftest import Lab, create_blinded_study, sqlite_only


def _export(database_url: str, study: str, code: str, out: Path, *extra: str) -> Result:
    return CliRunner().invoke(
        cli,
        ["participant", "export", "--study", study, "--code", code, "--out", str(out), *extra],
        env={"TRUSTLAB_DATABASE_URL": database_url},
    )


def test_everything_stored_about_one_participant_and_nothing_about_others(
    lab: Lab, database_url: str, tmp_path: Path
) -> None:
    mine = lab.enrol_and_assign("P-MINE")
    lab.start_session()
    lab.run_session()
    other = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants", json={"code": "P-OTHER"}
    )
    assert other.status_code == 201
    written = _export(database_url, lab.study, mine, tmp_path / "sar")
    assert written.exit_code == 0, written.output
    record = json.loads((tmp_path / "sar" / f"{mine}.json").read_text())
    page = (tmp_path / "sar" / f"{mine}.html").read_text()
    assert record["participant"] == mine and record["enrolment"]["condition"] in ("C1", "C2")
    with lab.database.read_session() as db:
        participant = enrolment.get_participant(
            db, studies.get_study(db, lab.study), mine, actor=Actor.system()
        )
        stored = questionnaires.stored_answers(db, participant, "tipi", None)
    tipi = next(q for q in record["questionnaires"] if q["instrument"] == "tipi")
    assert tipi["answers"] == stored
    assert len(record["robot_steps"]) == 3  # the practice run's three questions
    assert all(step["answer"] in ("yes", "no") and step["reply"] for step in record["robot_steps"])
    assert {"participant.enrolled", "participant.consented"} <= {
        e["action"] for e in record["audit_log"]
    }
    assert "P-OTHER" not in json.dumps(record) and "P-OTHER" not in page
    assert record["robot_steps"][0]["question"] in page
    for name in (f"{mine}.json", f"{mine}.html"):
        assert stat.S_IMODE((tmp_path / "sar" / name).stat().st_mode) == 0o600
    again = _export(database_url, lab.study, mine, tmp_path / "sar")
    assert again.exit_code == 2 and "exists" in again.stderr
    with lab.database.read_session() as db:
        logged = db.scalars(select(AuditEvent).where(AuditEvent.action == "participant.exported"))
        assert [e.subject for e in logged] == [mine]
    unknown = _export(database_url, lab.study, "P-NOBODY", tmp_path / "none")
    assert unknown.exit_code == 1 and "has no participant 'P-NOBODY'" in unknown.stderr


@sqlite_only("the sealing rule; the rows are read as in the test above")
def test_a_blinded_studys_condition_stays_sealed(
    lab: Lab, database_url: str, tmp_path: Path
) -> None:
    lab.study = create_blinded_study(lab.database)
    code = lab.enrol_and_assign("P-BLIND")
    written = _export(database_url, lab.study, code, tmp_path / "sar")
    assert written.exit_code == 0, written.output
    text = (tmp_path / "sar" / f"{code}.json").read_text()
    record = json.loads(text)
    assert record["enrolment"]["condition"] == "sealed until the study is unblinded"
    assert '"C1"' not in text and '"C2"' not in text
