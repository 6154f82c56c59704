"""Dashboard accounts: creation, password checks and sign-in sessions."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timedelta
from enum import StrEnum

from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import events
from app.errors import Conflict, InvalidInput, NotFound, TooManyAttempts
from app.inputs import USERNAME
from app.security import hash_password, new_token, password_problem, token_digest, verify_password
from app.services import audit
from app.services.audit import Actor
from app.services.staff import login_throttle
from app.tables import LoginSession, Role, User, utcnow


def normalise_username(username: str) -> str:
    """Usernames are case-insensitive: stored and compared in lower case."""
    return username.strip().lower()


def named(db: Session, username: str, *, for_update: bool = False) -> User:
    """The account a URL or a command names (NotFound otherwise). The name must be exactly a
    username, in any case: nothing is stripped, so ``"ada\\n"`` is not ``ada``."""
    name = username.lower()
    user = None
    if USERNAME.matches(name):
        query = select(User).where(User.username == name)
        if for_update:
            query = query.with_for_update().execution_options(populate_existing=True)
        user = db.scalar(query)
    if user is None:
        raise NotFound(f"no user named {username!r}")
    return user


def create_user(
    db: Session, *, username: str, role: Role | str, password: str, actor: Actor
) -> User:
    """Create an account; commits. Refuses bad names, weak passwords and duplicates."""
    name = normalise_username(username)
    if not USERNAME.matches(name):
        raise InvalidInput(USERNAME.rule)
    try:
        role = Role(role)
    except ValueError:
        raise InvalidInput(
            f"unknown role {role!r}: use one of {', '.join(r.value for r in Role)}"
        ) from None
    problem = password_problem(password)
    if problem:
        raise InvalidInput(problem)
    password_hash = hash_password(password)  # slow: before the write transaction begins
    if db.scalar(select(User.id).where(User.username == name)) is not None:
        raise Conflict(f"a user named {name!r} already exists")
    user = User(username=name, role=role, password_hash=password_hash)
    db.add(user)
    try:
        db.flush()  # PostgreSQL: a concurrent creation of the same name is refused here
    except IntegrityError:
        db.rollback()
        raise Conflict(f"a user named {name!r} already exists") from None
    audit.record(db, actor=actor, action="user.created", subject=name, details={"role": role})
    db.commit()
    return user


def count_users(db: Session) -> int:
    """How many accounts exist (first start creates the admin when there are none)."""
    return db.scalar(select(func.count()).select_from(User)) or 0


SIGN_IN_FAILED = "user.sign_in_failed"
PASSWORD_CHANGE_FAILED = "user.password_change_failed"


class Refusal(StrEnum):
    """Why a password check failed, as the audit log records it (never the password tried)."""

    WRONG_PASSWORD = "wrong password"
    UNKNOWN_USER = "unknown user"
    LOCKED = "locked"
    DISABLED = "disabled"


@dataclass(frozen=True)
class PasswordCheck:
    """A counted attempt (:func:`begin_password_check`) and the account it names, if any."""

    attempt_id: int
    username: str
    client_address: str
    user_id: int | None
    password_hash: str | None


def _record_refusal(
    db: Session,
    *,
    action: str,
    username: str,
    client_address: str,
    refusal: Refusal,
    **details: str,
) -> None:
    audit.record(
        db,
        actor=Actor.system("sign-in"),
        action=action,
        subject=username,
        details={"reason": refusal.value, "client_address": client_address, **details},
    )


def begin_password_check(
    db: Session, *, username: str, client_address: str = "", failed_action: str = SIGN_IN_FAILED
) -> PasswordCheck:
    """The first step of every password check: record the attempt as pending
    (login_throttle.reserve_when_free: it waits while other checks of the account or the address
    could still reach a limit) and read the account it names, in one write transaction; commits.

    Raises TooManyAttempts while the account or the address has failed too often; that refusal
    is audited as ``failed_action`` with the reason ``locked``. The password is checked next, with
    no transaction open (:func:`finish_sign_in`, app.services.staff.accounts.change_own_password).
    """
    name = normalise_username(username)[:64]
    address = client_address[:64]
    reserved = login_throttle.reserve_when_free(db, username=name, client_address=address)
    if isinstance(reserved, login_throttle.Locked):
        _record_refusal(
            db,
            action=failed_action,
            username=name,
            client_address=address,
            refusal=Refusal.LOCKED,
            by=reserved.by,
        )
        db.commit()
        raise TooManyAttempts(reserved.message())
    user = db.scalar(select(User).where(User.username == name))
    db.commit()
    return PasswordCheck(
        reserved, name, address, user.id if user else None, user.password_hash if user else None
    )


def check_password(
    db: Session, check: PasswordCheck, password: str, *, failed_action: str = SIGN_IN_FAILED
) -> User | Refusal:
    """Check the password of a :func:`begin_password_check`, then, in the caller's write
    transaction, read the account again (locked on PostgreSQL) and decide: the active account
    whose password this still is, or why not (audited as ``failed_action``).

    The check (Argon2id: deliberately slow) runs before the write transaction begins, because on
    SQLite that transaction is the single write lock; the caller must have no transaction open.
    An account disabled or given a new password meanwhile is refused.
    """
    valid = verify_password(check.password_hash, password)
    user = (
        db.get(User, check.user_id, with_for_update=True, populate_existing=True)
        if check.user_id is not None
        else None
    )
    if user is None:
        refusal = Refusal.UNKNOWN_USER
    elif not valid or user.password_hash != check.password_hash:
        refusal = Refusal.WRONG_PASSWORD
    elif not user.is_active:
        refusal = Refusal.DISABLED
    else:
        login_throttle.finish(db, check.attempt_id, succeeded=True)
        return user
    login_throttle.finish(db, check.attempt_id, succeeded=False)
    _record_refusal(
        db,
        action=failed_action,
        username=check.username,
        client_address=check.client_address,
        refusal=refusal,
    )
    return refusal


def authenticate(
    db: Session, *, username: str, password: str, client_address: str = ""
) -> User | None:
    """The active user with these credentials, or None (scripts and tests; pages and the API
    use :func:`begin_password_check` and :func:`finish_sign_in`). Commits; TooManyAttempts while
    throttled."""
    check = begin_password_check(db, username=username, client_address=client_address)
    user = check_password(db, check, password)
    db.commit()
    return user if isinstance(user, User) else None


@dataclass(frozen=True)
class NewLogin:
    """A fresh sign-in: the secret for the cookie (shown once) and its row."""

    token: str
    session: LoginSession


def _open_login(
    db: Session, *, user: User, lifetime: timedelta, user_agent: str, client_address: str
) -> NewLogin:
    token = new_token()
    now = utcnow()
    login = LoginSession(
        user_id=user.id,
        token_hash=token_digest(token),
        csrf_token=new_token(24),
        created_at=now,
        last_seen_at=now,
        expires_at=now + lifetime,
        user_agent=user_agent[:255],
        client_address=client_address[:64],
    )
    login.user = user
    db.add(login)
    user.last_login_at = now
    audit.record(db, actor=Actor.of_user(user), action="user.signed_in", subject=user.username)
    return NewLogin(token=token, session=login)


def sign_in(
    db: Session,
    *,
    user: User,
    lifetime: timedelta,
    user_agent: str = "",
    client_address: str = "",
) -> NewLogin:
    """Open a login session for an authenticated user; commits."""
    new_login = _open_login(
        db, user=user, lifetime=lifetime, user_agent=user_agent, client_address=client_address
    )
    db.commit()
    return new_login


def finish_sign_in(
    db: Session,
    *,
    check: PasswordCheck,
    password: str,
    lifetime: timedelta,
    user_agent: str = "",
    client_address: str = "",
) -> NewLogin | Refusal:
    """Check the password of a :func:`begin_password_check` and, if it is right, open a login
    session: the attempt's outcome, the login and its audit row in one write transaction; commits.
    A refusal is audited with its reason; pages show the same message for every reason but
    :attr:`Refusal.DISABLED`, which only the holder of the right password gets to see.

    The caller must have no transaction open (the password is checked before the write begins).
    """
    user = check_password(db, check, password)
    new_login = (
        _open_login(
            db, user=user, lifetime=lifetime, user_agent=user_agent, client_address=client_address
        )
        if isinstance(user, User)
        else user
    )
    db.commit()
    return new_login


def resolve_login(db: Session, *, token: str, idle_timeout: timedelta) -> LoginSession | None:
    """The live login session behind a cookie, or None if unknown, expired, idle or revoked."""
    login = db.scalar(select(LoginSession).where(LoginSession.token_hash == token_digest(token)))
    now = utcnow()
    if (
        login is None
        or login.revoked_at is not None
        or login.expires_at <= now
        or login.last_seen_at + idle_timeout <= now
        or not login.user.is_active
    ):
        return None
    return login


LOGIN_ENDED = "login.ended"
"""The event that ends a login's open event streams (app.web.streams) when the login ends."""


def login_topic(login_id: int) -> str:
    """The event topic of one login session: its event streams listen to it."""
    return f"login:{login_id}"


def end_logins(db: Session, *, user_id: int, keep: int | None = None) -> int:
    """Revoke the user's live login sessions (but ``keep``), in the caller's transaction: their
    next request is signed out, and their open event streams end when it commits. Returns how
    many ended."""
    query = select(LoginSession.id).where(
        LoginSession.user_id == user_id, LoginSession.revoked_at.is_(None)
    )
    if keep is not None:
        query = query.where(LoginSession.id != keep)
    ended = list(db.scalars(query))
    if ended:
        db.execute(
            update(LoginSession).where(LoginSession.id.in_(ended)).values(revoked_at=utcnow())
        )
        events.publish(db, topics=[login_topic(i) for i in ended], type=LOGIN_ENDED)
    return len(ended)


def sign_out(db: Session, *, login: LoginSession) -> None:
    """Revoke a login session (and end its event streams); commits."""
    login.revoked_at = utcnow()
    events.publish(db, topics=[login_topic(login.id)], type=LOGIN_ENDED)
    audit.record(
        db, actor=Actor.of_user(login.user), action="user.signed_out", subject=login.user.username
    )
    db.commit()
