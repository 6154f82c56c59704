"""Who did what: the actor of a change and the append-only audit log."""

from __future__ import annotations

import getpass
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session

from app.tables import ActorKind, AuditEvent, Role, User


@dataclass(frozen=True)
class Actor:
    """The person, device or process behind a change, as the audit log names it."""

    kind: ActorKind
    name: str
    role: Role | None = None
    sites: frozenset[str] | None = None
    """The only sites whose participants this actor may see and act on (app.services.privacy.sites);
    None: every site."""

    @classmethod
    def of_user(cls, user: User) -> Actor:
        """A signed-in dashboard user, limited to their account's sites unless an admin."""
        role = Role(user.role)
        limited = user.sites is not None and role != Role.ADMIN
        return cls(
            ActorKind.USER, user.username, role, frozenset(user.sites or ()) if limited else None
        )

    @classmethod
    def command_line(cls) -> Actor:
        """Whoever runs the ``trustlab`` command on the server (trusted like an admin)."""
        try:
            name = getpass.getuser()
        except (KeyError, OSError):
            name = "unknown"
        return cls(ActorKind.CLI, name[:64], Role.ADMIN)

    @classmethod
    def system(cls, what: str = "trustlab") -> Actor:
        """trustlab itself (first start, migrations)."""
        return cls(ActorKind.SYSTEM, what, Role.ADMIN)

    @property
    def sees_conditions(self) -> bool:
        """Whether this actor may see real condition labels in a blinded study."""
        return self.role in (Role.ADMIN, Role.ANALYST)


def record(
    db: Session,
    *,
    actor: Actor,
    action: str,
    study_id: int | None = None,
    subject: str = "",
    details: dict[str, Any] | None = None,
) -> AuditEvent:
    """Append one event in the caller's transaction (it commits or rolls back with the change)."""
    event = AuditEvent(
        actor_kind=actor.kind,
        actor=actor.name,
        action=action,
        study_id=study_id,
        subject=subject,
        details=details or {},
    )
    db.add(event)
    return event
