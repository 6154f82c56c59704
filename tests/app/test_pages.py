"""Server-rendered pages: content, htmx fragments, forms, confirmations and headers."""

from __future__ import annotations

from fastapi.testclient import TestClient

from app.protocol import default_protocol
from app.tables import Role
from tests.conftest import UserClientFactory, protocol_text


def test_empty_state_says_what_to_do(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    page = admin.get("/").text
    assert "No study yet." in page and "Create one from a protocol file" in page
    experimenter = user_client(Role.EXPERIMENTER)
    assert "Ask an admin to create one." in experimenter.get("/").text


def test_study_list_and_page(user_client: UserClientFactory, study_name: str) -> None:
    client = user_client(Role.EXPERIMENTER)
    listing = client.get("/").text
    assert 'href="/studies/default"' in listing
    page = client.get("/studies/default").text
    assert "Nobody is enrolled yet." in page
    assert "Enrol and randomise" in page
    assert "permuted blocks of 2 or 4" in page


def test_enrol_form_full_page_and_htmx_fragment(
    user_client: UserClientFactory, study_name: str
) -> None:
    client = user_client(Role.EXPERIMENTER)
    response = client.post("/studies/default/participants", data={"code": "K1"})
    assert response.status_code == 200
    assert "Enrolled K1: allocated to C" in response.text  # the notice, shown once
    assert "Enrolled K1" not in client.get("/studies/default").text
    duplicate = client.post(
        "/studies/default/participants", data={"code": "K1"}, headers={"HX-Request": "true"}
    )
    assert duplicate.status_code == 409
    assert duplicate.headers["vary"] == "HX-Request"
    assert duplicate.text.lstrip().startswith('<section id="participants"')
    assert "already used" in duplicate.text
    assert "<html" not in duplicate.text


def test_withdraw_asks_for_confirmation(user_client: UserClientFactory, study_name: str) -> None:
    client = user_client(Role.EXPERIMENTER)
    client.post("/studies/default/participants", data={"code": "W1"})
    confirm = client.get("/studies/default/participants/W1/withdraw")
    assert "Withdraw W1?" in confirm.text and "cannot be undone" in confirm.text
    done = client.post("/studies/default/participants/W1/withdraw", data={"reason": "tired"})
    assert "Withdrew W1." in done.text
    assert 'badge withdrawn">withdrawn' in done.text
    again = client.post("/studies/default/participants/W1/withdraw", data={})
    assert again.status_code == 409
    assert "already withdrawn" in again.text


def test_admin_manages_users(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    form = admin.get("/admin/users").text  # a new account is an experimenter unless chosen
    assert '<option value="experimenter" selected>' in form
    assert '<option value="admin" selected>' not in form
    created = admin.post(
        "/admin/users", data={"username": "Ada", "role": "analyst", "password": "long password 1"}
    )
    assert "Created ada." in created.text
    weak = admin.post("/admin/users", data={"username": "bob", "role": "analyst", "password": "x"})
    assert weak.status_code == 422
    assert "at least 10 characters" in weak.text


def test_admin_uploads_a_protocol(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    bad = protocol_text(**{"block_sizes = [2, 4]": "block_sizes = [3]", "sessions =": "sesions ="})
    refused = admin.post(
        "/admin/studies",
        data={"name": "lab"},
        files={"protocol": ("lab.toml", bad.encode(), "application/toml")},
    )
    assert refused.status_code == 422
    assert "lab.toml: allocation.block_sizes[0]: block size 3" in refused.text
    assert "lab.toml: schedule.sesions: Extra inputs" in refused.text  # both kinds at once
    accepted = admin.post(
        "/admin/studies",
        data={"name": "lab"},
        files={"protocol": ("lab.toml", default_protocol().source_text.encode(), "text/plain")},
    )
    assert accepted.status_code == 200
    assert "Study created." in accepted.text
    closed = admin.post("/admin/studies/lab/status", data={"status": "closed"})
    assert "Study is now closed." in closed.text and "Reopen enrolment" in closed.text


def test_unknown_pages_and_studies_render_html_errors(user_client: UserClientFactory) -> None:
    client = user_client(Role.ANALYST)
    missing = client.get("/studies/ghost", headers={"accept": "text/html"})
    assert missing.status_code == 404
    assert "no study named &#39;ghost&#39;" in missing.text
    nowhere = client.get("/no/such/page", headers={"accept": "text/html"})
    assert nowhere.status_code == 404 and "Not found" in nowhere.text


def test_security_headers(client: TestClient) -> None:
    headers = client.get("/login").headers
    policy = headers["content-security-policy"]
    assert "script-src 'self';" in policy and "frame-ancestors 'none'" in policy
    assert "unsafe-inline" not in policy.split("script-src")[1].split(";")[0]
    assert headers["x-content-type-options"] == "nosniff"
    assert headers["referrer-policy"] == "same-origin"
    assert headers["x-frame-options"] == "DENY"
    body = client.get("/login").text
    assert "<script>" not in body  # every script is an external file (the CSP forbids inline)
