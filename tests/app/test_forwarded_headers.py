"""X-Forwarded-For and X-Forwarded-Proto count only from configured proxies
(TRUSTLAB_TRUSTED_PROXIES, default none): otherwise any local process could choose the client
address the sign-in throttle counts."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from sqlalchemy import select

from app.db import Database
from app.main import create_app
from app.settings import Settings
from app.tables import LoginAttempt, Role
from app.tablet import TABLET_COOKIE
from tests.conftest import PASSWORD, Lab, UserClientFactory, make_user, sqlite_only
from tests.servers import TrustlabServe

SPOOFED = "203.0.113.9"


def _recorded_addresses(database: Database) -> list[str]:
    with database.read_session() as db:
        return list(db.scalars(select(LoginAttempt.client_address).order_by(LoginAttempt.id)))


def test_trusted_proxies_are_addresses_or_networks(monkeypatch: pytest.MonkeyPatch) -> None:
    assert Settings(_env_file=None).trusted_proxies == ()  # type: ignore[call-arg]
    monkeypatch.setenv("TRUSTLAB_TRUSTED_PROXIES", " 10.1.2.3/24, ::1,192.0.2.1 ")
    assert Settings(_env_file=None).trusted_proxies == (  # type: ignore[call-arg]
        "10.1.2.0/24",
        "::1",
        "192.0.2.1",
    )
    monkeypatch.setenv("TRUSTLAB_TRUSTED_PROXIES", "127.0.0.1,proxy.example")
    with pytest.raises(ValidationError, match=r"'proxy\.example' is not an IP address or network"):
        Settings(_env_file=None)  # type: ignore[call-arg]


@pytest.mark.parametrize(
    ("trusted", "forwarded_for", "recorded"),
    [
        ((), SPOOFED, "127.0.0.1"),
        (("127.0.0.1",), SPOOFED, SPOOFED),
        # Each proxy appends the address it saw: the nearest untrusted one is the client.
        (("127.0.0.1", "10.0.0.0/8"), f"198.51.100.1, {SPOOFED}, 10.2.3.4", SPOOFED),
    ],
)
@sqlite_only("which address counts is decided from the headers; storing it is tested elsewhere")
def test_the_throttle_counts_the_forwarded_address_only_from_trusted_proxies(
    settings: Settings,
    database: Database,
    trusted: tuple[str, ...],
    forwarded_for: str,
    recorded: str,
) -> None:
    app = create_app(settings.model_copy(update={"trusted_proxies": trusted}))
    with TestClient(app, client=("127.0.0.1", 40000)) as client:
        response = client.post(
            "/api/v1/session",
            json={"username": "nobody", "password": "wrong password"},
            headers={"X-Forwarded-For": forwarded_for},
        )
    assert response.status_code == 401
    assert _recorded_addresses(database) == [recorded]


@pytest.mark.parametrize(("trusted", "secure"), [((), False), (("127.0.0.1",), True)])
@sqlite_only("headers, not storage")
def test_the_forwarded_scheme_counts_only_from_trusted_proxies(
    settings: Settings, database: Database, trusted: tuple[str, ...], secure: bool
) -> None:
    """X-Forwarded-Proto decides the cookie's Secure flag, so it is trusted no more widely."""
    make_user(database, "ada", Role.ANALYST)
    app = create_app(settings.model_copy(update={"trusted_proxies": trusted}))
    with TestClient(app, client=("127.0.0.1", 40000)) as client:
        response = client.post(
            "/api/v1/session",
            json={"username": "ada", "password": PASSWORD},
            headers={"X-Forwarded-Proto": "https"},
        )
    assert response.status_code == 200
    assert ("secure" in response.headers["set-cookie"].lower()) is secure


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # headers, not storage
@pytest.mark.parametrize(("trusted", "secure"), [((), False), (("127.0.0.1",), True)])
def test_the_tablet_cookie_is_secure_by_the_same_rule(
    settings: Settings, lab: Lab, trusted: tuple[str, ...], secure: bool
) -> None:
    """A participant's tablet cookie is a bearer credential like the login cookie (issue 35)."""
    code = lab.enrol_and_assign()
    link = lab.experimenter.post(f"/api/v1/studies/{lab.study}/participants/{code}/link")
    app = create_app(settings.model_copy(update={"trusted_proxies": trusted}))
    with TestClient(app, client=("127.0.0.1", 40000)) as tablet:
        opened = tablet.get(
            f"/t/{link.json()['token']}",
            headers={"X-Forwarded-Proto": "https"},
            follow_redirects=False,
        )
    assert opened.status_code == 303
    cookie = opened.headers["set-cookie"]
    assert cookie.startswith(f"{TABLET_COOKIE}=")
    assert ("secure" in cookie.lower()) is secure


@pytest.mark.parametrize("engine_name", ["sqlite"], indirect=True)  # headers, not storage
@pytest.mark.parametrize(("trusted", "secure"), [((), False), (("127.0.0.1",), True)])
def test_the_sign_in_and_notice_cookies_follow_the_same_rule(
    settings: Settings, user_client: UserClientFactory, trusted: tuple[str, ...], secure: bool
) -> None:
    admin = user_client(Role.ADMIN)  # signed in over plain HTTP, so its cookies travel here too
    app = create_app(settings.model_copy(update={"trusted_proxies": trusted}))
    https = {"X-Forwarded-Proto": "https"}
    with TestClient(app, client=("127.0.0.1", 40000), headers=https) as client:
        login = client.get("/login")
        client.cookies, client.headers["X-CSRF-Token"] = (
            admin.cookies,
            admin.headers["X-CSRF-Token"],
        )
        noticed = client.post("/stations", data={"name": "lab-9"}, follow_redirects=False)
    assert ("secure" in login.headers["set-cookie"].lower()) is secure
    assert noticed.status_code == 303
    assert ("secure" in noticed.headers["set-cookie"].lower()) is secure


@contextmanager
def _serving(url: str, var_dir: Path, env: dict[str, str]) -> Iterator[str]:
    server = TrustlabServe(url, var_dir, extra_env=env)
    server.start()
    try:
        yield server.url
    finally:
        server.stop()


@pytest.mark.parametrize(("trusted", "recorded"), [("", "127.0.0.1"), ("127.0.0.1", SPOOFED)])
def test_trustlab_serve_trusts_forwarded_headers_only_from_configured_proxies(
    sqlite_template: Path, tmp_path: Path, trusted: str, recorded: str
) -> None:
    """Engine-independent, so on SQLite only: the server's own proxy handling, not the app's."""
    path = tmp_path / "serve.sqlite3"
    shutil.copyfile(sqlite_template, path)
    url = f"sqlite:///{path}"
    env = {"TRUSTLAB_TRUSTED_PROXIES": trusted} if trusted else {}
    with _serving(url, tmp_path / "var", env) as base:
        response = httpx.post(
            f"{base}/api/v1/session",
            json={"username": "nobody", "password": "wrong password"},
            headers={"X-Forwarded-For": SPOOFED},
        )
    assert response.status_code == 401
    database = Database(url)
    try:
        assert _recorded_addresses(database) == [recorded]
    finally:
        database.dispose()
