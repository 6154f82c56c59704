"""Slowing down password guessing: a password is checked only after its attempt has been counted.

Every password check (a sign-in, or the current password when someone changes theirs) first
*reserves* an attempt: in one write transaction it locks the account's and the client address's
throttle, counts their failures in the window and, below both limits, records the attempt as a
failure. Only then is the password checked (Argon2id, slow by design, with no transaction open);
an attempt that turns out right is marked succeeded afterwards (:func:`mark_succeeded`).

Deciding and counting happen under one lock, so however many attempts arrive at once, exactly
``limit`` of them are checked: on SQLite the write transaction is the single write lock
(``BEGIN IMMEDIATE``); on PostgreSQL it takes transaction-level advisory locks on the username and
on the address, because an unknown username or an address has no row that ``SELECT … FOR UPDATE``
could lock. The account lock is always taken before the address lock, so two reservations can
never wait for each other in a cycle.

An admin lifts an account's lockout early by clearing its failures (:func:`clear`): they stay in
the table, marked cleared, and no longer count.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import select, text, update
from sqlalchemy.orm import InstrumentedAttribute, Session

from app.tables import LoginAttempt, utcnow

WINDOW = timedelta(minutes=15)
MAX_FAILURES_PER_ACCOUNT = 5
MAX_FAILURES_PER_ADDRESS = 20

_ACCOUNT_LOCKS, _ADDRESS_LOCKS = 7301, 7302
"""The two key spaces of PostgreSQL advisory locks taken here (arbitrary, unused elsewhere)."""


@dataclass(frozen=True)
class Locked:
    """A refused reservation: which throttle refused it and when it will let attempts through."""

    by: str
    """``"account"`` or ``"address"``."""
    until: datetime

    def message(self, now: datetime | None = None) -> str:
        """The refusal as the person signing in reads it."""
        wait = self.until - (now or utcnow())
        minutes = max(1, int(wait.total_seconds() // 60) + 1)
        return f"too many failed sign-ins from this {self.by}; try again in {minutes} minutes"


def _lock(db: Session, space: int, key: str) -> None:
    if db.get_bind().dialect.name == "postgresql":
        db.execute(
            text("SELECT pg_advisory_xact_lock(:space, hashtext(:key))"),
            {"space": space, "key": key},
        )


def _failures(
    db: Session, column: InstrumentedAttribute[str], value: str, limit: int, now: datetime
) -> list[datetime]:
    """When the newest ``limit`` failures that still count happened (newest first)."""
    return list(
        db.scalars(
            select(LoginAttempt.attempted_at)
            .where(
                column == value,
                LoginAttempt.attempted_at > now - WINDOW,
                LoginAttempt.succeeded.is_(False),
                LoginAttempt.cleared_at.is_(None),
            )
            .order_by(LoginAttempt.attempted_at.desc())
            .limit(limit)
        )
    )


def _locked(db: Session, *, username: str, client_address: str, now: datetime) -> Locked | None:
    for by, column, value, limit in (
        ("account", LoginAttempt.username, username, MAX_FAILURES_PER_ACCOUNT),
        ("address", LoginAttempt.client_address, client_address, MAX_FAILURES_PER_ADDRESS),
    ):
        if not value:
            continue
        failures = _failures(db, column, value, limit, now)
        if len(failures) >= limit:
            return Locked(by, failures[-1] + WINDOW)
    return None


def reserve(
    db: Session, *, username: str, client_address: str, now: datetime | None = None
) -> int | Locked:
    """Count one attempt for ``username`` from ``client_address`` before its password is checked:
    its row's id, recorded as a failure, or :class:`Locked` (nothing recorded) when either has
    failed too often in the window. Call it in a write transaction; the caller commits."""
    now = now or utcnow()
    _lock(db, _ACCOUNT_LOCKS, username)
    if client_address:
        _lock(db, _ADDRESS_LOCKS, client_address)
    locked = _locked(db, username=username, client_address=client_address, now=now)
    if locked is not None:
        return locked
    attempt = LoginAttempt(
        username=username, client_address=client_address, succeeded=False, attempted_at=now
    )
    db.add(attempt)
    db.flush()
    return attempt.id


def mark_succeeded(db: Session, attempt_id: int) -> None:
    """The reserved attempt's password was right: it no longer counts as a failure."""
    db.execute(update(LoginAttempt).where(LoginAttempt.id == attempt_id).values(succeeded=True))


def locked_until(db: Session, *, username: str, now: datetime | None = None) -> datetime | None:
    """Until when the account refuses sign-ins (its own failures only), or None."""
    now = now or utcnow()
    failures = _failures(db, LoginAttempt.username, username, MAX_FAILURES_PER_ACCOUNT, now)
    return failures[-1] + WINDOW if len(failures) >= MAX_FAILURES_PER_ACCOUNT else None


def clear(db: Session, *, username: str, now: datetime | None = None) -> int:
    """Stop the account's failures in the window from counting (an admin's unlock); returns how
    many were cleared. The caller commits."""
    now = now or utcnow()
    result = db.execute(
        update(LoginAttempt)
        .where(
            LoginAttempt.username == username,
            LoginAttempt.attempted_at > now - WINDOW,
            LoginAttempt.succeeded.is_(False),
            LoginAttempt.cleared_at.is_(None),
        )
        .values(cleared_at=now)
    )
    return int(result.rowcount or 0)  # type: ignore[attr-defined]
