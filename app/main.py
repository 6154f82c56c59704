"""The FastAPI application factory.

``create_app()`` wires settings, database, routers, static files, error handling and security
headers. uvicorn runs it with ``--factory`` (see ``trustlab serve``); tests build one per database.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import APIRouter, FastAPI
from fastapi.staticfiles import StaticFiles

from app.api import health
from app.api import studies as studies_api
from app.db import Database
from app.http import SecurityHeaders, install_error_handlers
from app.settings import REPO_ROOT, Settings
from app.web import admin, auth, docs
from app.web import studies as studies_pages

API_PREFIX = "/api/v1"


def create_app(settings: Settings | None = None) -> FastAPI:
    """A trustlab application for ``settings`` (read from the environment when omitted)."""
    settings = settings or Settings()
    database = Database(settings.database_url, sqlite_synchronous=settings.sqlite_synchronous)

    @asynccontextmanager
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        yield
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

    api = APIRouter(prefix=API_PREFIX)
    api.include_router(studies_api.router)
    app.include_router(api)
    app.include_router(health.router)
    for pages in (auth.router, studies_pages.router, admin.router, docs.router):
        app.include_router(pages)
    app.mount("/static", StaticFiles(directory=REPO_ROOT / "static"), name="static")

    install_error_handlers(app)
    app.add_middleware(SecurityHeaders)
    return app
