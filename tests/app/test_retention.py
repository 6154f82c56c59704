"""Retention deadlines with an injected clock: nothing happens before the period has run out
after the study closed; then anonymising leaves analysable data with no code, free text or
transcript anywhere in the database, or erasing removes everyone; each run audited; refusals in
one line."""

from __future__ import annotations

from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import func, select

from app import events as live_events
from app.protocol import ProtocolError, parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.privacy import retention
from app.services.sessions import verify
from app.tables import Answer, AuditEvent, Participant, Response, StudyStatus
from tests.app.personal_data import (
    dump_database,
    enrol_with_data,
    heard_in_the_room_then_unseated,
    mentions,
    note_of,
    personal_data_study,
    run_cli,
)
from tests.conftest import EXP3_ONLY, Lab, protocol_text, sqlite_only

SECRET = b"retention-test-secret"


def _with_retention(period: str, then: str = "anonymise") -> dict[str, str]:
    section = f'[retention]\nidentifiable_for = "{period}"\nthen = "{then}"\n\n'
    return {"[allocation]": section + "[allocation]"}


def _close(lab: Lab) -> datetime:
    with lab.database.writing() as db:
        study = studies.set_study_status(
            db, name=lab.study, status=StudyStatus.CLOSED, actor=Actor.system("tests")
        )
        assert study.closed_at is not None
        return study.closed_at


