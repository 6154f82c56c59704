"""Versions of the consent text: adding one, re-consent before the next session (tablet API,
session start, staff pages), the record of every version accepted, and bad input refused."""

from __future__ import annotations

import dataclasses
import re

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import func, select, update

from app.db import Database
from app.errors import InvalidInput, NotFound
from app.protocol import parse_protocol
from app.services import studies
from app.services.audit import Actor
from app.services.privacy import consent, subject_access
from app.settings import REPO_ROOT
from app.tables import AuditEvent, ConsentRecord, ConsentVersion, Response, Role
from tests.conftest import (
    EXP3_ONLY,
    Lab,
    UserClientFactory,
    protocol_text,
    sqlite_only,
    tablet_client,
)

RECONSENT = {
    '[questionnaires.consent]\nversion = "1.0"': (
        '[questionnaires.consent]\nreconsent_before_next_session = true\nversion = "1.0"'
    )
}
NEW_TEXT = "You are invited to a study of robots. We now also keep your answers for ten years."
ADMIN = Actor.system("tests")


def _create(database: Database, name: str, **replacements: str) -> str:
    loaded = parse_protocol(protocol_text(**EXP3_ONLY, **replacements))
    with database.writing() as db:
        studies.create_study(db, name=name, loaded=loaded, actor=ADMIN)
    return name


def _add(database: Database, study: str, text: str = NEW_TEXT, **options: str) -> consent.Version:
    with database.writing() as db:
        return consent.add_version(db, study_name=study, texts={"": text}, actor=ADMIN, **options)


def _records(database: Database) -> list[tuple[int, bool]]:
    with database.read_session() as db:
        rows = db.execute(
            select(ConsentRecord.version, ConsentRecord.accepted).order_by(ConsentRecord.id)
        )
        return [(version, accepted) for version, accepted in rows]


def test_a_new_version_is_accepted_before_the_next_session(
    app: FastAPI, lab: Lab, user_client: UserClientFactory
) -> None:
    lab = dataclasses.replace(lab, study=_create(lab.database, "again", **RECONSENT))
    code = lab.enrol_and_assign()
    tablet = lab.tablets[code]
    lab.start_session()
    lab.run_session()  # the familiarisation run
    assert _records(lab.database) == [(1, True)]

    added = _add(lab.database, lab.study, reason="amendment 2 approved")
    assert (added.number, added.label) == (2, "2")
    page = tablet.get("/api/v1/tablet").json()
    assert page["kind"] == "consent"
    assert page["consent"] == {"version": "2", "number": 2, "text": NEW_TEXT, "again": True}
    refused = lab.experimenter.post(f"/api/v1/stations/{lab.station}/sessions")
    assert refused.status_code == 409
    waiting = (
        f"waiting for {code} to accept version 2 of the consent text on the tablet "
        "(they accepted version 1)"
    )
    assert refused.json()["detail"] == f"cannot start a session for {code}: {waiting}"
    assert lab.robot.get("/api/v1/station").json()["expected"]["message"] == waiting

    # Accepting words not shown (version 1's form, sent after version 2 was added) is refused.
    stale = tablet.post("/api/v1/tablet/consent", json={"accept": True, "version": 1})
    assert stale.status_code == 409 and "now version 2" in stale.json()["detail"]
    declined = tablet.post("/api/v1/tablet/consent", json={"accept": False, "decline": True})
    assert declined.json()["kind"] == "consent"  # still asked; staff decide about withdrawal
    admin = user_client(Role.ADMIN)
    study_page = admin.get(f"/studies/{lab.study}").text
    assert "declined consent version 2" in study_page
    assert f"{code} declined version 2 of the consent text" in study_page
    one = lab.experimenter.get(f"/api/v1/studies/{lab.study}/participants/{code}").json()
    assert one["status"] != "withdrawn"
    assert one["consent"] == {
        "current_version": 2,
        "accepted_version": 1,
        "declined_version": 2,
        "reconsent_needed": True,
        "before_next_session": True,
    }

    accepted = tablet.post("/api/v1/tablet/consent", json={"accept": True, "version": 2})
    assert accepted.status_code == 200 and accepted.json()["kind"] == "wait"
    lab.start_session()
    assert _records(lab.database) == [(1, True), (2, False), (2, True)]
    with lab.database.read_session() as db:
        stored = dict(
            db.execute(
                select(Response.item, Response.value).where(Response.instrument == "consent")
            ).all()
        )
        actions = db.scalars(
            select(AuditEvent.action)
            .where(AuditEvent.action.like("%consent%"))
            .order_by(AuditEvent.id)
        ).all()
    assert stored["consent_version"] == "2" and stored["protocol_version"] == "2"
    assert stored["consent_sha256"] == consent.digest(NEW_TEXT)
    assert actions == [
        "participant.consented",
        "consent.version_added",
        "participant.consent_declined",
        "participant.reconsented",
    ]
    record_page = admin.get(f"/studies/{lab.study}/participants/{code}").text
    assert re.search(r"<td>1 <span[^>]*>\(1\.0\)</span></td><td>accepted</td>", record_page)
    assert re.search(r"<td>2 <span[^>]*>\(2\)</span></td><td>declined</td>", record_page)
    assert "declined consent version 2" not in admin.get(f"/studies/{lab.study}").text


