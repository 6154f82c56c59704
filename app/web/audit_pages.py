"""The audit log for admins: browse with filters, export as CSV.

Both leave out what older entries recorded of an allocation's place in its sequence until its study
discloses it (app.services.blinding.allocation_disclosed): before, the block numbers and sizes made
the rest of each block predictable."""

from __future__ import annotations

import json
from typing import Any

import pandas as pd
from fastapi import Request
from fastapi.responses import Response
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

from analysis.exports import csv_bytes
from app.deps import AdminUser, OneHopRouter, SessionDep
from app.inputs import PageNumber
from app.services import audit, blinding
from app.services.audit import Actor
from app.tables import AuditEvent, Study
from app.web.templating import render

router = OneHopRouter(tags=["pages"], include_in_schema=False)

PAGE_SIZE = 100

AUDIT_CSV_COLUMNS = (
    "id",
    "occurred_at",
    "actor_kind",
    "actor",
    "action",
    "study",
    "subject",
    "details",
)
"""Columns of ``/admin/audit.csv``."""


def detail_pairs(details: object) -> list[tuple[str, str]]:
    """An audit entry's details as (label, value) pairs to read at a glance, not JSON to parse:
    keys in order, ``snake_case`` as words, lists joined, nested mappings as ``key value``."""
    if not isinstance(details, dict):
        return [] if details in (None, "") else [("details", _detail_value(details))]
    return [(str(key).replace("_", " "), _detail_value(value)) for key, value in details.items()]


def _detail_value(value: object) -> str:
    if value is None or value == "":
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, list | tuple):
        return ", ".join(_detail_value(item) for item in value) or "none"
    if isinstance(value, dict):
        return "; ".join(f"{key} {_detail_value(item)}" for key, item in value.items()) or "none"
    return str(value)


def _disclosing_studies(db: Session) -> set[int]:
    """The studies whose allocations' places in the sequence may be shown
    (app.services.blinding.allocation_disclosed): older audit entries recorded them."""
    return {study.id for study in db.scalars(select(Study)) if blinding.allocation_disclosed(study)}


def _shown_details(event: AuditEvent, disclosing: set[int]) -> dict[str, Any]:
    return blinding.visible_details(event.details, disclosed=event.study_id in disclosing)


def _filtered(study: str, action: str, actor: str) -> Select[AuditEvent, str]:
    query: Select[AuditEvent, str] = select(AuditEvent, Study.name).outerjoin(
        Study, Study.id == AuditEvent.study_id
    )
    if study:
        query = query.where(Study.name == study)
    if action:
        query = query.where(AuditEvent.action.startswith(action))
    if actor:
        query = query.where(AuditEvent.actor.startswith(actor))
    return query


@router.get("/admin/audit")
def audit_log(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    study: str = "",
    action: str = "",
    actor: str = "",
    page: PageNumber = 1,
) -> Response:
    """Every recorded change, newest first."""
    page = max(page, 1)
    query = _filtered(study, action, actor)
    total = db.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = db.execute(
        query.order_by(AuditEvent.id.desc()).limit(PAGE_SIZE).offset((page - 1) * PAGE_SIZE)
    ).all()
    disclosing = _disclosing_studies(db)
    return render(
        request,
        "audit.html",
        {
            "rows": [
                (event, name, detail_pairs(_shown_details(event, disclosing)))
                for event, name in rows
            ],
            "total": total,
            "page": page,
            "pages": max(1, -(-total // PAGE_SIZE)),
            "filters": {"study": study, "action": action, "actor": actor},
            "studies": db.scalars(select(Study.name).order_by(Study.name)).all(),
        },
    )


@router.get("/admin/audit.csv")
def audit_export(
    request: Request,
    db: SessionDep,
    admin: AdminUser,
    study: str = "",
    action: str = "",
    actor: str = "",
) -> Response:
    """The (filtered) audit log as CSV, oldest first; the export itself is audited.

    Written by :func:`analysis.exports.csv_bytes` like every CSV, so an actor or subject that a
    spreadsheet would run as a formula (the login name of whoever ran a command, say) stays text.
    """
    disclosing = _disclosing_studies(db)
    rows = [
        (
            event.id,
            event.occurred_at.isoformat(),
            event.actor_kind,
            event.actor,
            event.action,
            study_name or "",
            event.subject,
            json.dumps(_shown_details(event, disclosing), sort_keys=True),
        )
        for event, study_name in db.execute(_filtered(study, action, actor).order_by(AuditEvent.id))
    ]
    table = pd.DataFrame(rows, columns=list(AUDIT_CSV_COLUMNS))
    with request.app.state.database.write_session() as writer_db:
        audit.record(
            writer_db,
            actor=Actor.of_user(admin),
            action="audit.exported",
            details={"study": study, "action": action, "actor": actor},
        )
        writer_db.commit()
    return Response(
        csv_bytes(table),
        media_type="text/csv",
        headers={
            "Content-Disposition": 'attachment; filename="trustlab-audit.csv"',
            "Cache-Control": "no-store",
        },
    )
