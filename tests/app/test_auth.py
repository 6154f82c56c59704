"""Sign-in, sign-out, cookies, CSRF and roles."""

from __future__ import annotations

import threading
from collections.abc import Callable
from datetime import timedelta

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import event, select, update

from app.db import Database
from app.services.audit import Actor
from app.services.staff import accounts, users
from app.tables import AttemptOutcome, AuditEvent, LoginAttempt, LoginSession, Role, utcnow
from tests.conftest import CSRF_INPUT, PASSWORD, UserClientFactory, make_user, sign_in, sqlite_only


def _login_form_token(client: TestClient) -> str:
    match = CSRF_INPUT.search(client.get("/login").text)
    assert match
    return match.group(1)


@sqlite_only("no session cookie: refused before any query")
def test_pages_and_api_require_sign_in(client: TestClient) -> None:
    page = client.get("/", follow_redirects=False)
    assert page.status_code == 303
    assert page.headers["location"] == "/login?next=/"
    api = client.get("/api/v1/studies")
    assert api.status_code == 401
    assert api.json() == {"detail": "sign in first"}


def test_sign_in_sets_a_protected_cookie(client: TestClient, database: Database) -> None:
    make_user(database, "ada", Role.EXPERIMENTER)
    response = client.post(
        "/login",
        data={"username": "ADA", "password": PASSWORD, "csrf_token": _login_form_token(client)},
        follow_redirects=False,
    )
    assert response.status_code == 303
    cookie = response.headers["set-cookie"].lower()
    assert "tl_session=" in cookie
    assert "httponly" in cookie
    assert "samesite=lax" in cookie
    assert "secure" not in cookie  # plain http in tests; https requests get Secure
    assert client.get("/").status_code == 200
    with database.read_session() as db:
        login = db.scalars(select(LoginSession)).one()
        assert len(login.token_hash) == 64 and login.token_hash not in cookie


def test_cookie_is_secure_over_https(app: object, database: Database) -> None:
    make_user(database, "ada", Role.EXPERIMENTER)
    with TestClient(app, base_url="https://testserver") as secure_client:  # type: ignore[arg-type]
        response = secure_client.post(
            "/login",
            data={
                "username": "ada",
                "password": PASSWORD,
                "csrf_token": _login_form_token(secure_client),
            },
            follow_redirects=False,
        )
    assert "secure" in response.headers["set-cookie"].lower()


def test_wrong_password_and_unknown_user_look_the_same(
    client: TestClient, database: Database
) -> None:
    make_user(database, "ada", Role.EXPERIMENTER)
    answers = []
    for username, password in [("ada", "wrong password!"), ("nobody", PASSWORD)]:
        response = client.post(
            "/login",
            data={
                "username": username,
                "password": password,
                "csrf_token": _login_form_token(client),
            },
        )
        assert response.status_code == 401
        answers.append(response.text.replace(username, "NAME"))
    assert "Invalid username or password." in answers[0]
    assert answers[0].split("<main")[1].count("Invalid") == answers[1].split("<main")[1].count(
        "Invalid"
    )
    assert "tl_session" not in client.cookies


def test_sign_in_without_csrf_token_is_refused(client: TestClient, database: Database) -> None:
    make_user(database, "ada", Role.EXPERIMENTER)
    client.get("/login")
    response = client.post("/login", data={"username": "ada", "password": PASSWORD})
    assert response.status_code == 403
    forged = client.post(
        "/login", data={"username": "ada", "password": PASSWORD, "csrf_token": "abc.def"}
    )
    assert forged.status_code == 403
    assert "tl_session" not in client.cookies


def test_next_parameter_cannot_redirect_off_site(client: TestClient, database: Database) -> None:
    make_user(database, "ada", Role.EXPERIMENTER)
    for target, expected in [
        ("/studies/x", "/studies/x"),
        ("//evil.example", "/"),
        ("https://evil.example", "/"),
    ]:
        client.cookies.clear()
        response = client.post(
            "/login",
            data={
                "username": "ada",
                "password": PASSWORD,
                "next": target,
                "csrf_token": _login_form_token(client),
            },
            follow_redirects=False,
        )
        assert response.headers["location"] == expected


def test_state_changes_need_the_csrf_token(user_client: UserClientFactory, study_name: str) -> None:
    client = user_client(Role.EXPERIMENTER)
    token = client.headers.pop("X-CSRF-Token")
    refused = client.post(f"/api/v1/studies/{study_name}/participants", json={})
    assert refused.status_code == 403
    assert "CSRF" in refused.json()["detail"]
    form = client.post(f"/studies/{study_name}/participants", data={"code": "X1"})
    assert form.status_code == 403
    accepted = client.post(
        f"/studies/{study_name}/participants", data={"code": "X1", "csrf_token": token}
    )
    assert accepted.status_code == 200  # redirected to the study page
    logout = client.post("/logout", follow_redirects=False)
    assert logout.status_code == 403


def test_sign_out_revokes_the_session(user_client: UserClientFactory, database: Database) -> None:
    client = user_client(Role.ANALYST)
    cookie = client.cookies.get("tl_session")
    response = client.post("/logout", follow_redirects=False)
    assert response.status_code == 303
    client.cookies.set("tl_session", cookie or "")
    assert client.get("/api/v1/studies").status_code == 401
    with database.read_session() as db:
        actions = db.scalars(select(AuditEvent.action)).all()
    assert {"user.signed_in", "user.signed_out"} <= set(actions)


