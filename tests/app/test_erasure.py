"""Withdrawal with erasure: nothing of the participant left in any table, any export or the
database file; their allocation slot kept so the sequence still balances and verifies; everyone
else untouched; each refusal in one line with nothing changed."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import delete, func, select
from sqlalchemy.engine import make_url
from sqlalchemy.exc import DBAPIError
from typer.testing import CliRunner, Result

from app.cli import cli
from app.db import Database
from app.protocol import parse_protocol
from app.services import erasure, studies, verify
from app.services.audit import Actor
from app.tables import (
    Allocation,
    Answer,
    AuditEvent,
    ErasureInProgress,
    Participant,
    Prompt,
    Role,
)
from tests.conftest import (
    EXP3_ONLY,
    PRE_STUDY_ANSWERS,
    Lab,
    UserClientFactory,
    protocol_text,
    sqlite_only,
    tablet_client,
)

FREE_TEXT = "Quagmire-Xylophone remembers the orange lighthouse"
TRANSCRIPT = "yes zebrafish certainly"
STRATUM = "lefthanded"
AGE_ITEM = (
    '{ key = "age", text = "How old are you (in years)?", kind = "number", minimum = 18, '
    "maximum = 99 },"
)
NOTE_ITEM = (
    '{ key = "note", text = "Anything else?", kind = "text", required = false, max_length = 400 },'
)


def _erasable_study(database: Database, name: str = "erasable", **replacements: str) -> str:
    """Exp3 in both conditions, a free-text pre-study item, stratified by handedness."""
    text = protocol_text(
        **EXP3_ONLY,
        **{AGE_ITEM: AGE_ITEM + "\n    " + NOTE_ITEM},
        **{"stratify_by = []": 'stratify_by = ["hand"]'},
        **replacements,
    )
    with database.writing() as db:
        studies.create_study(db, name=name, loaded=parse_protocol(text), actor=Actor.system())
    return name


def _note(code: str) -> str:
    """The participant's free-text answer (distinct per participant)."""
    return f"{FREE_TEXT} for {code.lower()}"


def _enrol_with_data(lab: Lab, code: str) -> None:
    """Enrol, consent, pre-study with free text, the practice run answered by voice."""
    enrolled = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants",
        json={"code": code, "strata": {"hand": STRATUM}},
    )
    assert enrolled.status_code == 201, enrolled.text
    seated = lab.experimenter.put(
        f"/api/v1/stations/{lab.station}/participant", json={"study": lab.study, "code": code}
    )
    assert seated.status_code == 200, seated.text
    tablet = lab.tablets[code] = tablet_client(lab.app, lab, code)
    assert tablet.post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
    for instrument, answers in PRE_STUDY_ANSWERS.items():
        extra = {"note": _note(code)} if instrument == "demographics" else {}
        sent = tablet.post(
            f"/api/v1/tablet/questionnaires/{instrument}", json={"answers": answers | extra}
        )
        assert sent.status_code == 200, sent.text
    lab.start_session()
    expected = lab.robot.get("/api/v1/station").json()["expected"]
    for category in expected["categories"]:
        step = lab.prompt(category)
        answered = lab.robot.post(
            f"/api/v1/station/steps/{step['step_id']}/answer",
            json={
                "answer": "yes",
                "idempotency_key": f"{code}-{category}",
                "modality": "speech",
                "transcript": f"{TRANSCRIPT} {code.lower()}",
                "transcript_confidence": 0.9,
            },
        )
        assert answered.status_code == 200, answered.text


def _cli(database_url: str, *args: str) -> Result:
    return CliRunner().invoke(cli, list(args), env={"TRUSTLAB_DATABASE_URL": database_url})


def _dump(database: Database) -> bytes:
    """Everything the database holds: pg_dump's SQL, or the SQLite file and its WAL byte for
    byte (deleted content included, were it not zeroed)."""
    url = make_url(database.url)
    if url.get_backend_name() == "sqlite":
        database.dispose()
        path = Path(str(url.database))
        return b"".join(
            p.read_bytes() for p in (path, path.with_name(path.name + "-wal")) if p.exists()
        )
    conninfo = url.set(drivername="postgresql").render_as_string(hide_password=False)
    return subprocess.run(
        ["pg_dump", "--data-only", conninfo], capture_output=True, check=True
    ).stdout


def _mentions(content: bytes, code: str) -> list[str]:
    found = []
    # Not the stratum: it stays with the allocation slot, shared with others of the stratum.
    for secret in (code, _note(code), f"{TRANSCRIPT} {code.lower()}"):
        if re.search(rb"(?<![A-Za-z0-9_-])" + re.escape(secret.encode()), content):
            found.append(secret)
    return found


