"""The account pages: an admin's page per account, everyone's own page, what sign-in shows a
disabled account, and the failed sign-ins in the audit log."""

from __future__ import annotations

import json
import threading

from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.db import Database
from app.services.staff import login_throttle
from app.tables import AuditEvent, Role
from tests.conftest import CSRF_INPUT, PASSWORD, UserClientFactory, make_user, sign_in_api

NEW_PASSWORD = "a brand new passphrase"


def _login_form(client: TestClient, username: str, password: str) -> tuple[int, str]:
    token = CSRF_INPUT.search(client.get("/login").text)
    assert token
    response = client.post(
        "/login",
        data={"username": username, "password": password, "csrf_token": token.group(1)},
        follow_redirects=False,
    )
    return response.status_code, response.text


def _audit(database: Database, action: str) -> list[AuditEvent]:
    with database.read_session() as db:
        return list(
            db.scalars(
                select(AuditEvent).where(AuditEvent.action == action).order_by(AuditEvent.id)
            )
        )


def test_disabling_signs_the_browser_out_at_once(
    user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN)
    ada = user_client(Role.EXPERIMENTER, "ada")
    assert ada.get("/").status_code == 200
    page = admin.get("/admin/users/ada")
    assert page.status_code == 200 and 'href="/admin/users/ada/disable"' in page.text
    confirm = admin.get("/admin/users/ada/disable")  # asks first, without needing JavaScript
    assert confirm.status_code == 200 and "Disable ada?" in confirm.text
    assert 'method="post" action="/admin/users/ada/disable"' in confirm.text
    assert ada.get("/").status_code == 200  # asking changed nothing
    done = admin.post("/admin/users/ada/disable", follow_redirects=False)
    assert done.status_code == 303 and done.headers["location"] == "/admin/users/ada"
    following = ada.get("/", follow_redirects=False)
    assert following.status_code == 303 and following.headers["location"] == "/login?next=/"
    assert ada.get("/api/v1/studies").status_code == 401
    listing = admin.get("/admin/users")
    assert '<a href="/admin/users/ada">ada</a>' in listing.text and "disabled" in listing.text
    assert [e.subject for e in _audit(database, "user.disabled")] == ["ada"]
    enabled = admin.post("/admin/users/ada/enable", follow_redirects=False)
    assert enabled.status_code == 303
    assert _login_form(TestClient(admin.app), "ada", PASSWORD)[0] == 303


def test_a_disabled_account_is_told_so_only_with_its_password(
    app: FastAPI, user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN)
    make_user(database, "ada", Role.ANALYST)
    admin.post("/admin/users/ada/disable")
    client = TestClient(app)
    status, page = _login_form(client, "ada", PASSWORD)
    assert status == 403 and "This account is disabled" in page
    status, page = _login_form(client, "ada", "wrong password")
    assert status == 401 and "Invalid username or password." in page
    assert "disabled" not in page.split("<main")[1]
    api = client.post("/api/v1/session", json={"username": "ada", "password": PASSWORD})
    assert api.status_code == 403 and "disabled" in api.json()["detail"]
    assert "tl_session" not in client.cookies


def test_the_last_active_admin_is_refused_on_the_page(
    user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN, "root")
    for path, data in (("disable", {}), ("role", {"role": "analyst"})):
        refused = admin.post(f"/admin/users/root/{path}", data=data)
        assert refused.status_code == 409
        assert "&#39;root&#39; is the last active admin" in refused.text
    assert admin.get("/admin/users").status_code == 200  # still an admin, still signed in
    assert _audit(database, "user.disabled") == _audit(database, "user.role_changed") == []


