"""Domain errors: each says in one sentence what went wrong and what is expected instead.

Services raise these; the web layer maps them to HTTP statuses and the CLI to ``error: …`` lines,
so a person never sees a stack trace for a mistake they can fix.
"""

from __future__ import annotations


class TrustlabError(Exception):
    """Base class: ``message`` is shown to the user as is."""

    status_code = 400

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message

    @property
    def extra(self) -> dict[str, object]:
        """Machine-readable details added to the JSON error body (none by default)."""
        return {}


class InvalidInput(TrustlabError):
    """The request is well-formed but its content is not acceptable."""

    status_code = 422


class NotFound(TrustlabError):
    """A named study, participant, station or user does not exist."""

    status_code = 404


class Conflict(TrustlabError):
    """The request contradicts the current state (duplicate code, closed study, wrong order)."""

    status_code = 409


class PermissionDenied(TrustlabError):
    """The caller is known but may not do this."""

    status_code = 403


class NotAuthenticated(TrustlabError):
    """The caller must sign in (or present a valid key/token) first."""

    status_code = 401


class DatabaseUnavailable(TrustlabError):
    """The database cannot be reached; retrying later may succeed."""

    status_code = 503


class TooManyAttempts(TrustlabError):
    """Too many failed attempts in a short time; retry later."""

    status_code = 429
