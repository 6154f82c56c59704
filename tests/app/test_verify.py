"""``trustlab verify``'s findings name sessions as people do (the familiarisation run)."""

from __future__ import annotations

from sqlalchemy import select, update

from app.services import verify
from app.tables import Run, RunStatus, StudySession
from tests.conftest import Lab


def _findings(lab: Lab) -> list[tuple[str, str]]:
    with lab.database.read_session() as db:
        report = verify.verify_study(db, study_name=lab.study)
    return [(f.check, f.detail) for f in report.findings]


def test_findings_name_the_familiarisation_run_not_session_0(lab: Lab) -> None:
    lab.enrol_and_assign()
    lab.start_session()
    lab.run_session()
    lab.start_session()
    lab.run_session()
    assert _findings(lab) == []
    with lab.database.writing() as db:
        sessions = {s.number: s for s in db.scalars(select(StudySession))}
        db.execute(update(StudySession).where(StudySession.number == 0).values(ended_at=None))
        for number in (0, 1):
            last = db.scalars(
                select(Run).where(Run.session_id == sessions[number].id).order_by(Run.number.desc())
            ).first()
            assert last is not None
            db.execute(update(Run).where(Run.id == last.id).values(status=RunStatus.RUNNING))
        db.commit()
    findings = _findings(lab)
    assert findings == [
        ("timeline", "the familiarisation run: status and end time disagree"),
        ("timeline", "the familiarisation run is running out of turn"),
        ("timeline", "session 1 run 3 is running out of turn"),
    ]
    assert not any("session 0" in detail for _, detail in findings)
