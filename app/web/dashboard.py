"""The live study dashboard: trust by session and adaptation curves, redrawn as data arrives."""

from __future__ import annotations

import functools

from fastapi import APIRouter, Request
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from analysis.population import source_label
from app.db import Database
from app.deps import CurrentUser, SessionDep, SiteFilter, StreamingUser
from app.services import blinding, studies, topics
from app.services.analysis_views import dashboard
from app.services.analysis_views.freshness import FreshnessCache
from app.services.audit import Actor
from app.services.privacy import sites
from app.services.sessions import learners
from app.web.monitor_pages import monitor_context
from app.web.templating import render

router = APIRouter(tags=["pages"], include_in_schema=False)


@router.get("/studies/{name}/dashboard")
def dashboard_page(
    request: Request, db: SessionDep, user: CurrentUser, name: str, site: SiteFilter = ""
) -> Response:
    """The page; its figures come from the JSON below and refresh on every change
    (``?site=``: one site's participants only)."""
    study = studies.get_study(db, name)
    protocol = studies.protocol_of(study)
    actor = Actor.of_user(user)
    sites.narrowed(actor, site, study)  # refuses a site the study lacks or the user may not see
    shown = blinding.shows_learners(study)
    # As enrolment resolves them (it does not read settings.checkpoint_dir either).
    priors = learners.priors_in_use(protocol) if shown else []
    population = next((row.population for row in priors if row.population), None)
    uniform = all(row.start is None or max(row.start) - min(row.start) < 1e-9 for row in priors)
    return render(
        request,
        "dashboard.html",
        {
            "study": study,
            "protocol": protocol,
            "items": dashboard.session_items(protocol),
            "learners_hidden": "" if shown else blinding.LEARNERS_SEALED,
            "priors": priors,
            "population": population,
            "uniform_start": uniform,
            "population_source": source_label(population["source"]) if population else "",
            "site": site.strip(),
            "site_choices": sites.choices(protocol, actor),
            "panels": monitor_context(db, study, sites.narrowed(actor, site, study)),
        },
    )


@router.get("/studies/{name}/dashboard.json")
async def dashboard_data(
    request: Request, user: StreamingUser, name: str, site: SiteFilter = ""
) -> Response:
    """The figures' data (Plotly payloads), blinded for roles that may not see conditions.

    Dashboards share one computation, and its encoded body, whenever it includes every change of
    the study this process had counted when they asked and is at most ``DASHBOARD_DATA_MAX_AGE``
    old; a newer one starts at most every ``DASHBOARD_DATA_MIN_INTERVAL`` (app/main.py,
    app/services/analysis_views/freshness.py). Waiting for one holds no admission slot, connection
    or snapshot: only the reads and the computation itself are admitted like any request's database
    work (while a dashboard waited holding a slot, other requests queued behind it).
    """
    database: Database = request.app.state.database
    actor = Actor.of_user(user)

    def plan_now() -> dashboard.Plan:
        with database.read_session() as db:
            study = studies.get_study(db, name)
            return dashboard.plan_for(study, sites.narrowed(actor, site, study))

    async with database.admission():
        plan = await run_in_threadpool(plan_now)
    shared: FreshnessCache[bytes] = request.app.state.dashboard_data
    topic = topics.study_topic(plan.study_id)

    def compute() -> bytes:
        # A fresh snapshot, taken after the cache read the change count and the clock.
        with database.admitted_from_thread(), database.read_session() as db:
            return dashboard.encode(dashboard.compute(db, plan))

    body = await run_in_threadpool(
        functools.partial(
            shared.get, plan.key, compute, version=lambda: database.hub.version(topic)
        )
    )
    return Response(body, media_type="application/json")