@pytest.fixture
def published(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The types of the events published from now on (retention's: one per participant, for
    every view of them, app.services.participants.participant_changes)."""
    types: list[str] = []
    publish = live_events.publish

    def recording(*args: Any, **kwargs: Any) -> None:
        types.append(kwargs["type"])
        publish(*args, **kwargs)

    monkeypatch.setattr(live_events, "publish", recording)
    return types


def _run(lab: Lab, now: datetime, *, dry_run: bool = False) -> retention.StudyRetention:
    with lab.database.writing() as db:
        (state,) = retention.run(
            db, now=now, actor=Actor.system("tests"), secret=SECRET, dry_run=dry_run
        )
    return state


def test_anonymising_when_due_leaves_analysable_data_and_nothing_that_links_it(
    lab: Lab, database_url: str, tmp_path: Path, published: list[str]
) -> None:
    lab.study = personal_data_study(lab.database, **_with_retention("1 year"))
    enrol_with_data(lab, "ANON-ME-1")
    enrol_with_data(lab, "ANON-ME-2")
    heard_in_the_room_then_unseated(lab, "ANON-ME-2")  # their presence must go all the same
    with lab.database.read_session() as db:
        answers = db.scalar(select(func.count()).select_from(Answer))
        likert = db.scalar(
            select(func.count()).select_from(Response).where(Response.item != "note")
        )
    closed = _close(lab)

    early = _run(lab, closed + timedelta(days=364))
    assert not early.due and early.participants == 2 and early.done == {}
    planned = _run(lab, closed + timedelta(days=366), dry_run=True)
    assert planned.due and planned.participants == 2 and planned.done == {}
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).where(Participant.code == "ANON-ME-1")) == 1

    published.clear()
    done = _run(lab, closed + timedelta(days=366))

    assert done.done["participants"] == 2 and done.done["transcript"] == 6
    assert done.done["room_presence"] == 1  # ANON-ME-2's, though they sit at no station now
    assert published == ["participant_anonymised"] * 2  # nobody was erased
    content = dump_database(lab.database, lab.app.state.database)
    for code in ("ANON-ME-1", "ANON-ME-2"):
        assert mentions(content, code) == [], code
    with lab.database.read_session() as db:
        codes = list(db.scalars(select(Participant.code)))
        assert len(codes) == 2 and all(c.startswith(retention.ANONYMOUS_PREFIX) for c in codes)
        assert db.scalar(select(func.count()).select_from(Answer)) == answers
        assert db.scalar(select(func.count()).select_from(Response)) == likert
        assert db.scalar(select(func.count()).where(Answer.transcript.is_not(None))) == 0
        events = list(
            db.scalars(select(AuditEvent.action).where(AuditEvent.action.like("retention.%")))
        )
        assert events == ["retention.anonymised"]
        assert verify.verify_study(db, study_name=lab.study).ok
    exported = run_cli(
        database_url,
        "export",
        "--study",
        lab.study,
        "--format",
        "wide-csv",
        "--out",
        str(tmp_path / "wide.csv"),
    )
    assert exported.exit_code == 0, exported.output
    wide = (tmp_path / "wide.csv").read_text()
    assert wide.count(retention.ANONYMOUS_PREFIX) == 2 and note_of("ANON-ME-1") not in wide
    again = _run(lab, closed + timedelta(days=400))
    assert again.due and again.participants == 0 and again.done == {}
    assert "nothing identifiable left" in again.describe()


@sqlite_only("the erasure itself is checked on both databases in test_erasure")
def test_erasing_when_due_removes_everyone_and_keeps_the_slots(
    lab: Lab, published: list[str]
) -> None:
    lab.study = personal_data_study(lab.database, **_with_retention("P6M", "erase"))
    enrol_with_data(lab, "ERASE-DUE")
    closed = _close(lab)
    published.clear()
    done = _run(lab, closed + timedelta(days=200))
    assert done.done["participants"] == 1 and done.done["answer"] == 3
    assert published == ["participant_erased"]
    assert mentions(dump_database(lab.database, lab.app.state.database), "ERASE-DUE") == []
    with lab.database.read_session() as db:
        slot = db.scalar(select(Participant))
        assert slot is not None and slot.erased_at is not None
        assert verify.verify_study(db, study_name=lab.study).ok


@sqlite_only("reopening and the study page: nothing database-specific")
def test_a_reopened_study_is_not_due_and_the_study_page_shows_the_date(lab: Lab) -> None:
    lab.study = personal_data_study(lab.database, **_with_retention("2 years"))
    enrol_with_data(lab, "STILL-HERE")
    closed = _close(lab)
    page = lab.experimenter.get(f"/studies/{lab.study}")
    due = (closed + timedelta(days=731)).strftime("%Y-%m-%d")  # 2 calendar years, give or take
    assert "identifiable data kept until" in page.text
    assert f"{closed.year + 2}-{closed:%m}" in page.text or due in page.text
    with lab.database.writing() as db:
        studies.set_study_status(db, name=lab.study, status=StudyStatus.OPEN, actor=Actor.system())
    state = _run(lab, closed + timedelta(days=3650))
    assert not state.due and state.due_at is None and "(it is open)" in state.describe()


@pytest.mark.parametrize(
    ("period", "why"),
    [("-1 year", "negative"), ("forever", "not a period"), ("0 days", "zero")],
)
def test_a_period_that_is_no_duration_is_refused_at_study_creation(period: str, why: str) -> None:
    text = protocol_text(**EXP3_ONLY, **_with_retention(period))
    with pytest.raises(ProtocolError, match=why) as refused:
        parse_protocol(text)
    assert "retention.identifiable_for" in str(refused.value)


@sqlite_only("refused before the database is changed")
def test_the_command_refuses_unclear_requests_in_one_line(lab: Lab, database_url: str) -> None:
    lab.study = personal_data_study(lab.database, **_with_retention("1 day"))
    enrol_with_data(lab, "KEEP-ME")
    _close(lab)

    def refused(*args: str) -> str:
        result = run_cli(database_url, "retention", "run", *args)
        assert result.exit_code == 2, result.output
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in result.output, result.output
        return lines[0]

    assert "only with --dry-run" in refused("--as-of", "2099-01-01")
    assert "not a date" in refused("--dry-run", "--as-of", "next week")
    far = run_cli(database_url, "retention", "run", "--dry-run", "--as-of", "2099-01-01")
    assert far.exit_code == 0 and "1 participant to anonymise" in far.output
    today = run_cli(database_url, "retention", "run", "--yes")
    assert today.exit_code == 0 and "identifiable data kept until" in today.output
    other = personal_data_study(lab.database, "no-deadline")
    assert "declares no retention period" in refused("--dry-run", "--study", other)
    with lab.database.writing() as db:  # closed two days ago: due today
        study = studies.get_study(db, lab.study)
        study.closed_at = study.closed_at - timedelta(days=2) if study.closed_at else None
        db.commit()
    assert "add --yes" in refused()
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).where(Participant.code == "KEEP-ME")) == 1
    ran = run_cli(database_url, "retention", "run", "--yes", "--study", lab.study)
    assert ran.exit_code == 0 and f"{lab.study}: anonymised 1 participant" in ran.output
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).where(Participant.code == "KEEP-ME")) == 0
