"""The login throttle under real concurrency: no more than ``limit`` wrong passwords are ever
checked, right ones are never refused for being many at once, and a restart locks nobody out."""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable
from datetime import timedelta

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import select

from app.db import Database
from app.errors import TooManyAttempts
from app.main import create_app
from app.services.staff import login_throttle, users
from app.settings import Settings
from app.tables import AttemptOutcome, AuditEvent, LoginAttempt, Role, utcnow
from tests.conftest import PASSWORD, make_user

PARALLEL = 30


def _count_verifications(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Wrap the password verifier: each call appends the password it was given."""
    checked: list[str] = []
    guard = threading.Lock()
    verify = users.verify_password

    def counting(password_hash: str | None, password: str) -> bool:
        with guard:
            checked.append(password)
        return verify(password_hash, password)

    monkeypatch.setattr(users, "verify_password", counting)
    return checked


def _all_at_once(database: Database, attempts: list[Callable[[], str]]) -> Counter[str]:
    """Run every attempt in its own thread, released together by a barrier; how they ended."""
    barrier = threading.Barrier(len(attempts))
    outcomes: Counter[str] = Counter()
    guard = threading.Lock()

    def run(attempt: Callable[[], str]) -> None:
        barrier.wait(timeout=60)  # a guard against a hang, not a timing assumption
        try:
            outcome = attempt()
        except TooManyAttempts:
            outcome = "throttled"
        with guard:
            outcomes[outcome] += 1

    threads = [threading.Thread(target=run, args=(attempt,)) for attempt in attempts]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return outcomes


def _sign_in(database: Database, username: str, password: str, address: str) -> str:
    """One sign-in as the pages do it: count, check with no transaction open, decide."""
    with database.writing() as counting:
        check = users.begin_password_check(counting, username=username, client_address=address)
    with database.writing() as db:
        result = users.finish_sign_in(
            db, check=check, password=password, lifetime=timedelta(hours=1)
        )
    return result.value if isinstance(result, users.Refusal) else "signed in"


def test_parallel_wrong_passwords_check_exactly_the_account_limit(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    make_user(database, "target", Role.ADMIN)
    checked = _count_verifications(monkeypatch)
    outcomes = _all_at_once(
        database,
        [
            lambda n=n: _sign_in(database, "target", f"guess {n}", f"10.0.{n}.1")  # type: ignore[misc]
            for n in range(PARALLEL)
        ],
    )
    limit = login_throttle.MAX_FAILURES_PER_ACCOUNT
    assert len(checked) == limit
    assert outcomes == {"wrong password": limit, "throttled": PARALLEL - limit}
    with database.read_session() as db:
        assert len(db.scalars(select(LoginAttempt)).all()) == limit
        reasons = Counter(
            event.details["reason"]
            for event in db.scalars(
                select(AuditEvent).where(AuditEvent.action == users.SIGN_IN_FAILED)
            )
        )
    assert reasons == {"wrong password": limit, "locked": PARALLEL - limit}


def test_parallel_guesses_from_one_address_check_exactly_the_address_limit(
    database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Unknown usernames have no row to lock: the address's own lock keeps its count exact."""
    checked = _count_verifications(monkeypatch)
    outcomes = _all_at_once(
        database,
        [
            lambda n=n: _sign_in(database, f"nobody{n}", PASSWORD, "192.0.2.7")  # type: ignore[misc]
            for n in range(PARALLEL)
        ],
    )
    limit = login_throttle.MAX_FAILURES_PER_ADDRESS
    assert len(checked) == limit
    assert outcomes == {"unknown user": limit, "throttled": PARALLEL - limit}


def test_parallel_right_passwords_all_sign_in(
    app: FastAPI, database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Twenty tablets signing in as one account at once (issue 35, item 12: 15 of them got 429).
    The checks are held until ``limit`` of them run at once, so every round of them overlaps:
    then the rest wait for a free place instead of being refused."""
    make_user(database, "lab", Role.EXPERIMENTER)
    limit = login_throttle.MAX_FAILURES_PER_ACCOUNT
    together = threading.Barrier(limit)
    verify = users.verify_password

    def overlapping(password_hash: str | None, password: str) -> bool:
        together.wait(timeout=60)  # a guard against a hang, not a timing assumption
        return verify(password_hash, password)

    monkeypatch.setattr(users, "verify_password", overlapping)
    parallel = 4 * limit
    with TestClient(app) as client:

        def sign_in() -> str:
            body = {"username": "lab", "password": PASSWORD}
            return str(client.post("/api/v1/session", json=body).status_code)

        outcomes = _all_at_once(database, [sign_in] * parallel)
    assert outcomes == {"200": parallel}
    with database.read_session() as db:
        assert set(db.scalars(select(LoginAttempt.outcome))) == {AttemptOutcome.SUCCEEDED}
        assert login_throttle.locked_until(db, username="lab") is None


def test_a_restart_abandons_the_checks_it_interrupted(
    database: Database, settings: Settings
) -> None:
    """A server that stopped during sign-ins (here: attempts counted, their checks never
    finished) leaves nobody locked out nor waiting once it starts again."""
    make_user(database, "ada", Role.EXPERIMENTER)
    for _ in range(login_throttle.MAX_FAILURES_PER_ACCOUNT):
        with database.writing() as counting:
            users.begin_password_check(counting, username="ada", client_address="10.0.0.1")
    with TestClient(create_app(settings)) as restarted:
        with database.read_session() as db:
            outcomes = set(db.scalars(select(LoginAttempt.outcome)))
        assert outcomes == {AttemptOutcome.ABANDONED}
        wrong = restarted.post("/api/v1/session", json={"username": "ada", "password": "nope"})
        assert wrong.status_code == 401
        right = restarted.post("/api/v1/session", json={"username": "ada", "password": PASSWORD})
        assert right.status_code == 200
    with database.read_session() as db:
        assert login_throttle.locked_until(db, username="ada") is None


def test_a_right_password_frees_its_reserved_attempt(database: Database) -> None:
    make_user(database, "ada", Role.EXPERIMENTER)
    for _ in range(login_throttle.MAX_FAILURES_PER_ACCOUNT - 1):
        assert _sign_in(database, "ada", "wrong password", "") == "wrong password"
    for _ in range(3):
        assert _sign_in(database, "ada", PASSWORD, "") == "signed in"
    assert _sign_in(database, "ada", "wrong password", "") == "wrong password"
    with pytest.raises(TooManyAttempts, match="from this account"):
        _sign_in(database, "ada", PASSWORD, "")


def test_the_lockout_ends_with_the_window(database: Database) -> None:
    """The throttle's clock is a parameter: the window's end is checked without waiting."""
    make_user(database, "ada", Role.EXPERIMENTER)
    for _ in range(login_throttle.MAX_FAILURES_PER_ACCOUNT):
        _sign_in(database, "ada", "wrong password", "")
    now = utcnow()
    with database.writing() as db:
        until = login_throttle.locked_until(db, username="ada", now=now)
        assert until is not None and now < until <= now + login_throttle.WINDOW
        locked = login_throttle.reserve(db, username="ada", client_address="", now=now)
        assert isinstance(locked, login_throttle.Locked) and locked.by == "account"
        assert locked.message(until - timedelta(minutes=3, seconds=30)) == (
            "too many failed sign-ins from this account; try again in 4 minutes"
        )
        assert login_throttle.locked_until(db, username="ada", now=until) is None
        assert isinstance(
            login_throttle.reserve(db, username="ada", client_address="", now=until), int
        )
        db.rollback()
