"""The tablet flow over its JSON API: consent, pre-study, session and post-study questionnaires,
gates on the next session, validation, edits, locking and links."""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from app.tables import AuditEvent, Response, Submission
from tests.conftest import (
    POST_ANSWERS,
    TRUST_ANSWERS,
    Lab,
    fill_pre_study,
    tablet_client,
)


def item_errors(response: object) -> dict[str, str]:
    """The per-item messages of a refused questionnaire, keyed by item."""
    errors = response.json()["errors"]  # type: ignore[attr-defined]
    assert all(e["loc"][:2] == ["body", "answers"] for e in errors), errors
    return {e["loc"][2]: e["msg"] for e in errors}


def _count(lab: Lab, table: type) -> int:
    with lab.database.read_session() as db:
        return db.scalar(select(func.count()).select_from(table)) or 0


def test_the_whole_flow_with_gates(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    tablet = tablet_client(app, lab, code)
    page = tablet.get("/api/v1/tablet").json()
    assert page["kind"] == "consent" and page["consent"]["version"] == "1.0"
    blocked = lab.experimenter.post("/api/v1/stations/lab-1/sessions")
    assert blocked.status_code == 409
    assert blocked.json()["detail"] == (
        f"cannot start a session for {code}: waiting for {code} to give consent on the tablet"
    )
    tablet.post("/api/v1/tablet/consent", json={"accept": True})
    page = tablet.get("/api/v1/tablet").json()
    assert (page["kind"], page["instrument"]["key"]) == ("questionnaire", "demographics")
    assert (
        lab.experimenter.post("/api/v1/stations/lab-1/sessions")
        .json()["detail"]
        .endswith(
            "fill in on the tablet: About you, Your experience, Ten-Item Personality Inventory, "
            "Attitudes towards robots"
        )
    )
    fill_pre_study(tablet)
    assert tablet.get("/api/v1/tablet").json()["kind"] == "wait"
    lab.start_session()
    lab.run_session()  # familiarisation: no questionnaire follows
    assert tablet.get("/api/v1/tablet").json()["kind"] == "wait"
    lab.start_session()
    lab.run_session()
    page = tablet.get("/api/v1/tablet").json()
    assert (page["kind"], page["instrument"]["key"], page["session"]) == (
        "questionnaire",
        "trust",
        1,
    )
    state = lab.robot.get("/api/v1/station").json()
    assert state["expected"] == {
        "action": "wait",
        "message": f"waiting for {code}'s questionnaire after session 1: This session",
        "categories": [],
        "step_id": None,
        "session": 2,
    }
    answered = tablet.post(
        "/api/v1/tablet/questionnaires/trust", json={"session": 1, "answers": TRUST_ANSWERS}
    )
    assert answered.json()["kind"] == "wait"
    for number in (2, 3, 4):
        lab.start_session()
        lab.run_session()
        tablet.post(
            "/api/v1/tablet/questionnaires/trust",
            json={"session": number, "answers": TRUST_ANSWERS},
        )
    page = tablet.get("/api/v1/tablet").json()
    assert (page["kind"], page["instrument"]["key"]) == ("questionnaire", "overall")
    done = tablet.post("/api/v1/tablet/questionnaires/overall", json={"answers": POST_ANSWERS})
    assert done.json()["kind"] == "done"
    assert _count(lab, Submission) == 1 + 4 + 4 + 1


def test_invalid_answers_are_refused_and_nothing_partial_is_stored(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    tablet = tablet_client(app, lab, code)
    tablet.post("/api/v1/tablet/consent", json={"accept": True})
    before = _count(lab, Response)
    missing = tablet.post(
        "/api/v1/tablet/questionnaires/demographics", json={"answers": {"age": "30"}}
    )
    assert missing.status_code == 422
    assert item_errors(missing) == {"gender": "Please answer this question."}
    out_of_range = tablet.post(
        "/api/v1/tablet/questionnaires/demographics",
        json={"answers": {"age": 17, "gender": "female"}},
    )
    assert item_errors(out_of_range) == {"age": "Enter a number from 18 to 99."}
    bad_option = tablet.post(
        "/api/v1/tablet/questionnaires/demographics",
        json={"answers": {"age": 30, "gender": "robot"}},
    )
    assert item_errors(bad_option) == {"gender": "Choose one of the options."}
    unknown = tablet.post(
        "/api/v1/tablet/questionnaires/demographics",
        json={"answers": {"age": 30, "gender": "male", "shoe_size": 44}},
    )
    assert unknown.status_code == 422
    assert unknown.json()["detail"].startswith("demographics has no item 'shoe_size'")
    too_high = tablet.post(
        "/api/v1/tablet/questionnaires/tipi",
        json={"answers": {f"tipi_{n}": 8 if n == 3 else 4 for n in range(1, 11)}},
    )
    assert item_errors(too_high) == {"tipi_3": "Choose one of 1–7."}
    early = tablet.post(
        "/api/v1/tablet/questionnaires/trust", json={"session": 1, "answers": TRUST_ANSWERS}
    )
    assert early.status_code == 409
    assert early.json()["detail"] == (
        f"session 1 of {code} has not finished yet; its questionnaire opens when it ends"
    )
    no_session = tablet.post("/api/v1/tablet/questionnaires/trust", json={"answers": TRUST_ANSWERS})
    assert no_session.status_code == 422
    unknown_instrument = tablet.post("/api/v1/tablet/questionnaires/mood", json={"answers": {}})
    assert unknown_instrument.status_code == 404
    assert _count(lab, Response) == before
    described = tablet.post(
        "/api/v1/tablet/questionnaires/demographics",
        json={
            "answers": {"age": 44, "gender": "self_described", "gender_description": "genderfluid"}
        },
    )
    assert described.status_code == 200
    with lab.database.read_session() as db:
        stored = dict(
            db.execute(
                select(Response.item, Response.value).where(Response.instrument == "demographics")
            ).all()
        )
    assert stored == {"age": "44", "gender": "self_described", "gender_description": "genderfluid"}


def test_edits_are_audited_until_locked(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    tablet = tablet_client(app, lab, code)
    fill_pre_study(tablet)
    changed = {**{f"tipi_{n}": str(1 + n % 7) for n in range(1, 11)}, "tipi_1": "7"}
    assert (
        tablet.post("/api/v1/tablet/questionnaires/tipi", json={"answers": changed}).status_code
        == 200
    )
    with lab.database.read_session() as db:
        edit = db.scalars(
            select(AuditEvent).where(AuditEvent.action == "questionnaire.edited")
        ).one()
        revision = db.scalar(select(Submission.revision).where(Submission.instrument == "tipi"))
    assert edit.details == {
        "instrument": "tipi",
        "session": None,
        "item": "tipi_1",
        "old": "2",
        "new": "7",
    }
    assert revision == 2
    locked = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants/{code}/lock")
    assert locked.json()["locked"] is True
    refused = tablet.post("/api/v1/tablet/questionnaires/tipi", json={"answers": changed})
    assert refused.status_code == 409
    assert refused.json()["detail"] == (
        f"{code}'s answers are locked; the experimenter can unlock them"
    )


LOCKED_HELP = (
    "Locking freezes the answers for analysis: the tablet can neither submit new questionnaires "
    "nor change submitted ones until they are unlocked."
)


def test_locking_freezes_new_submissions_and_edits_until_unlocked(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    tablet = tablet_client(app, lab, code)
    base = f"/api/v1/studies/{lab.study}/participants/{code}"
    assert lab.experimenter.post(f"{base}/lock").json()["locked"] is True
    refusal = f"{code}'s answers are locked; the experimenter can unlock them"
    consent = tablet.post("/api/v1/tablet/consent", json={"accept": True})
    assert (consent.status_code, consent.json()["detail"]) == (409, refusal)
    assert lab.experimenter.post(f"{base}/unlock").json()["locked"] is False
    assert tablet.post("/api/v1/tablet/consent", json={"accept": True}).status_code == 200
    lab.experimenter.post(f"{base}/lock")
    new = tablet.post(
        "/api/v1/tablet/questionnaires/demographics",
        json={"answers": {"age": "27", "gender": "female"}},
    )
    assert (new.status_code, new.json()["detail"]) == (409, refusal)
    assert _count(lab, Submission) == 1, "only the consent is stored"
    assert tablet.get("/api/v1/tablet").json()["instrument"]["key"] == "demographics"
    lab.experimenter.post(f"{base}/unlock")
    fill_pre_study(tablet)
    # What the experimenter reads agrees: the participant page and the API's own description.
    lab.experimenter.post(f"{base}/lock")
    page = lab.experimenter.get(f"/studies/{lab.study}/participants/{code}").text
    assert "answers locked" in page and LOCKED_HELP in page
    described = lab.experimenter.get("/api/v1/openapi.json").json()["paths"]
    lock_doc = described["/api/v1/studies/{name}/participants/{code}/lock"]["post"]["description"]
    assert "new questionnaires" in lock_doc and "revisions" in lock_doc
    submit_doc = described["/api/v1/tablet/questionnaires/{instrument}"]["post"]["description"]
    assert "until locked, revise" not in submit_doc and "locked" in submit_doc


def test_links_can_be_revoked_and_reissued(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    base = f"/api/v1/studies/{lab.study}/participants/{code}/link"
    assert lab.experimenter.get(base).json() == {"token": None, "url": None}
    first = lab.experimenter.post(base).json()
    assert first["url"] == f"http://testserver/t/{first['token']}"
    assert lab.experimenter.get(base).json() == first  # shown again, e.g. as a QR code
    second = lab.experimenter.post(base).json()
    assert second["token"] != first["token"]
    with TestClient(app) as anonymous:
        old = anonymous.get("/api/v1/tablet", headers={"Authorization": f"Bearer {first['token']}"})
        assert old.status_code == 401
        assert old.json()["detail"] == "this tablet link is not valid (it may have been replaced)"
        new = anonymous.get(
            "/api/v1/tablet", headers={"Authorization": f"Bearer {second['token']}"}
        )
        assert new.json()["participant"] == code
        lab.experimenter.delete(base)
        revoked = anonymous.get(
            "/api/v1/tablet", headers={"Authorization": f"Bearer {second['token']}"}
        )
        assert revoked.status_code == 401


def test_kiosk_shows_whoever_is_seated(app: FastAPI, lab: Lab, user_client: object) -> None:
    from app.tables import Role

    admin = user_client(Role.ADMIN)  # type: ignore[operator]
    kiosk = admin.post("/api/v1/stations/lab-1/kiosk").json()
    assert kiosk["url"].startswith("http://testserver/k/tls_")
    with TestClient(app, headers={"Authorization": f"Bearer {kiosk['token']}"}) as tablet:
        empty = tablet.get("/api/v1/tablet")
        assert empty.status_code == 409
        assert "nobody is at station 'lab-1' yet" in empty.json()["detail"]
        first = lab.enrol_and_assign(questionnaires=False)
        assert tablet.get("/api/v1/tablet").json()["participant"] == first
        lab.experimenter.delete("/api/v1/stations/lab-1/participant")
        second = lab.enrol_and_assign(questionnaires=False)
        assert tablet.get("/api/v1/tablet").json()["participant"] == second