def test_expired_and_idle_sessions_end(user_client: UserClientFactory, database: Database) -> None:
    client = user_client(Role.ANALYST)
    assert client.get("/api/v1/studies").status_code == 200
    with database.writing() as db:
        db.execute(update(LoginSession).values(expires_at=utcnow() - timedelta(seconds=1)))
        db.commit()
    assert client.get("/api/v1/studies").status_code == 401
    other = user_client(Role.ANALYST)
    with database.writing() as db:
        db.execute(
            update(LoginSession)
            .where(LoginSession.revoked_at.is_(None), LoginSession.expires_at > utcnow())
            .values(last_seen_at=utcnow() - timedelta(hours=3))
        )
        db.commit()
    assert other.get("/api/v1/studies").status_code == 401


def test_roles(user_client: UserClientFactory, study_name: str) -> None:
    analyst = user_client(Role.ANALYST)
    experimenter = user_client(Role.EXPERIMENTER)
    admin = user_client(Role.ADMIN)
    enrol = f"/api/v1/studies/{study_name}/participants"
    assert analyst.get(enrol).status_code == 200
    denied = analyst.post(enrol, json={})
    assert denied.status_code == 403
    assert denied.json()["detail"] == "this needs the admin or experimenter role; you are analyst"
    assert experimenter.post(enrol, json={}).status_code == 201
    assert admin.post(enrol, json={}).status_code == 201
    assert experimenter.get("/admin/users").status_code == 403
    assert (
        analyst.post("/api/v1/studies", json={"name": "x", "protocol_toml": ""}).status_code == 403
    )
    assert admin.get("/admin/users").status_code == 200


def test_signed_in_user_sees_login_form_fields_only_once(
    client: TestClient, database: Database
) -> None:
    make_user(database, "ada", Role.ADMIN)
    sign_in(client, "ada")
    page = client.get("/")
    assert page.status_code == 200
    assert "ada" in page.text and "Sign out" in page.text


def test_sign_in_checks_the_password_with_no_transaction_open(
    app: FastAPI, client: TestClient, database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Argon2id is slow by design: no transaction — on SQLite, not the single write lock — waits
    for it, through the API or the sign-in page, right password or wrong."""
    make_user(database, "hasher", Role.ANALYST)
    engine = app.state.database.engine
    open_transactions: set[int] = set()
    seen: list[bool] = []
    verify = users.verify_password

    def opened(conn: object) -> None:
        if threading.current_thread().name != "trustlab-activity":
            open_transactions.add(id(conn))

    def closed(conn: object) -> None:
        open_transactions.discard(id(conn))

    def checked(password_hash: str | None, password: str) -> bool:
        seen.append(bool(open_transactions))
        return verify(password_hash, password)

    monkeypatch.setattr(users, "verify_password", checked)
    listeners = [("begin", opened), ("commit", closed), ("rollback", closed)]
    for name, listener in listeners:
        event.listen(engine, name, listener)
    try:
        for password in (PASSWORD, "wrong password"):
            client.post("/api/v1/session", json={"username": "hasher", "password": password})
        sign_in(TestClient(app), "hasher")
    finally:
        for name, listener in listeners:
            event.remove(engine, name, listener)
    assert seen == [False, False, False]


def test_sign_in_refuses_an_account_disabled_after_it_was_read(database: Database) -> None:
    make_user(database, "leaving", Role.EXPERIMENTER)
    with database.writing() as db:
        check = users.begin_password_check(db, username="leaving", client_address="10.0.0.9")
    with database.writing() as other:
        accounts.disable_user(other, username="leaving", actor=Actor.system("tests"))
    with database.writing() as db:
        refused = users.finish_sign_in(
            db, check=check, password=PASSWORD, lifetime=timedelta(hours=1)
        )
    assert refused is users.Refusal.DISABLED
    with database.read_session() as db:
        assert db.scalars(select(LoginAttempt.outcome)).all() == [AttemptOutcome.FAILED]


def test_new_passwords_are_hashed_with_no_transaction_open(
    app: FastAPI, user_client: UserClientFactory, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Hashing is as slow as checking: creating an account, an admin's reset and one's own change
    hash the new password before their write transaction begins."""
    admin = user_client(Role.ADMIN)
    make_user(app.state.database, "ada", Role.ANALYST)
    engine = app.state.database.engine
    open_transactions: set[int] = set()
    seen: list[bool] = []

    def opened(conn: object) -> None:
        if threading.current_thread().name != "trustlab-activity":
            open_transactions.add(id(conn))

    def closed(conn: object) -> None:
        open_transactions.discard(id(conn))

    def hashing(hash_password: Callable[[str], str]) -> Callable[[str], str]:
        def hashed(password: str) -> str:
            seen.append(bool(open_transactions))
            return hash_password(password)

        return hashed

    monkeypatch.setattr(users, "hash_password", hashing(users.hash_password))
    monkeypatch.setattr(accounts, "hash_password", hashing(accounts.hash_password))
    listeners = [("begin", opened), ("commit", closed), ("rollback", closed)]
    for name, listener in listeners:
        event.listen(engine, name, listener)
    renewed = "a brand new passphrase"
    try:
        created = admin.post(
            "/admin/users", data={"username": "bob", "role": "analyst", "password": renewed}
        )
        reset = admin.post(
            "/admin/users/ada/password", data={"password": renewed, "confirm": renewed}
        )
        own = admin.post(
            "/account/password",
            data={"current_password": PASSWORD, "new_password": renewed, "confirm": renewed},
        )
    finally:
        for name, listener in listeners:
            event.remove(engine, name, listener)
    assert [created.status_code, reset.status_code, own.status_code] == [200, 200, 200]
    assert seen == [False, False, False]