def test_without_reconsent_the_flag_only_informs(app: FastAPI, lab: Lab) -> None:
    first = lab.enrol_and_assign()
    _add(lab.database, lab.study, label="1.1")
    assert lab.tablets[first].get("/api/v1/tablet").json()["kind"] == "wait"
    lab.start_session()  # not held back
    lab.run_session()
    page = lab.experimenter.get(f"/studies/{lab.study}").text
    assert "re-consent needed (accepted version 1 of 2)" in page
    listed = lab.experimenter.get(f"/api/v1/studies/{lab.study}/participants").json()
    assert [p["consent"] for p in listed] == [
        {
            "current_version": 2,
            "accepted_version": 1,
            "declined_version": None,
            "reconsent_needed": True,
            "before_next_session": False,  # the protocol only flags them
        }
    ]
    # Someone enrolled now consents to the current version, in the words they were shown.
    second = lab.enrol_and_assign(questionnaires=False)
    tablet = tablet_client(app, lab, second)
    shown = tablet.get("/api/v1/tablet").json()["consent"]
    assert shown == {"version": "1.1", "number": 2, "text": NEW_TEXT, "again": False}
    before = lab.experimenter.get(f"/api/v1/studies/{lab.study}/participants/{second}").json()
    assert before["consent"]["accepted_version"] is None  # not consented yet
    assert before["consent"]["reconsent_needed"] is False
    assert tablet.post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
    after = lab.experimenter.get(f"/api/v1/studies/{lab.study}/participants/{second}").json()
    assert after["consent"]["accepted_version"] == 2
    with lab.database.read_session() as db:
        assert consent.standing(db, *_participant(db, lab.study, second)).note == ""
        record = subject_access.participant_record(db, study_name=lab.study, code=second)
    assert [(c["version"], c["label"], c["answer"]) for c in record["consent"]] == [
        (2, "1.1", "accepted")
    ]
    assert record["consent"][0]["sha256"] == consent.digest(NEW_TEXT)


def _participant(db: object, study: str, code: str) -> tuple[object, object]:
    from app.services.participants import enrolment

    found = studies.get_study(db, study)  # type: ignore[arg-type]
    return enrolment.get_participant(db, found, code, actor=Actor.system()), found  # type: ignore[arg-type]


def test_the_study_page_adds_a_version_after_confirmation(
    client: TestClient, database: Database, study_name: str, user_client: UserClientFactory
) -> None:
    admin = user_client(Role.ADMIN)
    page = admin.get(f"/studies/{study_name}").text
    assert "Consent text · version 1 (1.0)" in page and "Add version 2" in page
    form = {"text_en": NEW_TEXT, "label": "2.0", "reason": "ethics amendment"}
    unconfirmed = admin.post(f"/admin/studies/{study_name}/consent", data=form)
    assert unconfirmed.status_code == 422
    assert "tick the box to confirm the new text; nothing was added" in unconfirmed.text
    added = admin.post(
        f"/admin/studies/{study_name}/consent",
        data=form | {"confirm": "yes"},
        follow_redirects=False,
    )
    assert added.status_code == 303
    page = admin.get(f"/studies/{study_name}").text
    assert "Added version 2 (2.0) of the consent text." in page
    assert consent.digest(NEW_TEXT)[:12] in page and "ethics amendment" in page
    again = admin.post(f"/admin/studies/{study_name}/consent", data=form | {"confirm": "yes"})
    assert again.status_code == 422 and "unchanged: the text is version 2&#39;s" in again.text
    with database.read_session() as db:
        assert db.scalars(select(ConsentVersion.version)).all() == [1, 2]
    experimenter = user_client(Role.EXPERIMENTER)
    assert "Add version" not in experimenter.get(f"/studies/{study_name}").text


