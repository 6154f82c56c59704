"""A live study's protocol after going live (issue 50, item 5): a change is a new version with a
reason, shown as a diff against the version in force; one that would break comparability is
refused unless the study is split; each participant and session records the version it ran
under, verify checks each session against its own, and exports carry it."""

from __future__ import annotations

import html
import re
from pathlib import Path

import pandas as pd
from fastapi.testclient import TestClient
from sqlalchemy import select
from typer.testing import CliRunner

from app.cli import cli
from app.services import studies
from app.services.sessions import verify
from app.tables import AuditEvent, Participant, Role, StudySession
from tests.conftest import Lab, UserClientFactory, sqlite_only

HIGH = "Awesome, I knew you would say so."
AMENDED = "Wonderful, just as I thought."


def _current(lab: Lab) -> tuple[str, str]:
    with lab.database.read_session() as db:
        study = studies.get_study(db, lab.study)
        return study.protocol_source, study.protocol_sha256


def _save(admin: TestClient, lab: Lab, text: str, reason: str = "") -> object:
    _, base = _current(lab)
    return admin.post(
        f"/admin/studies/{lab.study}/protocol",
        data={"base": base, "text": text, "reason": reason},
    )


def test_an_amendment_is_a_version_each_session_records_and_verify_follows(
    lab: Lab, user_client: UserClientFactory, database_url: str, tmp_path: Path
) -> None:
    admin = user_client(Role.ADMIN)
    first = lab.enrol_and_assign()
    for _ in ("familiarisation", "session 1"):
        lab.start_session()
        lab.run_session()
    text, _ = _current(lab)
    assert HIGH in text
    amended = text.replace(HIGH, AMENDED)
    live_check = admin.post(f"/admin/studies/{lab.study}/protocol/check", data={"text": amended})
    assert "What your change amends" in live_check.text
    assert f"+    {{ name = &#34;high&#34;, text = &#34;{AMENDED}&#34; }}," in live_check.text
    without_reason = _save(admin, lab, amended)
    assert without_reason.status_code == 422  # type: ignore[attr-defined]
    assert "an amendment" in without_reason.text  # type: ignore[attr-defined]
    saved = _save(admin, lab, amended, reason="the ethics board asked for a softer line")
    assert "Saved as version 2." in saved.text  # type: ignore[attr-defined]

    lab.start_session()  # session 2 runs under version 2
    lab.run_session()
    later = lab.enrol_and_assign()
    with lab.database.read_session() as db:
        versions = {
            (p.code, s.number): s.protocol_version
            for s, p in db.execute(
                select(StudySession, Participant).join(
                    Participant, Participant.id == StudySession.participant_id
                )
            )
        }
        enrolled = dict(db.execute(select(Participant.code, Participant.protocol_version)).all())
        report = verify.verify_study(db, study_name=lab.study)
        amendment = db.scalar(select(AuditEvent).where(AuditEvent.action == "study.protocol_saved"))
    assert versions == {(first, 0): 1, (first, 1): 1, (first, 2): 2}
    assert enrolled == {first: 1, later: 2}
    assert report.ok, report.findings  # each session checked against its own version
    assert amendment is not None and amendment.details["phase"] == "live"
    assert amendment.details["reason"] == "the ethics board asked for a softer line"

    out = tmp_path / "wide.csv"
    exported = CliRunner().invoke(
        cli,
        ["export", "--study", lab.study, "--format", "wide-csv", "--out", str(out)],
        env={"TRUSTLAB_DATABASE_URL": database_url},
    )
    assert exported.exit_code == 0, exported.output
    wide = pd.read_csv(out, dtype=str).set_index("participant")
    assert wide.loc[first, "protocol_versions"] == "1+2"
    assert wide.loc[later, "protocol_versions"] == "2"


@sqlite_only("refusals decided before any write; versions per session are tested on both engines")
def test_a_change_that_breaks_comparability_is_refused_and_can_start_a_new_study(
    lab: Lab, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    lab.enrol_and_assign()  # answers the pre-study questionnaires (their items are in use)
    text, sha = _current(lab)
    breaking = {
        "an arm": text.replace("Do you want to escape the room?", "Do you want to leave the room?"),
        "the blocks": text.replace("block_sizes = [2, 4]", "block_sizes = [2]"),
        "an answered item's scale": text.replace(
            "minimum = 18, maximum = 99 }",
            "minimum = 18, maximum = 120 }",
        ),
    }
    expected = {
        "an arm": "categories: their names, questions",
        "the blocks": "allocation: the block sizes",
        "an answered item's scale": "questionnaires.demographics.age: already answered",
    }
    for what, changed in breaking.items():
        assert changed != text, what
        refused = _save(admin, lab, changed, reason=f"change {what}")
        assert refused.status_code == 409, what  # type: ignore[attr-defined]
        page = html.unescape(refused.text)  # type: ignore[attr-defined]
        assert "This change needs a new study" in page and expected[what] in page, what
    assert _current(lab) == (text, sha)  # nothing saved
    split = admin.post(
        f"/admin/studies/{lab.study}/split",
        data={"text": breaking["the blocks"], "new_name": "rt-two-blocks", "title": "Two"},
        follow_redirects=False,
    )
    assert split.status_code == 303
    assert split.headers["location"] == "/admin/studies/rt-two-blocks/design/study"
    with lab.database.read_session() as db:
        created = studies.get_study(db, "rt-two-blocks")
        assert created.phase == "draft"
        assert studies.protocol_of(created).allocation.block_sizes == [2]
        audited = db.scalar(
            select(AuditEvent).where(
                AuditEvent.action == "study.created", AuditEvent.subject == "rt-two-blocks"
            )
        )
        assert audited is not None
        assert audited.details["started_from"] == f"split from study {lab.study} version 1"


@sqlite_only("refusals decided before any write; versions per session are tested on both engines")
def test_an_amendment_waits_for_running_sessions_and_an_unanswered_item_may_change(
    lab: Lab, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    lab.enrol_and_assign()
    lab.start_session()
    text, _ = _current(lab)
    reworded = text.replace('"How old are you (in years)?"', '"Your age (in years)?"')
    assert reworded != text
    waiting = _save(admin, lab, reworded, reason="clearer wording")
    assert waiting.status_code == 409  # type: ignore[attr-defined]
    assert "are running" in waiting.text  # type: ignore[attr-defined]
    lab.run_session()
    saved = _save(admin, lab, reworded, reason="clearer wording")
    assert "Saved as version 2." in saved.text  # type: ignore[attr-defined]
    page = admin.get(f"/admin/studies/{lab.study}/design/questionnaires")
    assert 'id="protocol-amendment"' in page.text
    assert re.search(r"required: an amendment", page.text)
