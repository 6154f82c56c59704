"""Pre-registrations written by ``trustlab prereg``, as the audit log records them.

The bundle (prereg.json, .md, .html and the protocol) is a set of files the PI attaches to an
OSF registration; the audit log keeps, for each one written, the SHA-256 of its prereg.json,
its analysis plan (:func:`analysis.prereg.analysis_plan`) and how many participants had been
enrolled and had answered when it was written (:func:`analysis.prereg.data_at_registration`).
:func:`latest` gives the newest, so every report of the study (the command line's and the
download) checks its analyses against the registration without being told where the file went;
``trustlab export --prereg FILE`` checks against a given file instead (e.g. the one on OSF).
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.tables import AuditEvent, Study

__all__ = ["ACTION", "latest"]

ACTION = "prereg.written"
"""The audit action of a registration written by ``trustlab prereg``."""


def latest(db: Session, study: Study) -> tuple[dict[str, Any] | None, str]:
    """The newest registration of ``study`` (its ``created_at``, ``data_at_registration`` and
    analysis plan) and where it is from, or ``(None, "")``."""
    event = db.scalars(
        select(AuditEvent)
        .where(AuditEvent.study_id == study.id, AuditEvent.action == ACTION)
        .order_by(AuditEvent.id.desc())
        .limit(1)
    ).first()
    if event is None or not isinstance(event.details.get("registration"), dict):
        return None, ""
    digest = str(event.details.get("sha256", ""))
    return event.details["registration"], (
        f"written by trustlab prereg, prereg.json SHA-256 {digest[:16]}…, in the audit log"
    )
