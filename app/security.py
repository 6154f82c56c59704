"""Passwords, random tokens and CSRF tokens.

Passwords are hashed with Argon2id (argon2-cffi's defaults, which follow RFC 9106's
recommendations). Bearer secrets (login cookies, device keys, participant tokens) are long random
strings whose SHA-256 alone is stored: they are high-entropy, so a slow hash adds nothing, and a
fast one keeps every request cheap. CSRF tokens for anonymous forms are HMAC-signed so the login
page needs no server-side state.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import secrets

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

_hasher = PasswordHasher()

MIN_PASSWORD_LENGTH = 10


def hash_password(password: str) -> str:
    """An Argon2id hash of ``password``."""
    return _hasher.hash(password)


@functools.cache
def dummy_hash() -> str:
    """What an unknown username's password is checked against, so that the answer takes as long
    as for a known one. Made on first use rather than at import (it costs a hash, about 0.3 s,
    that every command importing this module paid); a served app makes it at start (app.main),
    so no sign-in waits for it."""
    return _hasher.hash("trustlab: equalises the timing of unknown usernames")


def verify_password(password_hash: str | None, password: str) -> bool:
    """Whether ``password`` matches; with no hash, spend the same time and say no."""
    try:
        return _hasher.verify(password_hash or dummy_hash(), password) and password_hash is not None
    except (VerificationError, InvalidHashError):
        return False


def password_problem(password: str) -> str | None:
    """Why a new password is unacceptable, or None."""
    if len(password) < MIN_PASSWORD_LENGTH:
        return f"a password needs at least {MIN_PASSWORD_LENGTH} characters"
    if len(password) > 1024:
        return "a password may have at most 1024 characters"
    return None


def new_token(nbytes: int = 32) -> str:
    """A URL-safe random secret."""
    return secrets.token_urlsafe(nbytes)


def token_digest(token: str) -> str:
    """The SHA-256 (hex) under which a bearer secret is stored and looked up."""
    return hashlib.sha256(token.encode()).hexdigest()


def same(a: str, b: str) -> bool:
    """Constant-time string comparison."""
    return hmac.compare_digest(a.encode(), b.encode())


def sign(secret: bytes, value: str) -> str:
    """``value`` with an HMAC-SHA256 signature appended."""
    mac = hmac.new(secret, value.encode(), hashlib.sha256).hexdigest()
    return f"{value}.{mac}"


def unsign(secret: bytes, signed: str) -> str | None:
    """The value inside a :func:`sign`-ed string, or None if the signature is wrong."""
    value, _, mac = signed.rpartition(".")
    if not value:
        return None
    expected = hmac.new(secret, value.encode(), hashlib.sha256).hexdigest()
    return value if hmac.compare_digest(mac, expected) else None
