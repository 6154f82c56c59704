"""Dashboard accounts: creation, password checks and sign-in sessions."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import timedelta

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput, NotFound, TooManyAttempts
from app.inputs import USERNAME
from app.security import hash_password, new_token, password_problem, token_digest, verify_password
from app.services import audit
from app.services.audit import Actor
from app.tables import LoginAttempt, LoginSession, Role, User, utcnow


def normalise_username(username: str) -> str:
    """Usernames are case-insensitive: stored and compared in lower case."""
    return username.strip().lower()


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
    if db.scalar(select(User.id).where(User.username == name)) is not None:
        raise Conflict(f"a user named {name!r} already exists")
    user = User(username=name, role=role, password_hash=hash_password(password))
    db.add(user)
    db.flush()
    audit.record(db, actor=actor, action="user.created", subject=name, details={"role": role})
    db.commit()
    return user


def deactivate_user(db: Session, *, username: str, actor: Actor) -> User:
    """Stop an account from signing in (its history stays); commits."""
    name = normalise_username(username)
    user = db.scalar(select(User).where(User.username == name))
    if user is None:
        raise NotFound(f"no user named {name!r}")
    user.is_active = False
    db.execute(
        update(LoginSession)
        .where(LoginSession.user_id == user.id, LoginSession.revoked_at.is_(None))
        .values(revoked_at=utcnow())
    )
    audit.record(db, actor=actor, action="user.deactivated", subject=name, details={})
    db.commit()
    return user


def count_users(db: Session) -> int:
    """How many accounts exist (first start creates the admin when there are none)."""
    return db.scalar(select(func.count()).select_from(User)) or 0


THROTTLE_WINDOW = timedelta(minutes=15)
MAX_FAILURES_PER_ACCOUNT = 5
MAX_FAILURES_PER_ADDRESS = 20


def _throttle(db: Session, *, username: str, client_address: str) -> None:
    """Refuse (429) while an account or an address has failed too often in the window."""
    since = utcnow() - THROTTLE_WINDOW
    for column, value, limit, what in (
        (LoginAttempt.username, username, MAX_FAILURES_PER_ACCOUNT, "this account"),
        (LoginAttempt.client_address, client_address, MAX_FAILURES_PER_ADDRESS, "this address"),
    ):
        if not value:
            continue
        failures = db.scalars(
            select(LoginAttempt.attempted_at)
            .where(
                column == value,
                LoginAttempt.attempted_at > since,
                LoginAttempt.succeeded.is_(False),
            )
            .order_by(LoginAttempt.attempted_at.desc())
            .limit(limit)
        ).all()
        if len(failures) >= limit:
            wait = failures[-1] + THROTTLE_WINDOW - utcnow()
            minutes = max(1, int(wait.total_seconds() // 60) + 1)
            raise TooManyAttempts(
                f"too many failed sign-ins from {what}; try again in {minutes} minutes"
            )


@dataclass(frozen=True)
class Candidate:
    """Who a sign-in claims to be, read before its password is checked (:func:`find_candidate`)."""

    username: str
    client_address: str
    user_id: int | None
    password_hash: str | None


def find_candidate(db: Session, *, username: str, client_address: str = "") -> Candidate:
    """The first, read-only step of a sign-in: refused (TooManyAttempts) while the account or the
    address has failed too often, otherwise the account the username names, if any."""
    name = normalise_username(username)[:64]
    address = client_address[:64]
    _throttle(db, username=name, client_address=address)
    user = db.scalar(select(User).where(User.username == name))
    return Candidate(name, address, user.id if user else None, user.password_hash if user else None)


def _attempt(db: Session, candidate: Candidate, password: str) -> User | None:
    """Check the password, then record the attempt in the caller's write transaction.

    The check (Argon2id: deliberately slow) runs before the write transaction begins, because on
    SQLite that transaction is the single write lock; the caller must have no transaction open.
    Inside the transaction the throttle is checked again and the account read again (locked on
    PostgreSQL), so concurrent attempts cannot exceed the limits, and an account deactivated or
    given a new password meanwhile is refused.
    """
    valid = verify_password(candidate.password_hash, password)
    _throttle(db, username=candidate.username, client_address=candidate.client_address)
    user = (
        db.get(User, candidate.user_id, with_for_update=True, populate_existing=True)
        if candidate.user_id is not None
        else None
    )
    ok = (
        user is not None
        and valid
        and user.is_active
        and user.password_hash == candidate.password_hash
    )
    db.add(
        LoginAttempt(
            username=candidate.username, client_address=candidate.client_address, succeeded=ok
        )
    )
    return user if ok else None


def authenticate(
    db: Session, *, username: str, password: str, client_address: str = ""
) -> User | None:
    """The active user with these credentials, or None (never saying which part was wrong).

    Every attempt is recorded (and committed, successful or not); after repeated failures the
    account or the address is refused with TooManyAttempts before any password is checked.
    """
    candidate = find_candidate(db, username=username, client_address=client_address)
    db.commit()  # no transaction stays open while the password is checked
    user = _attempt(db, candidate, password)
    db.commit()
    return user


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


def sign_in_with_password(
    db: Session,
    *,
    candidate: Candidate,
    password: str,
    lifetime: timedelta,
    user_agent: str = "",
    client_address: str = "",
) -> NewLogin | None:
    """Check the password of a :func:`find_candidate` and, if it is right, open a login session:
    the attempt, the login and its audit row in one write transaction; commits. None when the
    credentials are wrong (never saying which part); TooManyAttempts when throttled meanwhile.

    The caller must have no transaction open (the password is checked before the write begins).
    """
    user = _attempt(db, candidate, password)
    new_login = (
        _open_login(
            db, user=user, lifetime=lifetime, user_agent=user_agent, client_address=client_address
        )
        if user is not None
        else None
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


def sign_out(db: Session, *, login: LoginSession) -> None:
    """Revoke a login session; commits."""
    login.revoked_at = utcnow()
    audit.record(
        db, actor=Actor.of_user(login.user), action="user.signed_out", subject=login.user.username
    )
    db.commit()