def test_an_erased_participant_leaves_no_trace_and_their_slot_keeps_the_sequence_whole(
    lab: Lab, database_url: str, tmp_path: Path
) -> None:
    lab.study = _erasable_study(lab.database)
    _enrol_with_data(lab, "GONE-4711")
    _enrol_with_data(lab, "STAYS-0815")
    before = _cli(
        database_url,
        "export",
        "--study",
        lab.study,
        "--format",
        "all",
        "--out",
        str(tmp_path / "before"),
    )
    assert before.exit_code == 0, before.output
    with lab.database.read_session() as db:
        allocations = db.scalar(select(func.count()).select_from(Allocation))
        kept_answers = db.scalar(
            select(func.count())
            .select_from(Answer)
            .join(Participant)
            .where(Participant.code == "STAYS-0815")
        )

    erased = _cli(
        database_url,
        "participant",
        "withdraw",
        "--study",
        lab.study,
        "--code",
        "GONE-4711",
        "--erase",
        "--yes",
    )

    assert erased.exit_code == 0, erased.output
    assert "erased GONE-4711" in erased.output and "allocation slot stays" in erased.output
    assert str(tmp_path / "before") in erased.output  # the earlier export is listed
    assert _mentions(_dump(lab.database), "GONE-4711") == []
    after = _cli(
        database_url,
        "export",
        "--study",
        lab.study,
        "--format",
        "all",
        "--out",
        str(tmp_path / "after"),
    )
    assert after.exit_code == 0, after.output
    files = list((tmp_path / "after").iterdir())
    assert len(files) > 5
    for path in files:
        assert _mentions(path.read_bytes(), "GONE-4711") == [], path.name
    wide = next(p for p in files if p.name.endswith("wide.csv")).read_text()
    assert "STAYS-0815" in wide
    with lab.database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(Allocation)) == allocations
        assert (
            db.scalar(
                select(func.count())
                .select_from(Answer)
                .join(Participant)
                .where(Participant.code == "STAYS-0815")
            )
            == kept_answers
        )
        slot = db.scalar(select(Participant).where(Participant.erased_at.is_not(None)))
        assert slot is not None and erasure.is_erased_code(slot.code) and slot.status == "withdrawn"
        assert slot.strata == {} and slot.token_hash is None and slot.language is None
        assert db.scalar(select(func.count()).select_from(ErasureInProgress)) == 0
        event = db.scalar(select(AuditEvent).where(AuditEvent.action == "participant.erased"))
        assert event is not None and event.subject == slot.code
        report = verify.verify_study(db, study_name=lab.study)
    assert report.ok, report.to_json()
    # The stratum's sequence goes on after the erased slot: the next enrolment verifies too.
    enrolled = lab.experimenter.post(
        f"/api/v1/studies/{lab.study}/participants",
        json={"code": "NEXT-1", "strata": {"hand": STRATUM}},
    )
    assert enrolled.status_code == 201, enrolled.text
    with lab.database.read_session() as db:
        assert verify.verify_study(db, study_name=lab.study).ok


@sqlite_only("refusals happen before anything is written; the database does not matter")
def test_each_refusal_is_one_line_and_changes_nothing(lab: Lab, database_url: str) -> None:
    lab.study = _erasable_study(lab.database)
    _enrol_with_data(lab, "P-ONE")
    keep_only = _erasable_study(
        lab.database, "kept", **{"[allocation]": '[withdrawal]\noptions = ["keep"]\n\n[allocation]'}
    )
    erase_only = _erasable_study(
        lab.database,
        "erasing",
        **{"[allocation]": '[withdrawal]\noptions = ["erase"]\n\n[allocation]'},
    )
    for study in (keep_only, erase_only):
        assert (
            lab.experimenter.post(
                f"/api/v1/studies/{study}/participants",
                json={"code": "Q1", "strata": {"hand": "x"}},
            ).status_code
            == 201
        )

    def refused(*args: str) -> str:
        result = _cli(database_url, "participant", "withdraw", *args)
        assert result.exit_code != 0, result.output
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in result.output, result.output
        return lines[0]

    assert "add --yes" in refused("--study", lab.study, "--code", "P-ONE", "--erase")
    assert "no participant 'NOBODY'" in refused(
        "--study", lab.study, "--code", "NOBODY", "--erase", "--yes"
    )
    assert "has no 'erase'" in refused("--study", keep_only, "--code", "Q1", "--erase", "--yes")
    assert "erase instead" in refused("--study", erase_only, "--code", "Q1")
    with lab.database.read_session() as db:
        answers = db.scalar(select(func.count()).select_from(Answer))
        assert (
            answers
            and db.scalar(select(Participant.erased_at).where(Participant.code == "P-ONE")) is None
        )
    ok = _cli(
        database_url,
        "participant",
        "withdraw",
        "--study",
        lab.study,
        "--code",
        "P-ONE",
        "--erase",
        "--yes",
    )
    assert ok.exit_code == 0, ok.output
    assert "already erased" in refused("--study", lab.study, "--code", "P-ONE", "--erase", "--yes")
    kept = _cli(
        database_url,
        "participant",
        "withdraw",
        "--study",
        erase_only,
        "--code",
        "Q1",
        "--erase",
        "--yes",
    )
    assert kept.exit_code == 0 and "(rows removed: learner 3)" in kept.output


