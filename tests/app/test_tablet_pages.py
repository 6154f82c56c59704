"""The tablet's pages: the server decides the page, forms are protected, errors sit beside items."""

from __future__ import annotations

import re
import threading

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from app.tables import Role
from tests.conftest import Lab, UserClientFactory

FORM_TOKEN = re.compile(r'name="csrf_token" value="([^"]+)"')


def _open(app: FastAPI, lab: Lab, code: str) -> TestClient:
    base = f"/api/v1/studies/{lab.study}/participants/{code}/link"
    link = lab.experimenter.get(base).json()
    if link["token"] is None:
        link = lab.experimenter.post(base).json()
    client = TestClient(app)
    opened = client.get(f"/t/{link['token']}", follow_redirects=False)
    assert opened.status_code == 303 and opened.headers["location"] == "/tablet"
    assert "httponly" in opened.headers["set-cookie"].lower()
    return client


def _token(page: str) -> str:
    match = FORM_TOKEN.search(page)
    assert match, "the page has no form token"
    return match.group(1)


def test_pages_follow_the_flow_and_redirect_elsewhere(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    tablet = _open(app, lab, code)
    home = tablet.get("/tablet", follow_redirects=False)
    assert home.headers["location"] == "/tablet/consent"
    assert home.headers["cache-control"] == "no-store"
    skipped = tablet.get("/tablet/q/tipi", follow_redirects=False)
    assert skipped.status_code == 303 and skipped.headers["location"] == "/tablet/consent"
    consent = tablet.get("/tablet/consent")
    assert "I agree to take part" in consent.text
    assert "Your goal is to escape the room." in consent.text  # the rules are shown
    assert consent.headers["cache-control"] == "no-store"
    refused = tablet.post("/tablet/consent", data={"csrf_token": _token(consent.text)})
    assert refused.status_code == 422
    assert "Please tick the box to take part." in refused.text
    given = tablet.post(
        "/tablet/consent", data={"csrf_token": _token(consent.text), "accept": "yes"}
    )
    assert given.url.path == "/tablet/q/demographics"
    assert "How old are you" in given.text


def test_missing_items_get_messages_beside_them(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    tablet = _open(app, lab, code)
    consent = tablet.get("/tablet/consent")
    tablet.post("/tablet/consent", data={"csrf_token": _token(consent.text), "accept": "yes"})
    page = tablet.get("/tablet/q/demographics")
    answer = tablet.post(
        "/tablet/q/demographics", data={"csrf_token": _token(page.text), "age": "16"}
    )
    assert answer.status_code == 422
    assert 'id="err-age" role="alert">Enter a number from 18 to 99.<' in answer.text
    assert 'id="err-gender" role="alert">Please answer this question.' in answer.text
    assert 'value="16"' in answer.text  # what was typed is kept
    ok = tablet.post(
        "/tablet/q/demographics",
        data={"csrf_token": _token(page.text), "age": "30", "gender": "prefer_not_to_say"},
    )
    assert ok.url.path == "/tablet/q/background"
    likert = ok.text
    assert likert.count('type="radio" name="bg_robot_experience"') == 5
    assert "Very little" in likert and "Very much" in likert


def test_forms_need_their_token(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    tablet = _open(app, lab, code)
    forged = tablet.post("/tablet/consent", data={"accept": "yes", "csrf_token": "x.y"})
    assert forged.status_code == 403
    assert "This form expired" in forged.text


def test_a_tablet_reaches_only_its_own_participant(app: FastAPI, lab: Lab) -> None:
    first = lab.enrol_and_assign(questionnaires=False)
    lab.experimenter.delete("/api/v1/stations/lab-1/participant")
    second = lab.enrol_and_assign()  # fills consent and the pre-study questionnaires
    tablet = _open(app, lab, first)
    assert tablet.get("/tablet").url.path == "/tablet/consent"  # first's own page, not second's
    assert tablet.get("/tablet/wait", follow_redirects=False).headers["location"] == (
        "/tablet/consent"
    )
    experimenter_page = tablet.get("/", follow_redirects=False)
    assert experimenter_page.status_code == 303
    assert experimenter_page.headers["location"].startswith("/login")
    assert tablet.get("/api/v1/studies").status_code == 401
    assert second != first


def test_invalid_links_explain_themselves(client: TestClient) -> None:
    invalid = client.get("/t/tlp_nothing", headers={"accept": "text/html"})
    assert invalid.status_code == 401
    assert "This tablet link is not valid" in invalid.text
    bare = client.get("/tablet", headers={"accept": "text/html"})
    assert bare.status_code == 401
    assert "Open the tablet link (or scan the QR code)" in bare.text
    for page in (invalid.text, bare.text):  # a participant's page: no staff chrome, no sign-in
        assert (
            'class="tablet-page"' in page and "Please hand the tablet to the experimenter" in page
        )
        assert "/login" not in page and "topbar" not in page


def test_locked_answers_are_explained_on_a_participant_page(
    app: FastAPI, lab: Lab, user_client: UserClientFactory
) -> None:
    code = lab.enrol_and_assign(questionnaires=False)
    tablet = _open(app, lab, code)
    consent = tablet.get("/tablet/consent")
    assert "Page 1 of 5" in consent.text  # consent and the four pre-study questionnaires
    admin = user_client(Role.ADMIN)
    assert admin.post(f"/studies/{lab.study}/participants/{code}/lock").status_code == 200
    token = consent.text.split('name="csrf_token" value="')[1].split('"')[0]
    refused = tablet.post("/tablet/consent", data={"accept": "yes", "csrf_token": token})
    assert refused.status_code == 409
    assert "answers are locked" in refused.text
    assert 'class="tablet-page"' in refused.text and "/login" not in refused.text


def test_the_wait_page_is_told_when_a_session_ends(app: FastAPI, lab: Lab) -> None:
    code = lab.enrol_and_assign()
    tablet = _open(app, lab, code)
    assert tablet.get("/tablet").url.path == "/tablet/wait"
    lab.start_session()
    lines: list[str] = []
    worker = threading.Thread(target=lab.run_session)
    with tablet.stream("GET", "/tablet/events") as stream:
        received = stream.iter_lines()
        # the stream sends its retry hint once it has subscribed: no change can be missed now
        assert next(received).startswith("retry:")
        worker.start()
        for line in received:
            lines.append(line)
            if line.startswith("data:") and "session_ended" in line:
                break
    worker.join(timeout=30)
    assert "event: changed" in lines
    assert tablet.get("/tablet").url.path == "/tablet/wait"  # familiarisation has no questionnaire


@pytest.mark.parametrize("how", ["revoke", "reissue"])
def test_a_tablets_stream_ends_when_its_link_is_revoked_or_replaced(
    app: FastAPI, lab: Lab, how: str
) -> None:
    """A revoked or replaced link must not keep hearing the participant's changes through a
    stream it opened before (its EventSource's reconnection is then refused)."""
    code = lab.enrol_and_assign()
    tablet = _open(app, lab, code)
    link = f"/api/v1/studies/{lab.study}/participants/{code}/link"
    with tablet.stream("GET", "/tablet/events") as stream:
        received = stream.iter_lines()
        assert next(received).startswith("retry:")  # subscribed
        changed = lab.experimenter.delete(link) if how == "revoke" else lab.experimenter.post(link)
        assert changed.status_code in (200, 204), changed.text
        rest = list(received)  # ends instead of waiting for the next change
    assert not any(line.startswith("event:") for line in rest)
    assert tablet.get("/tablet/events").status_code == 401
