"""``trustlab user list|disable|enable|set-password|set-role|unlock`` (and create's prompt)."""

from __future__ import annotations

import json
from datetime import timedelta

import pytest
from sqlalchemy import select

from app.cli import accounts as accounts_cli
from app.db import Database
from app.services.staff import login_throttle, users
from app.tables import AuditEvent, LoginSession, Role
from tests.app.test_cli import run
from tests.conftest import PASSWORD, make_user

NEW_PASSWORD = "a brand new passphrase"


def _sign_in(database: Database, username: str, password: str = PASSWORD) -> bool:
    with database.writing() as db:
        return users.authenticate(db, username=username, password=password) is not None


def _open_login(database: Database, username: str) -> None:
    with database.writing() as db:
        users.sign_in(db, user=users.named(db, username), lifetime=timedelta(hours=1))


def _live_sessions(database: Database) -> int:
    with database.read_session() as db:
        return len(db.scalars(select(LoginSession).where(LoginSession.revoked_at.is_(None))).all())


def _cli_actions(database: Database) -> list[str]:
    with database.read_session() as db:
        return list(
            db.scalars(
                select(AuditEvent.action)
                .where(AuditEvent.actor_kind == "cli")
                .order_by(AuditEvent.id)
            )
        )


def test_list_disable_enable(database_url: str, database: Database) -> None:
    make_user(database, "root", Role.ADMIN)
    make_user(database, "ada", Role.EXPERIMENTER)
    _open_login(database, "ada")
    code, out, _ = run(database_url, "user", "list")
    assert code == 0
    assert [line.split()[:3] for line in out.splitlines()] == [
        ["ada", "experimenter", "active"],
        ["root", "admin", "active"],
    ]
    assert run(database_url, "user", "disable", "ADA")[:2] == (
        0,
        "disabled 'ada' (1 login session ended)\n",
    )
    assert _live_sessions(database) == 0
    assert not _sign_in(database, "ada")
    code, out, _ = run(database_url, "user", "list", "--json")
    listed = {row["username"]: row for row in json.loads(out)["users"]}
    assert listed["ada"]["active"] is False and listed["root"]["active"] is True
    assert run(database_url, "user", "disable", "ada")[::2] == (
        1,
        "error: 'ada' is already disabled\n",
    )
    assert run(database_url, "user", "enable", "ada")[:2] == (0, "enabled 'ada'\n")
    assert _sign_in(database, "ada")
    assert run(database_url, "user", "disable", "ada\n")[::2] == (
        1,
        "error: no user named 'ada\\n'\n",
    )
    assert _cli_actions(database) == ["user.disabled", "user.enabled"]


def test_the_last_active_admin_stays(database_url: str, database: Database) -> None:
    make_user(database, "root", Role.ADMIN)
    refusal = (
        "error: 'root' is the last active admin and cannot be {}: "
        "make another account admin first\n"
    )
    assert run(database_url, "user", "disable", "root")[::2] == (1, refusal.format("disabled"))
    assert run(database_url, "user", "set-role", "root", "analyst")[::2] == (
        1,
        refusal.format("demoted"),
    )
    make_user(database, "ada", Role.EXPERIMENTER)
    assert run(database_url, "user", "set-role", "ada", "admin")[:2] == (
        0,
        "'ada' is now admin (was experimenter)\n",
    )
    assert run(database_url, "user", "set-role", "root", "analyst")[0] == 0
    code, _, err = run(database_url, "user", "set-role", "ada", "boss")
    assert code == 2 and "boss" in err


def test_set_password_reads_stdin_or_a_hidden_prompt_never_an_argument(
    database_url: str, database: Database, monkeypatch: pytest.MonkeyPatch
) -> None:
    make_user(database, "ada", Role.ANALYST)
    _open_login(database, "ada")
    code, _, err = run(database_url, "user", "set-password", "ada")
    assert code == 2 and "--password-stdin" in err  # no terminal, no stdin flag: nothing read
    code, _, err = run(database_url, "user", "set-password", "ada", NEW_PASSWORD)
    assert code == 2  # a password given as an argument is refused
    code, out, _ = run(
        database_url, "user", "set-password", "ada", "--password-stdin", stdin=NEW_PASSWORD + "\n"
    )
    assert (code, out) == (0, "set a new password for 'ada' (1 login session ended)\n")
    assert _live_sessions(database) == 0
    assert _sign_in(database, "ada", NEW_PASSWORD) and not _sign_in(database, "ada")
    code, _, err = run(
        database_url, "user", "set-password", "ada", "--password-stdin", stdin="short\n"
    )
    assert (code, err) == (2, "error: a password needs at least 10 characters\n")
    monkeypatch.setattr(accounts_cli, "on_terminal", lambda: True)
    code, out, _ = run(
        database_url, "user", "set-password", "ada", stdin=f"{PASSWORD}\n{PASSWORD}\n"
    )
    assert code == 0 and PASSWORD not in out  # the prompt does not echo
    assert _sign_in(database, "ada")
    code, out, _ = run(
        database_url,
        "user",
        "create",
        "--username",
        "bob",
        "--role",
        "analyst",
        stdin=f"{PASSWORD}\n{PASSWORD}\n",
    )
    assert code == 0 and "created analyst 'bob'" in out
    assert _cli_actions(database) == ["user.password_set", "user.password_set", "user.created"]


def test_unlock_lets_a_locked_out_admin_sign_in_again(
    database_url: str, database: Database
) -> None:
    make_user(database, "root", Role.ADMIN)
    for _ in range(login_throttle.MAX_FAILURES_PER_ACCOUNT):
        assert not _sign_in(database, "root", "wrong password")
    assert "locked until" in run(database_url, "user", "list")[1]
    assert run(database_url, "user", "unlock", "root")[:2] == (
        0,
        "unlocked 'root': 5 recent failed sign-ins no longer count\n",
    )
    assert _sign_in(database, "root")
    assert run(database_url, "user", "unlock", "root")[:2] == (
        0,
        "'root' had no recent failed sign-ins; nothing to unlock\n",
    )
    assert run(database_url, "user", "unlock", "nobody")[::2] == (
        1,
        "error: no user named 'nobody'\n",
    )
    assert _cli_actions(database) == ["user.unlocked", "user.unlocked"]