@sqlite_only("every refusal comes before anything is written; the queries are the same")
@pytest.mark.parametrize(
    ("texts", "options", "refusal"),
    [
        ({"": "   "}, {}, "text: empty in 'en': give the text"),
        ({}, {}, "text: missing"),
        ({"": NEW_TEXT, "sv": "Hej"}, {}, "translations.sv: 'sv' is not one of the study's"),
        ({"": NEW_TEXT, "en": "Hi"}, {}, "'en' is the study's first language"),
        ({"": NEW_TEXT}, {"label": "1.0"}, "version: '1.0' is version 1's label already"),
        ({"": "x" * 2001}, {}, "text: at most 2000 characters in 'en'"),
    ],
    ids=["empty", "missing", "unknown-language", "first-as-translation", "label", "long"],
)
def test_bad_texts_are_refused_and_nothing_is_written(
    database: Database,
    study_name: str,
    texts: dict[str, str],
    options: dict[str, str],
    refusal: str,
) -> None:
    with database.writing() as db, pytest.raises(InvalidInput, match=re.escape(refusal)):
        consent.add_version(db, study_name=study_name, texts=texts, actor=ADMIN, **options)
    with database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(ConsentVersion)) == 0


@sqlite_only("refused before anything is written")
def test_unchanged_unknown_and_unmentioned_recording_are_refused(database: Database) -> None:
    with database.writing() as db, pytest.raises(NotFound, match="no study named 'ghost'"):
        consent.add_version(db, study_name="ghost", texts={"": NEW_TEXT}, actor=ADMIN)
    multilingual = "sv-study"
    with database.writing() as db:
        loaded = parse_protocol(
            (REPO_ROOT / "app/protocols/fast_adaptation_trust_sv.toml").read_text()
        )
        studies.create_study(db, name=multilingual, loaded=loaded, actor=ADMIN)
        own = consent.versions(db, studies.get_study(db, multilingual))[0].texts
    with database.writing() as db, pytest.raises(InvalidInput, match="unchanged"):
        consent.add_version(db, study_name=multilingual, texts=dict(own), actor=ADMIN)
    with (
        database.writing() as db,
        pytest.raises(InvalidInput, match=r"translations\.sv\.text: missing in 'sv'"),
    ):
        consent.add_version(db, study_name=multilingual, texts={"": NEW_TEXT}, actor=ADMIN)
    recording = _create(
        database,
        "recorded",
        **{
            "record_audio = false": "record_audio = true",
            "Your answers are stored under a code": (
                "Your spoken answers are recorded as audio. Your answers are stored under a code"
            ),
        },
    )
    with database.writing() as db, pytest.raises(InvalidInput, match="voice is recorded"):
        consent.add_version(db, study_name=recording, texts={"": NEW_TEXT}, actor=ADMIN)
    with database.read_session() as db:
        assert db.scalar(select(func.count()).select_from(ConsentVersion)) == 0


def test_verify_checks_each_consent_against_its_version(lab: Lab) -> None:
    from app.services.sessions import verify

    lab = dataclasses.replace(lab, study=_create(lab.database, "checked", **RECONSENT))
    code = lab.enrol_and_assign()
    _add(lab.database, lab.study)
    assert (
        lab.tablets[code].post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
    )
    with lab.database.read_session() as db:
        assert verify.verify_study(db, study_name=lab.study).findings == []
    with lab.database.writing() as db:
        db.execute(update(ConsentRecord).where(ConsentRecord.version == 2).values(sha256="0" * 64))
        db.commit()
    with lab.database.read_session() as db:
        findings = verify.verify_study(db, study_name=lab.study).findings
    assert [(f.check, f.participant, f.detail) for f in findings] == [
        ("consent", code, "the words of version 2 answered in en are not the version's")
    ]
