"""The live study dashboard: trust by session and adaptation curves, redrawn as data arrives."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response

from app.deps import CurrentUser, SessionDep
from app.events import EventHub
from app.services import dashboard, stations, studies
from app.services.audit import Actor
from app.services.freshness import FreshnessCache
from app.web.templating import render

router = APIRouter(tags=["pages"], include_in_schema=False)


@router.get("/studies/{name}/dashboard")
def dashboard_page(request: Request, db: SessionDep, user: CurrentUser, name: str) -> Response:
    """The page; its figures come from the JSON below and refresh on every change."""
    study = studies.get_study(db, name)
    return render(
        request,
        "dashboard.html",
        {
            "study": study,
            "protocol": studies.protocol_of(study),
            "items": dashboard.session_items(studies.protocol_of(study)),
        },
    )


@router.get("/studies/{name}/dashboard.json")
def dashboard_data(
    request: Request, db: SessionDep, user: CurrentUser, name: str
) -> dict[str, Any]:
    """The figures' data (Plotly payloads), blinded for roles that may not see conditions.

    Dashboards asking at nearly the same moment, with no change of the study in between, share
    one computation (``DASHBOARD_DATA_MAX_AGE`` in app/main.py, app/services/freshness.py).
    """
    study = studies.get_study(db, name)
    actor = Actor.of_user(user)
    shared: FreshnessCache[dict[str, Any]] = request.app.state.dashboard_data
    hub: EventHub = request.app.state.database.hub
    changes = hub.version(stations.study_topic(study.id))
    return shared.get(
        (dashboard.data_key(study, actor), changes),
        lambda: dashboard.dashboard_data(db, study=study, actor=actor),
    )
