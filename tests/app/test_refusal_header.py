"""What static/js/refusals.js relies on: a refused page request carries the page's own message in
X-Trustlab-Refusal (percent-encoded UTF-8); staff and tablet responses are never stored."""

from __future__ import annotations

from urllib.parse import unquote

from fastapi.testclient import TestClient

from tests.conftest import Lab

HTMX = {"HX-Request": "true"}


def test_a_refused_enrolment_carries_its_message(lab: Lab) -> None:
    taken = lab.enrol_and_assign("P777", questionnaires=False)
    refused = lab.experimenter.post(
        f"/studies/{lab.study}/participants", data={"code": taken}, headers=HTMX
    )
    assert refused.status_code == 409
    message = f"participant code '{taken}' is already used in study 'rt'"
    assert unquote(refused.headers["x-trustlab-refusal"]) == message
    assert message.replace("'", "&#39;") in refused.text  # the page says the same words


def test_a_refused_console_action_and_an_error_page_carry_theirs(lab: Lab) -> None:
    seat = lab.experimenter.post(
        "/stations/lab-1/assign", data={"study": lab.study, "code": "NÖPE"}, headers=HTMX
    )
    assert seat.status_code == 404
    assert unquote(seat.headers["x-trustlab-refusal"]) == "study 'rt' has no participant 'NÖPE'"
    missing = lab.experimenter.get("/stations/nowhere", headers=HTMX)
    assert missing.status_code == 404 and "nowhere" in unquote(
        missing.headers["x-trustlab-refusal"]
    )
    fine = lab.experimenter.get("/stations/lab-1", headers=HTMX)
    assert fine.status_code == 200 and "x-trustlab-refusal" not in fine.headers


def test_nothing_but_static_files_may_be_stored(lab: Lab, app: object) -> None:
    for path in (f"/studies/{lab.study}", "/stations", f"/api/v1/studies/{lab.study}"):
        assert lab.experimenter.get(path).headers["cache-control"] == "no-store", path
    with TestClient(app) as anonymous:  # type: ignore[arg-type]
        assert anonymous.get("/login").headers["cache-control"] == "no-store"
        assert "no-store" not in anonymous.get("/static/css/app.css").headers.get(
            "cache-control", ""
        )
