"""The account lifecycle in the service layer: disable, enable, passwords, roles, unlock, and the
active admin that always remains, also when two changes race."""

from __future__ import annotations

import threading
from collections.abc import Callable
from datetime import timedelta

import pytest
from sqlalchemy import select

from app.db import Database
from app.errors import Conflict, NotFound, PermissionDenied, TooManyAttempts
from app.services.audit import Actor
from app.services.staff import accounts, login_throttle, users
from app.tables import AuditEvent, LoginAttempt, LoginSession, Role, User
from tests.conftest import PASSWORD, make_user

CLI = Actor.command_line()
NEW_PASSWORD = "a brand new passphrase"


def _sign_in(database: Database, username: str, password: str = PASSWORD) -> object:
    with database.writing() as counting:
        check = users.begin_password_check(counting, username=username)
    with database.writing() as db:
        return users.finish_sign_in(db, check=check, password=password, lifetime=timedelta(hours=1))


def _live_sessions(database: Database, username: str) -> list[int]:
    with database.read_session() as db:
        return list(
            db.scalars(
                select(LoginSession.id)
                .join(User)
                .where(User.username == username, LoginSession.revoked_at.is_(None))
                .order_by(LoginSession.id)
            )
        )


def _actions(database: Database, subject: str) -> list[str]:
    with database.read_session() as db:
        return list(
            db.scalars(
                select(AuditEvent.action)
                .where(AuditEvent.subject == subject)
                .order_by(AuditEvent.id)
            )
        )


def _active_admins(database: Database) -> list[str]:
    with database.read_session() as db:
        return list(
            db.scalars(
                select(User.username).where(User.role == Role.ADMIN, User.is_active.is_(True))
            )
        )


def test_disabling_ends_every_session_and_refuses_sign_in(database: Database) -> None:
    make_user(database, "ada", Role.EXPERIMENTER)
    for _ in range(2):
        assert isinstance(_sign_in(database, "ada"), users.NewLogin)
    assert len(_live_sessions(database, "ada")) == 2
    with database.writing() as db:
        assert accounts.disable_user(db, username="ada", actor=CLI) == 2
    assert _live_sessions(database, "ada") == []
    assert _sign_in(database, "ada") is users.Refusal.DISABLED
    assert _sign_in(database, "ada", "wrong password") is users.Refusal.WRONG_PASSWORD
    with database.writing() as db, pytest.raises(Conflict, match="already disabled"):
        accounts.disable_user(db, username="ada", actor=CLI)
    with database.writing() as db:
        accounts.enable_user(db, username="ada", actor=CLI)
    assert isinstance(_sign_in(database, "ada"), users.NewLogin)
    assert _actions(database, "ada") == [
        "user.created",
        "user.signed_in",
        "user.signed_in",
        "user.disabled",
        "user.sign_in_failed",
        "user.sign_in_failed",
        "user.enabled",
        "user.signed_in",
    ]


def test_the_last_active_admin_can_be_neither_disabled_nor_demoted(database: Database) -> None:
    make_user(database, "root", Role.ADMIN)
    make_user(database, "spare", Role.ADMIN)
    with database.writing() as db:
        accounts.disable_user(db, username="spare", actor=CLI)  # a disabled admin does not count
    changes: dict[str, Callable[..., object]] = {
        "disabled": lambda db: accounts.disable_user(db, username="root", actor=CLI),
        "demoted": lambda db: accounts.set_role(db, username="root", role="analyst", actor=CLI),
    }
    for what, change in changes.items():
        with database.writing() as db, pytest.raises(Conflict) as refused:
            change(db)
        assert refused.value.message == (
            f"'root' is the last active admin and cannot be {what}: "
            "make another account admin first"
        )
    assert _active_admins(database) == ["root"]
    with database.writing() as db:
        accounts.enable_user(db, username="spare", actor=CLI)
    with database.writing() as db:
        assert accounts.set_role(db, username="root", role="analyst", actor=CLI) == "admin"
    assert _active_admins(database) == ["spare"]


def _at_once(changes: list[Callable[[], None]]) -> list[BaseException | None]:
    """Run each change in its own thread, released together by a barrier; what each raised."""
    barrier = threading.Barrier(len(changes))
    results: list[BaseException | None] = [None] * len(changes)

    def run(index: int) -> None:
        barrier.wait(timeout=60)  # a guard against a hang, not a timing assumption
        try:
            changes[index]()
        except (Conflict, PermissionDenied) as exc:
            results[index] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(changes))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return results


@pytest.mark.parametrize("how", ["demote", "disable"])
def test_two_admins_removing_each_other_at_once_leave_one(database: Database, how: str) -> None:
    """Each change locks every active admin before counting them, so the second one waits and
    then sees that only one admin is left (or that its own actor is no longer one)."""
    make_user(database, "alice", Role.ADMIN)
    make_user(database, "bob", Role.ADMIN)
    with database.read_session() as db:
        actors = {
            name: Actor.of_user(db.scalars(select(User).where(User.username == name)).one())
            for name in ("alice", "bob")
        }

    def remove(target: str, actor: Actor) -> Callable[[], None]:
        def change() -> None:
            with database.writing() as db:
                if how == "demote":
                    accounts.set_role(db, username=target, role=Role.EXPERIMENTER, actor=actor)
                else:
                    accounts.disable_user(db, username=target, actor=actor)

        return change

    for round_actors in (
        {"alice": actors["bob"], "bob": actors["alice"]},
        {"alice": CLI, "bob": CLI},
    ):
        results = _at_once([remove(target, actor) for target, actor in round_actors.items()])
        assert sum(result is None for result in results) == 1, results
        assert len(_active_admins(database)) == 1
        # Restore both admins for the next round (the command line always may).
        with database.writing() as db:
            for name in ("alice", "bob"):
                user = users.named(db, name)
                user.role, user.is_active = Role.ADMIN, True
            db.commit()