def test_a_role_change_applies_to_the_next_request(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    ada = user_client(Role.EXPERIMENTER, "ada")
    assert ada.get("/admin/users").status_code == 403
    assert admin.post("/admin/users/ada/role", data={"role": "admin"}).status_code == 200
    assert ada.get("/admin/users").status_code == 200
    assert admin.post("/admin/users/ada/role", data={"role": "analyst"}).status_code == 200
    assert ada.get("/admin/users").status_code == 403
    assert ada.post("/api/v1/studies/x/participants", json={}).status_code == 403
    assert admin.post("/admin/users/ada/role", data={"role": "boss"}).status_code == 422


def test_an_admin_resets_a_password_and_ends_its_sign_ins(
    app: FastAPI, user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN)
    ada = user_client(Role.ANALYST, "ada")
    form = admin.get("/admin/users/ada/password")
    assert form.status_code == 200 and "Every sign-in of ada ends" in form.text
    mismatch = admin.post(
        "/admin/users/ada/password", data={"password": NEW_PASSWORD, "confirm": "something else"}
    )
    assert mismatch.status_code == 422 and "the two new passwords differ" in mismatch.text
    assert 'action="/admin/users/ada/password"' in mismatch.text  # the form again, to retry
    weak = admin.post("/admin/users/ada/password", data={"password": "short", "confirm": "short"})
    assert weak.status_code == 422 and "at least 10 characters" in weak.text
    assert ada.get("/").status_code == 200
    done = admin.post(
        "/admin/users/ada/password", data={"password": NEW_PASSWORD, "confirm": NEW_PASSWORD}
    )
    assert done.status_code == 200
    assert ada.get("/api/v1/studies").status_code == 401
    assert _login_form(TestClient(app), "ada", PASSWORD)[0] == 401
    assert _login_form(TestClient(app), "ada", NEW_PASSWORD)[0] == 303
    assert admin.get("/").status_code == 200  # the admin's own sign-in is not touched
    [event] = _audit(database, "user.password_set")
    assert event.subject == "ada" and NEW_PASSWORD not in json.dumps(event.details)


def test_an_admin_unlocks_a_locked_out_account(
    app: FastAPI, user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN)
    make_user(database, "ada", Role.EXPERIMENTER)
    client = TestClient(app)
    for _ in range(login_throttle.MAX_FAILURES_PER_ACCOUNT):
        assert _login_form(client, "ada", "wrong password")[0] == 401
    assert _login_form(client, "ada", PASSWORD)[0] == 429
    page = admin.get("/admin/users/ada")
    assert "Locked out" in page.text and 'action="/admin/users/ada/unlock"' in page.text
    assert "locked until" in admin.get("/admin/users").text
    assert admin.post("/admin/users/ada/unlock").status_code == 200
    assert "Locked out" not in admin.get("/admin/users/ada").text
    assert _login_form(client, "ada", PASSWORD)[0] == 303
    [event] = _audit(database, "user.unlocked")
    assert event.actor_kind == "user" and event.details == {"cleared": 5}


def test_users_are_named_exactly_in_urls(user_client: UserClientFactory) -> None:
    admin = user_client(Role.ADMIN)
    user_client(Role.ANALYST, "ada")
    assert admin.get("/admin/users/ADA").status_code == 200
    for lookalike in ("ada%0A", "ada%20", "%20ada", "nobody", "a" * 65):
        assert admin.get(f"/admin/users/{lookalike}").status_code == 404, lookalike
        assert admin.post(f"/admin/users/{lookalike}/disable").status_code == 404, lookalike


def test_account_changes_are_for_admins_only(user_client: UserClientFactory) -> None:
    user_client(Role.ADMIN, "root")
    experimenter = user_client(Role.EXPERIMENTER)
    assert experimenter.get("/admin/users/root").status_code == 403
    for path, data in (
        ("disable", {}),
        ("enable", {}),
        ("role", {"role": "analyst"}),
        ("password", {"password": NEW_PASSWORD, "confirm": NEW_PASSWORD}),
        ("unlock", {}),
    ):
        assert experimenter.post(f"/admin/users/root/{path}", data=data).status_code == 403
    token = experimenter.headers.pop("X-CSRF-Token")
    assert experimenter.post("/account/password", data={}).status_code == 403  # no CSRF token
    experimenter.headers["X-CSRF-Token"] = token


def test_everyone_changes_their_own_password(
    app: FastAPI, user_client: UserClientFactory, database: Database
) -> None:
    ada = user_client(Role.ANALYST, "ada")
    elsewhere = TestClient(app)
    sign_in_api(elsewhere, "ada")
    page = ada.get("/account")
    assert page.status_code == 200 and 'action="/account/password"' in page.text
    assert 'href="/account"' in page.text  # linked from every page's header
    form = {"current_password": PASSWORD, "new_password": NEW_PASSWORD, "confirm": NEW_PASSWORD}
    wrong = ada.post("/account/password", data={**form, "current_password": "not my password"})
    assert wrong.status_code == 403 and "current password is not right" in wrong.text
    mismatch = ada.post("/account/password", data={**form, "confirm": "another new one"})
    assert mismatch.status_code == 422
    assert elsewhere.get("/").status_code == 200
    done = ada.post("/account/password", data=form, follow_redirects=False)
    assert done.status_code == 303 and done.headers["location"] == "/account"
    assert ada.get("/").status_code == 200  # this browser stays signed in
    assert elsewhere.get("/api/v1/studies").status_code == 401  # the other one does not
    assert _login_form(TestClient(app), "ada", NEW_PASSWORD)[0] == 303
    [failed] = _audit(database, "user.password_change_failed")
    assert failed.details["reason"] == "wrong password"
    assert [e.subject for e in _audit(database, "user.password_changed")] == ["ada"]


def test_wrong_current_passwords_count_towards_the_lockout(user_client: UserClientFactory) -> None:
    """Otherwise a stolen session could guess the account's password without limit."""
    ada = user_client(Role.ANALYST, "ada")
    form = {"current_password": "guess", "new_password": NEW_PASSWORD, "confirm": NEW_PASSWORD}
    statuses = [
        ada.post("/account/password", data=form).status_code
        for _ in range(login_throttle.MAX_FAILURES_PER_ACCOUNT + 1)
    ]
    assert statuses == [403] * login_throttle.MAX_FAILURES_PER_ACCOUNT + [429]


def test_failed_sign_ins_are_audited_with_their_reason_and_never_the_password(
    app: FastAPI, user_client: UserClientFactory, database: Database
) -> None:
    admin = user_client(Role.ADMIN)
    make_user(database, "ada", Role.ANALYST)
    make_user(database, "gone", Role.ANALYST)
    admin.post("/admin/users/gone/disable")
    client = TestClient(app)
    guesses = [f"guess number {n}" for n in range(login_throttle.MAX_FAILURES_PER_ACCOUNT)]
    for guess in guesses:
        _login_form(client, "ada", guess)
    _login_form(client, "ada", "one guess too many")
    _login_form(client, "nobody", "who am i really")
    _login_form(client, "gone", PASSWORD)
    events = _audit(database, "user.sign_in_failed")
    assert [(e.subject, e.details["reason"]) for e in events] == [
        *[("ada", "wrong password")] * len(guesses),
        ("ada", "locked"),
        ("nobody", "unknown user"),
        ("gone", "disabled"),
    ]
    assert events[0].details["client_address"] == "testclient"
    assert events[len(guesses)].details["by"] == "account"
    with database.read_session() as db:
        everything = json.dumps(
            [[e.actor, e.subject, e.details] for e in db.scalars(select(AuditEvent))]
        )
    for password in (*guesses, "one guess too many", "who am i really", PASSWORD):
        assert password not in everything
    page = admin.get("/admin/audit?action=user.sign_in_failed")
    for reason in ("wrong password", "locked", "unknown user", "disabled"):
        assert reason in page.text


def test_disabling_ends_the_accounts_open_event_streams(
    user_client: UserClientFactory, study_name: str
) -> None:
    """An open stream is part of the sign-in too: it ends when the account is disabled (the
    EventSource's reconnection is then refused), instead of telling it about changes for hours."""
    admin = user_client(Role.ADMIN)
    ada = user_client(Role.EXPERIMENTER, "ada")
    opened, ended = threading.Event(), threading.Event()
    lines: list[str] = []

    def listen() -> None:
        with ada.stream("GET", f"/studies/{study_name}/events") as stream:
            for line in stream.iter_lines():
                lines.append(line)
                opened.set()
        ended.set()

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    assert opened.wait(timeout=30)  # subscribed: the stream has said how to reconnect
    assert admin.post("/admin/users/ada/disable").status_code == 200
    assert ended.wait(timeout=30), "the stream outlived the account's sign-in"
    listener.join()
    assert lines[0] == "retry: 3000"
    refused = ada.get(f"/studies/{study_name}/events", follow_redirects=False)
    assert refused.status_code == 303  # to the sign-in page: the EventSource gives up


def test_an_admin_who_demotes_themselves_lands_on_a_page_they_may_see(
    user_client: UserClientFactory,
) -> None:
    root = user_client(Role.ADMIN, "root")
    user_client(Role.ADMIN, "spare")
    done = root.post("/admin/users/root/role", data={"role": "analyst"}, follow_redirects=False)
    assert done.status_code == 303 and done.headers["location"] == "/"
    landed = root.get("/")
    assert landed.status_code == 200 and "root is now analyst." in landed.text
    assert root.get("/admin/users").status_code == 403
