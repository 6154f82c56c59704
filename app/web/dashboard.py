"""The live study dashboard: trust by session and adaptation curves, redrawn as data arrives."""

from __future__ import annotations

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
def dashboard_data(request: Request, db: SessionDep, user: CurrentUser, name: str) -> Response:
    """The figures' data (Plotly payloads), blinded for roles that may not see conditions.

    Dashboards share one computation, and its encoded body, whenever it includes every change of
    the study this process had counted when they asked and is at most ``DASHBOARD_DATA_MAX_AGE``
    old; a newer one starts at most every ``DASHBOARD_DATA_MIN_INTERVAL`` (app/main.py,
    app/services/freshness.py).
    """
    plan = dashboard.plan_for(studies.get_study(db, name), Actor.of_user(user))
    shared: FreshnessCache[bytes] = request.app.state.dashboard_data
    hub: EventHub = request.app.state.database.hub
    topic = stations.study_topic(plan.study_id)

    # The request's read transaction began with its sign-in check. End it before asking: a
    # computation's snapshot must be younger than the change count and clock the cache reads
    # first, and a request waiting for a computation should hold no connection meanwhile.
    db.rollback()
    body = shared.get(
        plan.key,
        lambda: dashboard.encode(dashboard.compute(db, plan)),
        version=lambda: hub.version(topic),
    )
    return Response(body, media_type="application/json")