def test_a_demoted_admin_can_no_longer_change_accounts(database: Database) -> None:
    make_user(database, "alice", Role.ADMIN)
    make_user(database, "bob", Role.ADMIN)
    make_user(database, "carol", Role.EXPERIMENTER)
    with database.read_session() as db:
        bob = Actor.of_user(users.named(db, "bob"))
    with database.writing() as db:
        accounts.set_role(db, username="bob", role=Role.ANALYST, actor=CLI)
    with database.writing() as db, pytest.raises(PermissionDenied, match="no longer an active"):
        accounts.disable_user(db, username="carol", actor=bob)


def test_setting_a_password_ends_the_other_sessions(database: Database) -> None:
    make_user(database, "ada", Role.ADMIN)
    make_user(database, "root", Role.ADMIN)
    for _ in range(2):
        _sign_in(database, "ada")
    kept, _other = _live_sessions(database, "ada")
    with database.writing() as db:
        assert (
            accounts.set_password(
                db, username="ada", password=NEW_PASSWORD, actor=CLI, keep_login=kept
            )
            == 1
        )
    assert _live_sessions(database, "ada") == [kept]
    assert _sign_in(database, "ada") is users.Refusal.WRONG_PASSWORD
    assert isinstance(_sign_in(database, "ada", NEW_PASSWORD), users.NewLogin)
    with database.writing() as db:
        accounts.set_password(db, username="ada", password=PASSWORD, actor=CLI)
    assert _live_sessions(database, "ada") == []
    with database.writing() as db, pytest.raises(Exception, match="at least 10 characters"):
        accounts.set_password(db, username="ada", password="short", actor=CLI)
    assert _actions(database, "ada").count("user.password_set") == 2


def test_changing_ones_own_password_needs_the_current_one(database: Database) -> None:
    make_user(database, "ada", Role.ANALYST)
    for _ in range(2):
        _sign_in(database, "ada")
    current, other = _live_sessions(database, "ada")
    with database.read_session() as db:
        login = db.get(LoginSession, current)
        assert login is not None
    new_hash = accounts.new_password_hash(NEW_PASSWORD)

    def change(password: str) -> object:
        with database.writing() as counting:
            check = users.begin_password_check(
                counting, username="ada", failed_action=users.PASSWORD_CHANGE_FAILED
            )
        with database.writing() as db:
            return accounts.change_own_password(
                db, login=login, check=check, current_password=password, new_hash=new_hash
            )

    assert change("not my password") is users.Refusal.WRONG_PASSWORD
    assert _live_sessions(database, "ada") == [current, other]
    assert change(PASSWORD) == 1
    assert _live_sessions(database, "ada") == [current]
    assert isinstance(_sign_in(database, "ada", NEW_PASSWORD), users.NewLogin)
    assert "user.password_change_failed" in _actions(database, "ada")
    assert "user.password_changed" in _actions(database, "ada")


def test_an_unlocked_admin_signs_in_again_and_the_failures_stay_on_record(
    database: Database,
) -> None:
    make_user(database, "root", Role.ADMIN)
    for _ in range(login_throttle.MAX_FAILURES_PER_ACCOUNT):
        _sign_in(database, "root", "wrong password")
    with pytest.raises(TooManyAttempts):
        _sign_in(database, "root")
    with database.read_session() as db:
        assert accounts.get_account(db, "root").locked_until is not None
    with database.writing() as db:
        assert accounts.unlock_user(db, username="root", actor=CLI) == 5
    with database.read_session() as db:
        assert accounts.get_account(db, "root").locked_until is None
        cleared = db.scalars(select(LoginAttempt.cleared_at)).all()
    assert len(cleared) == 5 and None not in cleared  # the refused attempt recorded nothing
    assert isinstance(_sign_in(database, "root"), users.NewLogin)
    assert "user.unlocked" in _actions(database, "root")


def test_accounts_are_named_exactly(database: Database) -> None:
    make_user(database, "ada", Role.ANALYST)
    with database.read_session() as db:
        assert users.named(db, "ADA").username == "ada"
        for lookalike in ("ada\n", " ada", "ada ", "nobody"):
            with pytest.raises(NotFound):
                users.named(db, lookalike)
    with database.writing() as db, pytest.raises(NotFound):
        accounts.disable_user(db, username="ada\n", actor=CLI)


def test_two_creations_of_one_name_at_once_refuse_the_second_clearly(database: Database) -> None:
    """Both may read that the name is free; the unique index refuses one: a Conflict, not a 500."""
    outcomes: list[str] = []
    barrier = threading.Barrier(2)

    def create(role: Role) -> None:
        barrier.wait(timeout=60)  # a guard against a hang, not a timing assumption
        try:
            with database.writing() as db:
                users.create_user(db, username="twin", role=role, password=PASSWORD, actor=CLI)
            outcomes.append("created")
        except Conflict as exc:
            outcomes.append(exc.message)

    threads = [threading.Thread(target=create, args=(r,)) for r in (Role.ANALYST, Role.ADMIN)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(outcomes) == ["a user named 'twin' already exists", "created"]
