"""The FastAPI application factory.

``create_app()`` wires settings, database, routers, static files, error handling and security
headers. uvicorn runs it with ``--factory`` (see ``trustlab serve``); tests build one per database.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import APIRouter, FastAPI
from sqlalchemy.exc import DBAPIError
from starlette.routing import BaseRoute
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from app import collector, security
from app.activity import ActivityRecorder
from app.api import (
    health,
    languages,
    session,
    station,
    station_audio,
    station_ws,
    stations,
    tablet,
)
from app.api import studies as studies_api
from app.api.schemas import ERROR_RESPONSES
from app.db import Database
from app.events import PostgresListener
from app.http import BodyLimit, SecurityHeaders, install_error_handlers
from app.online import pages as online_pages
from app.services.analysis_views.fit_runner import FitRunner
from app.services.analysis_views.freshness import FreshnessCache
from app.services.staff import login_throttle
from app.settings import Settings
from app.speech.pool import RecognizerPool
from app.speech.synthesis import Synthesiser
from app.web import (
    accounts,
    admin,
    analysis_pages,
    assets,
    audit_pages,
    auth,
    dashboard,
    docs,
    live,
    monitor_pages,
    participants,
    preview,
    preview_room,
    protocol_editor,
    protocol_sections,
    room,
    tablet_pages,
)
from app.web import stations as station_pages
from app.web import studies as studies_pages
from app.web import study_phases as study_phases_pages
from app.web import study_protocol as study_protocol_pages
from app.web.assets import STATIC_ROOT, VersionedStaticFiles

API_PREFIX = "/api/v1"
MAX_BODY_BYTES = 1024 * 1024
"""Largest request body accepted (a protocol upload is at most 512 KiB); larger ones get 413."""
DASHBOARD_DATA_MAX_AGE = 0.25
"""Seconds for which live dashboards share one computation of their data. Shared only with
requests whose study changes, as counted in this process, it includes, so a reader never misses
its own write; the window bounds what another worker's not-yet-notified write can hide (below the
page's 300 ms refetch delay, which that write's own event triggers)."""
DASHBOARD_DATA_MIN_INTERVAL = 0.2
"""Seconds between the starts of two computations of a study's dashboard data: requests that need
a newer one wait for its turn and share it, so a busy study costs at most five a second however
many dashboards watch it (app/services/analysis_views/freshness.py). A dashboard still redraws well
within a second of an answer (issue 6): 100 ms event coalescing + 300 ms refetch delay + at most
this wait and two computations."""

log = logging.getLogger(__name__)


def _abandon_unfinished_sign_ins(database: Database) -> None:
    """A start: the password checks the last server began will never finish, so they must
    neither count nor be waited for (app.services.staff.login_throttle)."""
    try:
        with database.writing() as db:
            abandoned = login_throttle.abandon_unfinished(db)
            db.commit()
    except DBAPIError as exc:  # down or not migrated yet: requests will say so clearly
        log.warning("unfinished sign-ins were not abandoned at start: %s", exc.orig or exc)
        return
    if abandoned:
        log.info("%d sign-in checks interrupted by the last stop were abandoned", abandoned)


@functools.cache
def _routes() -> tuple[BaseRoute, ...]:
    """Every route of the app, built once per process.

    FastAPI analyses each endpoint's signature and dependencies as its router is included, about
    0.4 s for all of trustlab's. The routes hold nothing of one app (a handler reaches the
    settings and the database through ``request.app.state``), so every app a process creates
    shares them: the test suite creates one per test, over a thousand. They are built without an
    app to ask for ``app.dependency_overrides``, which trustlab does not use."""
    everything = APIRouter()
    api = APIRouter(prefix=API_PREFIX, responses=ERROR_RESPONSES)
    # FastAPI tries routes in the order they were included, at a cost per route tried: the
    # robots' routes, the latency-critical ones (docs/performance.md), come first.
    for resource in (
        station.router,
        station_ws.router,
        station_audio.router,
        session.router,
        studies_api.router,
        studies_api.protocols_router,
        stations.router,
        stations.devices_router,
        tablet.router,
        languages.router,
    ):
        api.include_router(resource)
    everything.include_router(api)
    everything.include_router(health.router)
    for pages in (
        auth.router,
        studies_pages.router,
        participants.router,
        dashboard.router,
        monitor_pages.router,
        analysis_pages.router,
        live.router,
        station_pages.router,
        room.router,
        admin.router,
        protocol_editor.router,
        study_phases_pages.router,
        study_protocol_pages.router,
        protocol_sections.router,
        accounts.router,
        audit_pages.router,
        docs.router,
        tablet_pages.router,
        online_pages.router,
        preview_room.router,  # before preview's /{language}/{number}, which would take it
        preview.router,
        assets.router,
    ):
        everything.include_router(pages)
    return tuple(everything.routes)


def create_app(settings: Settings | None = None) -> FastAPI:
    """A trustlab application for ``settings`` (read from the environment when omitted)."""
    settings = settings or Settings()
    database = Database(
        settings.database_url,
        sqlite_synchronous=settings.sqlite_synchronous,
        background_checkpoints=True,
    )
    activity = ActivityRecorder(database)

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        listener = (
            None if database.is_sqlite else PostgresListener(settings.database_url, database.hub)
        )
        if listener is not None:
            listener.start()
        _abandon_unfinished_sign_ins(database)
        security.dummy_hash()  # now, so that no sign-in with an unknown name waits for it
        database.start_background_work()
        activity.start()
        if settings.freeze_heap_at_start:
            collector.freeze_startup_objects()
        yield
        if settings.freeze_heap_at_start:
            collector.thaw()
        _app.state.analysis_fits.close()
        database.finish_requests()  # its robot work notes devices for the activity's last flush
        activity.stop()
        database.stop_background_work()
        if listener is not None:
            listener.stop()
        database.dispose()

    app = FastAPI(
        title="trustlab",
        version="0.1.0",
        summary="Adaptive-robot trust studies: randomisation, sessions, questionnaires, analysis.",
        openapi_url=f"{API_PREFIX}/openapi.json",
        docs_url=None,
        redoc_url=None,
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.database = database
    app.state.activity = activity
    app.state.synthesiser = Synthesiser()
    app.state.recognizers = RecognizerPool()
    app.state.analysis_fits = FitRunner(
        database, processes=settings.analysis_processes, wait=settings.analysis_wait_seconds
    )
    app.state.dashboard_data = FreshnessCache(
        max_age=DASHBOARD_DATA_MAX_AGE, min_interval=DASHBOARD_DATA_MIN_INTERVAL
    )

    app.router.routes.extend(_routes())
    app.mount("/static", VersionedStaticFiles(directory=STATIC_ROOT), name="static")

    install_error_handlers(app)
    app.add_middleware(BodyLimit, limit=MAX_BODY_BYTES)
    app.add_middleware(SecurityHeaders)
    if settings.trusted_proxies:  # outermost: everything after sees the client's own address
        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=list(settings.trusted_proxies))
    return app
