"""The lifecycle of existing accounts: disable, enable, passwords, roles and unlocking.

The web pages (app.web.accounts) and the command line (``trustlab user …``) both call these, so
they share every rule:

- An account that is disabled, or whose password is set, loses its login sessions at once (a
  password change by its owner keeps the login it was made from); a role change takes effect on
  the next request, because every request reads the role afresh.
- **There is always an active admin.** The last one can be neither disabled nor demoted. Two such
  changes at once must not both pass, so each first locks every active admin's row (``SELECT … FOR
  UPDATE`` in id order on PostgreSQL; SQLite's write lock does it there) and then counts: the second
  change waits, then sees the first one's result. A signed-in admin's change is also refused if the
  same lock shows they are no longer an active admin themselves.
- Each change is in the audit log, in the same transaction.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput, PermissionDenied
from app.security import hash_password, password_problem
from app.services import audit
from app.services.audit import Actor
from app.services.staff import login_throttle, users
from app.tables import ActorKind, LoginSession, Role, User


@dataclass(frozen=True)
class Account:
    """An account as listings show it."""

    username: str
    role: str
    is_active: bool
    created_at: datetime
    last_login_at: datetime | None
    locked_until: datetime | None
    """Until when failed sign-ins lock it out (app.services.staff.login_throttle), or None."""
    sites: list[str] | None = None
    """The sites the account is limited to (app.services.privacy.sites); None: every site."""


def _account(db: Session, user: User) -> Account:
    return Account(
        user.username,
        user.role,
        user.is_active,
        user.created_at,
        user.last_login_at,
        login_throttle.locked_until(db, username=user.username),
        user.sites,
    )


def list_accounts(db: Session) -> list[Account]:
    """Every account, by username."""
    return [_account(db, user) for user in db.scalars(select(User).order_by(User.username))]


def get_account(db: Session, username: str) -> Account:
    """One account (NotFound unless ``username`` is exactly an account's name)."""
    return _account(db, users.named(db, username))


def _lock_for_change(db: Session, username: str, actor: Actor) -> tuple[User, list[User]]:
    """The account to change and the active admins, all locked (admins first, in id order, so two
    changes always lock in the same order); refuses a user actor who is no longer an admin."""
    admins = list(
        db.scalars(
            select(User)
            .where(User.role == Role.ADMIN, User.is_active.is_(True))
            .order_by(User.id)
            .with_for_update()
            .execution_options(populate_existing=True)
        )
    )
    if actor.kind == ActorKind.USER and actor.name not in {a.username for a in admins}:
        raise PermissionDenied("you are no longer an active admin")
    return users.named(db, username, for_update=True), admins


def _keep_an_admin(target: User, admins: list[User], change: str) -> None:
    if target in admins and len(admins) == 1:
        raise Conflict(
            f"{target.username!r} is the last active admin and cannot be {change}: "
            "make another account admin first"
        )


def disable_user(db: Session, *, username: str, actor: Actor) -> int:
    """Stop an account from signing in and end its login sessions (its history stays); commits.
    Returns how many sessions ended."""
    user, admins = _lock_for_change(db, username, actor)
    if not user.is_active:
        raise Conflict(f"{user.username!r} is already disabled")
    _keep_an_admin(user, admins, "disabled")
    user.is_active = False
    ended = users.end_logins(db, user_id=user.id)
    audit.record(
        db, actor=actor, action="user.disabled", subject=user.username, details={"ended": ended}
    )
    db.commit()
    return ended


def enable_user(db: Session, *, username: str, actor: Actor) -> None:
    """Let a disabled account sign in again; commits."""
    user, _ = _lock_for_change(db, username, actor)
    if user.is_active:
        raise Conflict(f"{user.username!r} is already enabled")
    user.is_active = True
    audit.record(db, actor=actor, action="user.enabled", subject=user.username)
    db.commit()


def set_role(db: Session, *, username: str, role: Role | str, actor: Actor) -> str:
    """Give an account another role (effective on its next request); commits. Returns the old
    role."""
    try:
        new_role = Role(role)
    except ValueError:
        raise InvalidInput(
            f"unknown role {role!r}: use one of {', '.join(r.value for r in Role)}"
        ) from None
    user, admins = _lock_for_change(db, username, actor)
    old_role = user.role
    if old_role == new_role:
        raise Conflict(f"{user.username!r} is already {new_role.value}")
    if new_role != Role.ADMIN:
        _keep_an_admin(user, admins, "demoted")
    user.role = new_role
    details: dict[str, object] = {"from": old_role, "to": new_role.value}
    if new_role == Role.ADMIN and user.sites is not None:
        # Admins see every site (app.services.privacy.sites): a limit kept would only mislead.
        details["sites_cleared"] = user.sites
        user.sites = None
    audit.record(
        db,
        actor=actor,
        action="user.role_changed",
        subject=user.username,
        details=details,
    )
    db.commit()
    return old_role


def new_password_hash(password: str) -> str:
    """Check and hash a new password (InvalidInput if it is too weak). Slow by design: call it
    before the write transaction begins."""
    problem = password_problem(password)
    if problem:
        raise InvalidInput(problem)
    return hash_password(password)


def set_password(
    db: Session, *, username: str, password: str, actor: Actor, keep_login: int | None = None
) -> int:
    """Give an account a new password (an admin's reset) and end its login sessions but
    ``keep_login`` (the admin's own, when they reset their own password); commits. Returns how
    many sessions ended. The new password is hashed before the write transaction begins."""
    password_hash = new_password_hash(password)
    user, _ = _lock_for_change(db, username, actor)
    user.password_hash = password_hash
    ended = users.end_logins(db, user_id=user.id, keep=keep_login)
    audit.record(
        db, actor=actor, action="user.password_set", subject=user.username, details={"ended": ended}
    )
    db.commit()
    return ended


def change_own_password(
    db: Session,
    *,
    login: LoginSession,
    check: users.PasswordCheck,
    current_password: str,
    new_hash: str,
) -> users.Refusal | int:
    """A signed-in user's own password change: ``check`` (users.begin_password_check for their
    account, so wrong current passwords count towards the lockout like failed sign-ins) must
    verify ``current_password``; then the password becomes ``new_hash``
    (:func:`new_password_hash`) and every other login of theirs ends. Commits; returns how many
    sessions ended, or why the current password was refused (audited).

    The caller must have no transaction open (the current password is checked before the write).
    """
    user = users.check_password(
        db, check, current_password, failed_action=users.PASSWORD_CHANGE_FAILED
    )
    if not isinstance(user, User):
        db.commit()
        return user
    user.password_hash = new_hash
    ended = users.end_logins(db, user_id=user.id, keep=login.id)
    audit.record(
        db,
        actor=Actor.of_user(user),
        action="user.password_changed",
        subject=user.username,
        details={"ended": ended},
    )
    db.commit()
    return ended


def unlock_user(db: Session, *, username: str, actor: Actor) -> int:
    """End an account's lockout after failed sign-ins now: its failures in the window stop
    counting (they stay on record); commits. Returns how many were cleared."""
    user, _ = _lock_for_change(db, username, actor)
    cleared = login_throttle.clear(db, username=user.username)
    audit.record(
        db, actor=actor, action="user.unlocked", subject=user.username, details={"cleared": cleared}
    )
    db.commit()
    return cleared
