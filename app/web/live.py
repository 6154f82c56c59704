"""Live streams for signed-in pages: a study's changes and a station's changes.

Streams are long-lived, so they check the user and the name in a short unit of work and then hold
no database connection while they wait for events; each ends when its login does.
"""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from app.db import Database
from app.deps import OneHopRouter, StreamingLogin
from app.services import stations, studies, users
from app.web.streams import event_stream

router = OneHopRouter(tags=["pages"], include_in_schema=False)


@router.get("/studies/{name}/events")
async def study_events(request: Request, name: str, login: StreamingLogin) -> Response:
    """Server-sent events whenever the study's data changes (answers, questionnaires, sessions)."""
    database: Database = request.app.state.database

    def topic() -> str:
        with database.read_session() as db:
            return stations.study_topic(studies.get_study(db, name).id)

    return event_stream(
        database.hub, [await run_in_threadpool(topic)], ends_with=users.login_topic(login.id)
    )


@router.get("/stations/{name}/events")
async def station_events(request: Request, name: str, login: StreamingLogin) -> Response:
    """Server-sent events whenever the station changes (for its operator console)."""
    database: Database = request.app.state.database

    def topic() -> str:
        with database.read_session() as db:
            return stations.station_topic(stations.get_station(db, name))

    return event_stream(
        database.hub, [await run_in_threadpool(topic)], ends_with=users.login_topic(login.id)
    )
