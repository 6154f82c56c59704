"""A robot's request as one unit of work: authenticate its key, run the operation, commit, close.

All of it happens in a single hop to a worker thread, after admission (app.deps), so a request never
holds a connection or SQLite's write lock while waiting for a thread, and the write lock is held
only for the transaction itself. On SQLite robots' writes take turns on one writer thread
(app.db.WriterThread); everything else goes to the shared thread pool. The REST routes and the
station WebSocket both come through here, so a robot gets the same behaviour whichever transport
it speaks.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, TypeVar

from fastapi import Depends
from fastapi.responses import Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel
from sqlalchemy.orm import Session
from starlette.types import ASGIApp

from app.activity import ActivityRecorder
from app.db import Database
from app.errors import NotAuthenticated
from app.services.audit import Actor
from app.services.sessions import stations
from app.services.sessions.step_store import DeviceSeat
from app.tables import ActorKind

T = TypeVar("T")

_bearer = HTTPBearer(
    auto_error=False,
    scheme_name="DeviceKey",
    description="A station's device key: `Authorization: Bearer tlk_…`.",
)


async def device_key(
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> str:
    """The device key of the request (no database work: that happens in :func:`as_device`)."""
    key = credentials.credentials if credentials is not None else ""
    # Refused here, before the body is validated, when it cannot be a device key at all: a
    # participant's or a forged token learns nothing about the route's body from a 422.
    if not key.startswith(stations.KEY_PREFIX) or len(key) > stations.KEY_MAX_LENGTH:
        raise NotAuthenticated("send the device key as the header 'Authorization: Bearer tlk_…'")
    return key


DeviceKey = Annotated[str, Depends(device_key)]


def device_actor(device: DeviceSeat) -> Actor:
    """How a device appears in the audit log and the step log."""
    return Actor(ActorKind.DEVICE, device.actor_name)


def _work(
    database: Database,
    activity: ActivityRecorder | None,
    key: str,
    write: bool,
    op: Callable[[Session, DeviceSeat], T],
) -> T:
    with database.write_session() if write else database.read_session() as db:
        device = stations.authenticate_seat(db, key=key)
        if activity is not None:
            activity.note_device(device.device_id)
        return op(db, device)


async def as_device(
    app: ASGIApp, key: str, *, write: bool, op: Callable[[Session, DeviceSeat], T]
) -> T:
    """Run ``op(db, device)`` for the device holding ``key``, as one admitted unit of work."""
    state = app.state  # type: ignore[attr-defined]
    database: Database = state.database
    activity: ActivityRecorder | None = getattr(state, "activity", None)
    async with database.admission():
        return await database.run_unit_of_work(
            _work, database, activity, key, write, op, write=write
        )


class ModelResponse(Response):
    """A robot route's body, serialised straight from the model the operation built.

    A route that returns its model lets FastAPI validate it against the response model again and
    then serialise it: on the hot robot routes that second pass cost about as much CPU as the JSON
    itself (docs/performance.md). The operations build these models from typed service results,
    so the check adds nothing; the routes still declare ``response_model`` for the OpenAPI
    document, and the schema tests (tests/app/test_api_fuzz.py) check the bodies against it.
    """

    media_type = "application/json"

    def __init__(self, model: BaseModel, status_code: int = 200) -> None:
        super().__init__(model.__pydantic_serializer__.to_json(model), status_code=status_code)
