"""The dashboard's online and data-quality panels: one fragment, drawn into the dashboard page and
redrawn by htmx whenever the study changes (and every 30 seconds, since "online now" and "expired"
also change with the clock alone)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.deps import CurrentUser, SessionDep, SiteFilter
from app.online.monitor import online_monitor
from app.services import studies
from app.services.audit import Actor
from app.services.participants import data_quality
from app.services.privacy import sites
from app.services.privacy.sites import Scope
from app.tables import Participant, Study, utcnow
from app.web.templating import render

router = APIRouter(tags=["pages"], include_in_schema=False)


def monitor_context(db: Session, study: Study, actor: Actor) -> dict[str, Any]:
    """What the panels show to ``actor`` (its sites only): the online figures of an online
    study, and every flagged participant of a study with data-quality rules."""
    protocol = studies.protocol_of(study)
    scope = Scope.of(actor)
    monitor = (
        online_monitor(db, study=study, protocol=protocol, scope=scope, now=utcnow())
        if protocol.online is not None
        else None
    )
    rules = protocol.quality_rules()
    flagged: list[tuple[str, list[str], bool]] = []
    if rules is not None:
        whom = (
            (Participant.study_id == study.id)
            & scope.where()
            & Participant.pilot.is_(False)
            & Participant.erased_at.is_(None)
        )
        quality = data_quality.quality_by_participant(db, protocol, whom)
        named = select(Participant.id, Participant.code).where(whom)
        codes = {row.id: row.code for row in db.execute(named)}
        flagged = sorted(
            (codes[pid], found.reasons(), bool(set(found.flags) & set(rules.exclude)))
            for pid, found in quality.items()
            if found.flags
        )
    return {
        "study": study,
        "protocol": protocol,
        "monitor": monitor,
        "quality_rules": rules,
        "flagged": flagged,
    }


@router.get("/studies/{name}/monitor")
def monitor_panels(
    request: Request, db: SessionDep, user: CurrentUser, name: str, site: SiteFilter = ""
) -> Response:
    """The panels alone (``?site=``: one site's participants), for the dashboard to redraw."""
    study = studies.get_study(db, name)
    actor = sites.narrowed(Actor.of_user(user), site, study)
    return render(request, "_monitor.html", monitor_context(db, study, actor))