@sqlite_only("the guard's SQL differs per database; test_schema checks PostgreSQL's exists")
def test_the_marker_opens_the_guard_for_the_marked_participant_only(lab: Lab) -> None:
    lab.study = _erasable_study(lab.database)
    _enrol_with_data(lab, "P-MARKED")
    _enrol_with_data(lab, "P-OTHER")
    with lab.database.writing() as db:
        marked, other = (
            db.scalar(select(Participant.id).where(Participant.code == code))
            for code in ("P-MARKED", "P-OTHER")
        )
        db.add(ErasureInProgress(participant_id=marked, study_id=1))
        db.flush()
        db.execute(delete(Answer).where(Answer.participant_id == marked))
        with pytest.raises(DBAPIError, match="append-only"):
            db.execute(delete(Answer).where(Answer.participant_id == other))
        db.rollback()
    with lab.database.writing() as db:
        with pytest.raises(DBAPIError, match="append-only"):
            db.execute(delete(Prompt).where(Prompt.participant_id == marked))
        db.rollback()


@sqlite_only("the web form; the erasure itself is checked on both databases above")
def test_the_web_page_asks_which_option_and_for_the_code_before_erasing(
    lab: Lab, user_client: UserClientFactory
) -> None:
    lab.study = _erasable_study(lab.database)
    _enrol_with_data(lab, "P-WEB")
    experimenter = user_client(Role.EXPERIMENTER, "web-experimenter")
    page = experimenter.get(f"/studies/{lab.study}/participants/P-WEB/withdraw")
    assert page.status_code == 200
    assert (
        'value="keep"' in page.text and 'value="erase"' in page.text and "confirm_code" in page.text
    )
    form = experimenter.post(
        f"/studies/{lab.study}/participants/P-WEB/withdraw",
        data={"data": "erase", "confirm_code": "P-WE"},
    )
    assert form.status_code == 422 and "Type P-WEB to confirm" in form.text
    with lab.database.read_session() as db:
        assert db.scalar(select(Participant.erased_at).where(Participant.code == "P-WEB")) is None
    done = experimenter.post(
        f"/studies/{lab.study}/participants/P-WEB/withdraw",
        data={"data": "erase", "confirm_code": "P-WEB"},
    )
    assert done.status_code == 200 and "Erased P-WEB" in done.text
    study_page = experimenter.get(f"/studies/{lab.study}")
    assert "P-WEB" not in study_page.text and "(1) was erased" in study_page.text


@sqlite_only("the API's validation; the erasure itself is checked on both databases above")
def test_the_api_needs_the_code_repeated(lab: Lab, client: TestClient) -> None:
    lab.study = _erasable_study(lab.database)
    _enrol_with_data(lab, "P-API")
    url = f"/api/v1/studies/{lab.study}/participants/P-API/erase"
    wrong = lab.experimenter.post(url, json={"confirm": "P-AP"})
    assert wrong.status_code == 422 and "confirm must repeat" in wrong.text
    done = lab.experimenter.post(url, json={"confirm": "P-API"})
    assert done.status_code == 200, done.text
    body = done.json()
    assert body["removed"]["answer"] == 3 and body["removed"]["response"] > 0
    again = lab.experimenter.post(url, json={"confirm": "P-API"})
    assert again.status_code == 409 and "already erased" in again.json()["detail"]
    listed = lab.experimenter.get(f"/api/v1/studies/{lab.study}/participants").json()
    assert all(p["code"] != "P-API" and not p["code"].startswith("~") for p in listed)
