"""Slowing down password guessing: a failure counts once it has failed, and never more passwords
are checked at once than may still fail.

Every password check (a sign-in, or the current password when someone changes theirs) first
*reserves* an attempt: in one write transaction it locks the account's and the client address's
throttle and counts, per throttle, the failures in the window and the attempts still being checked
(*pending*). Below both limits the attempt is recorded pending and its password is checked
(Argon2id, slow by design, with no transaction open); it is then marked failed or succeeded
(:func:`finish`). Failures alone lock an account or an address out (:class:`Locked`). When the
failures are below the limit but the pending attempts fill the rest of it, the reservation waits
for them to finish rather than refusing (:func:`reserve_when_free`): had they all failed they would
reach the limit, so checking another password before they finish could let more than ``limit``
guesses through. Twenty right passwords at once therefore all sign in, five at a time, and thirty
wrong ones at once get exactly five checked.

An attempt whose check never finishes (the server stopped) does not count as a failure: it stops
holding a place after :data:`PENDING_TIMEOUT`, and a server start marks every pending attempt
abandoned at once (:func:`abandon_unfinished`), so a restart never locks anyone out nor makes
anyone wait.

Deciding and counting happen under one lock, so however many attempts arrive at once, no more
than ``limit`` of them are checked before the failures are known: on SQLite the write transaction
is the single write lock (``BEGIN IMMEDIATE``); on PostgreSQL it takes transaction-level advisory
locks on the username and on the address, because an unknown username or an address has no row
that ``SELECT … FOR UPDATE`` could lock. The account lock is always taken before the address lock,
so two reservations can never wait for each other in a cycle.

An admin lifts an account's lockout early by clearing its failures (:func:`clear`): they stay in
the table, marked cleared, and no longer count.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import ColumnElement, event, select, text, update
from sqlalchemy.orm import InstrumentedAttribute, Session

from app.tables import AttemptOutcome, LoginAttempt, utcnow

WINDOW = timedelta(minutes=15)
MAX_FAILURES_PER_ACCOUNT = 5
MAX_FAILURES_PER_ADDRESS = 20
PENDING_TIMEOUT = timedelta(minutes=1)
"""How long a pending attempt holds its place: far longer than any password check takes (Argon2id
is tuned to well under a second), so only an attempt whose server stopped outlives it."""
RECHECK_SECONDS = 0.2
"""How often a waiting reservation looks again when no attempt of this process has finished
(another worker's attempts finish unseen)."""

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


@dataclass(frozen=True)
class Busy:
    """A reservation that must wait: attempts still being checked fill the rest of a limit."""

    by: str


class _Finishes:
    """A count of this process's finished attempts that waiting reservations can sleep on."""

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._count = 0

    def seen(self) -> int:
        """How many have finished so far (read before looking at the table)."""
        with self._changed:
            return self._count

    def note(self) -> None:
        """One more attempt has finished and committed: wake the waiting reservations."""
        with self._changed:
            self._count += 1
            self._changed.notify_all()

    def wait_after(self, seen: int, timeout: float) -> None:
        """Return once another attempt finished after ``seen`` was read, or after ``timeout``."""
        with self._changed:
            self._changed.wait_for(lambda: self._count != seen, timeout)


_finishes = _Finishes()


def _lock(db: Session, space: int, key: str) -> None:
    if db.get_bind().dialect.name == "postgresql":
        db.execute(
            text("SELECT pg_advisory_xact_lock(:space, hashtext(:key))"),
            {"space": space, "key": key},
        )


def _still_counting(now: datetime) -> ColumnElement[bool]:
    """Attempts that are failures in the window (not cleared)."""
    return (
        (LoginAttempt.attempted_at > now - WINDOW)
        & (LoginAttempt.outcome == AttemptOutcome.FAILED)
        & LoginAttempt.cleared_at.is_(None)
    )


def _failures(
    db: Session, column: InstrumentedAttribute[str], value: str, limit: int, now: datetime
) -> list[datetime]:
    """When the newest ``limit`` failures that still count happened (newest first)."""
    return list(
        db.scalars(
            select(LoginAttempt.attempted_at)
            .where(column == value, _still_counting(now))
            .order_by(LoginAttempt.attempted_at.desc())
            .limit(limit)
        )
    )


def _tally(
    db: Session, column: InstrumentedAttribute[str], value: str, now: datetime
) -> tuple[list[datetime], int]:
    """The failures that still count (their times, newest first) and how many attempts are being
    checked (younger than :data:`PENDING_TIMEOUT`), read in one statement: on PostgreSQL each
    statement has its own snapshot, and a check finishing between two of them would be counted
    neither as pending nor as failed."""
    being_checked = (LoginAttempt.outcome == AttemptOutcome.PENDING) & (
        LoginAttempt.attempted_at > now - PENDING_TIMEOUT
    )
    rows = db.execute(
        select(LoginAttempt.outcome, LoginAttempt.attempted_at)
        .where(column == value, _still_counting(now) | being_checked)
        .order_by(LoginAttempt.attempted_at.desc())
    ).all()
    failures = [at for outcome, at in rows if outcome == AttemptOutcome.FAILED]
    return failures, len(rows) - len(failures)


def _verdict(
    db: Session, *, username: str, client_address: str, now: datetime
) -> Locked | Busy | None:
    """Why an attempt may not be checked now (locked out, or wait), or None. (Each throttle holds
    at most about ``limit`` such rows: no reservation is made past it.)"""
    for by, column, value, limit in (
        ("account", LoginAttempt.username, username, MAX_FAILURES_PER_ACCOUNT),
        ("address", LoginAttempt.client_address, client_address, MAX_FAILURES_PER_ADDRESS),
    ):
        if not value:
            continue
        failures, pending = _tally(db, column, value, now)
        if len(failures) >= limit:
            return Locked(by, failures[limit - 1] + WINDOW)
        if len(failures) + pending >= limit:
            return Busy(by)
    return None


def reserve(
    db: Session, *, username: str, client_address: str, now: datetime | None = None
) -> int | Locked | Busy:
    """Record one pending attempt for ``username`` from ``client_address`` before its password is
    checked: its row's id; or :class:`Locked` when either has failed too often in the window; or
    :class:`Busy` when attempts being checked fill the rest of a limit (nothing recorded in either
    case). Call it in a write transaction; the caller commits."""
    now = now or utcnow()
    _lock(db, _ACCOUNT_LOCKS, username)
    if client_address:
        _lock(db, _ADDRESS_LOCKS, client_address)
    verdict = _verdict(db, username=username, client_address=client_address, now=now)
    if verdict is not None:
        return verdict
    attempt = LoginAttempt(
        username=username,
        client_address=client_address,
        outcome=AttemptOutcome.PENDING,
        attempted_at=now,
    )
    db.add(attempt)
    db.flush()
    return attempt.id


def reserve_when_free(db: Session, *, username: str, client_address: str) -> int | Locked:
    """:func:`reserve`, waiting while it answers :class:`Busy`: the attempts being checked
    finish (or outlive :data:`PENDING_TIMEOUT`), and then this one is checked or locked out.

    Each look is its own write transaction (rolled back while waiting, so the write lock is free
    for the attempts that finish); the reservation is left for the caller to commit."""
    while True:
        seen = _finishes.seen()
        reserved = reserve(db, username=username, client_address=client_address)
        if not isinstance(reserved, Busy):
            return reserved
        db.rollback()
        _finishes.wait_after(seen, RECHECK_SECONDS)


def finish(db: Session, attempt_id: int, *, succeeded: bool) -> None:
    """The reserved attempt's password was checked: it failed (and now counts) or succeeded.
    In the caller's transaction; reservations waiting in this process look again once it
    commits."""
    outcome = AttemptOutcome.SUCCEEDED if succeeded else AttemptOutcome.FAILED
    db.execute(update(LoginAttempt).where(LoginAttempt.id == attempt_id).values(outcome=outcome))
    event.listen(db, "after_commit", lambda _session: _finishes.note(), once=True)


def abandon_unfinished(db: Session) -> int:
    """Mark every pending attempt abandoned (a server start: the checks they stood for died with
    the last server, and must neither count nor be waited for); returns how many. An attempt of
    another worker still being checked is finished as usual all the same. The caller commits."""
    result = db.execute(
        update(LoginAttempt)
        .where(LoginAttempt.outcome == AttemptOutcome.PENDING)
        .values(outcome=AttemptOutcome.ABANDONED)
    )
    return int(result.rowcount or 0)  # type: ignore[attr-defined]


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
        .where(LoginAttempt.username == username, _still_counting(now))
        .values(cleared_at=now)
    )
    return int(result.rowcount or 0)  # type: ignore[attr-defined]
