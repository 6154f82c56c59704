"""Live streams for signed-in pages: a study's changes and a station's changes.

Streams are long-lived, so they check the user and the name in a short unit of work and then hold
no database connection while they wait for events; each ends when its login does. Each carries
the account's scope (app.services.privacy.sites): an account limited to some sites hears nothing of
another site's participants, and a station seating one does not exist for it, as on every other
route of the station.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Query, Request
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from app.db import Database
from app.deps import OneHopRouter, StreamingLogin
from app.errors import NotFound
from app.services import studies, topics
from app.services.audit import Actor
from app.services.privacy import sites
from app.services.sessions import stations
from app.services.staff import users
from app.web.streams import event_stream

ROOM_EVENT = "room"
"""The SSE event of the console's room panel (templates/_room_panel.html listens for it)."""

Since = Annotated[
    float | None,
    Query(
        allow_inf_nan=False,
        description="When the page began to read (seconds since the epoch): changes since then "
        "are sent at once. Absent: from now on.",
    ),
]

router = OneHopRouter(tags=["pages"], include_in_schema=False)


@router.get("/studies/{name}/events")
async def study_events(
    request: Request, name: str, login: StreamingLogin, since: Since = None
) -> Response:
    """Server-sent events whenever the study's data changes (answers, questionnaires, sessions),
    starting with those since ``since``: when the page that listens began to read."""
    database: Database = request.app.state.database

    def topic() -> str:
        with database.read_session() as db:
            return topics.study_topic(studies.get_study(db, name).id)

    return event_stream(
        database.hub,
        [await run_in_threadpool(topic)],
        scope=sites.Scope.of(Actor.of_user(login.user)),
        ends_with=users.login_topic(login.id),
        since=since,
    )


@router.get("/stations/{name}/events")
async def station_events(
    request: Request, name: str, login: StreamingLogin, since: Since = None
) -> Response:
    """Server-sent events whenever the station changes (for its operator console): ``changed``,
    and ``room`` when the room client reports where the participant is (the room panel); from
    ``since`` on, as the study's."""
    database: Database = request.app.state.database
    actor = Actor.of_user(login.user)

    def station_id() -> int:
        with database.read_session() as db:
            station = stations.get_station(db, name)
            if sites.station_hidden(db, station, actor):
                raise NotFound(f"no station named {name!r}")
            return station.id

    found = await run_in_threadpool(station_id)
    return event_stream(
        database.hub,
        [topics.station_topic_of(found)],
        scope=sites.Scope.of(actor),
        ends_with=users.login_topic(login.id),
        named={topics.room_topic_of(found): ROOM_EVENT},
        since=since,
    )
