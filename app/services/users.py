"""Dashboard accounts: creation, password checks and sign-in sessions."""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import timedelta

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput
from app.security import hash_password, new_token, password_problem, token_digest, verify_password
from app.services import audit
from app.services.audit import Actor
from app.tables import LoginSession, Role, User, utcnow

USERNAME_PATTERN = re.compile(r"^[a-z0-9][a-z0-9._-]{1,63}$")

LAST_SEEN_GRANULARITY = timedelta(minutes=1)
"""A login's last-seen time is written at most this often, so reads stay reads."""


def normalise_username(username: str) -> str:
    """Usernames are case-insensitive: stored and compared in lower case."""
    return username.strip().lower()


def create_user(
    db: Session, *, username: str, role: Role | str, password: str, actor: Actor
) -> User:
    """Create an account; commits. Refuses bad names, weak passwords and duplicates."""
    name = normalise_username(username)
    if not USERNAME_PATTERN.match(name):
        raise InvalidInput(
            "a username has 2-64 characters: letters, digits, '.', '_' or '-', "
            "starting with a letter or digit"
        )
    try:
        role = Role(role)
    except ValueError:
        raise InvalidInput(
            f"unknown role {role!r}: use one of {', '.join(r.value for r in Role)}"
        ) from None
    problem = password_problem(password)
    if problem:
        raise InvalidInput(problem)
    if db.scalar(select(User.id).where(User.username == name)) is not None:
        raise Conflict(f"a user named {name!r} already exists")
    user = User(username=name, role=role, password_hash=hash_password(password))
    db.add(user)
    db.flush()
    audit.record(db, actor=actor, action="user.created", subject=name, details={"role": role})
    db.commit()
    return user


def count_users(db: Session) -> int:
    """How many accounts exist (first start creates the admin when there are none)."""
    return db.scalar(select(func.count()).select_from(User)) or 0


def authenticate(db: Session, *, username: str, password: str) -> User | None:
    """The active user with these credentials, or None (never saying which part was wrong)."""
    user = db.scalar(select(User).where(User.username == normalise_username(username)))
    valid = verify_password(user.password_hash if user else None, password)
    if user is None or not valid or not user.is_active:
        return None
    return user


@dataclass(frozen=True)
class NewLogin:
    """A fresh sign-in: the secret for the cookie (shown once) and its row."""

    token: str
    session: LoginSession


def sign_in(
    db: Session,
    *,
    user: User,
    lifetime: timedelta,
    user_agent: str = "",
    client_address: str = "",
) -> NewLogin:
    """Open a login session for an authenticated user; commits."""
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
    db.add(login)
    user.last_login_at = now
    audit.record(db, actor=Actor.of_user(user), action="user.signed_in", subject=user.username)
    db.commit()
    return NewLogin(token=token, session=login)


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


def login_needs_touch(login: LoginSession) -> bool:
    """Whether the login's last-seen time is stale enough to be written again."""
    return utcnow() - login.last_seen_at >= LAST_SEEN_GRANULARITY


def touch_login(db: Session, *, login_id: int) -> None:
    """Record activity on a login; commits. Call with a write session of its own."""
    db.execute(
        update(LoginSession).where(LoginSession.id == login_id).values(last_seen_at=utcnow())
    )
    db.commit()


def sign_out(db: Session, *, login: LoginSession) -> None:
    """Revoke a login session; commits."""
    login.revoked_at = utcnow()
    audit.record(
        db, actor=Actor.of_user(login.user), action="user.signed_out", subject=login.user.username
    )
    db.commit()
