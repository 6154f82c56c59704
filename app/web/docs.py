"""The interactive API reference, served from local assets (labs often have no internet)."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import Response

from app.deps import OneHopRouter
from app.web.templating import render

router = OneHopRouter(tags=["pages"], include_in_schema=False)


@router.get("/api/v1/docs")
def api_docs(request: Request) -> Response:
    """Swagger UI over /api/v1/openapi.json."""
    return render(request, "api_docs.html")
