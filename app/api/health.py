"""Liveness and database reachability, for load balancers and docker-compose."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from app.api.schemas import Health
from app.deps import DatabaseDep
from app.errors import DatabaseUnavailable

router = APIRouter(tags=["health"])


@router.get("/api/v1/ping")
def ping() -> dict[str, bool]:
    """A no-op: answers without touching the database (the baseline of bench/api.py)."""
    return {"pong": True}


@router.get("/healthz", response_model=Health, responses={503: {"model": Health}})
def healthz(database: DatabaseDep) -> JSONResponse:
    """200 when the database answers, 503 with the reason when it does not."""
    try:
        database.ping()
    except DatabaseUnavailable as exc:
        body = Health(status="unavailable", database=exc.message)
        return JSONResponse(body.model_dump(), status_code=503)
    return JSONResponse(Health(status="ok", database="ok").model_dump())
